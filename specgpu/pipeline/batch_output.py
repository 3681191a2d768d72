"""Reading a ``specgpu batch`` output (format ``specgpu.batch``), checked as a recording is read.

A batch output is laid out like a recording (:mod:`specgpu.io.recording`: its outputs along ``time``, one chunk per
sequence, CRC32C checksums) but it is filled in any order and may be resumed: a sequence holds results only once
its ``done`` mark is set. :func:`open_batch_output` checks the format and the arrays and gives a
:class:`BatchOutput`, whose :meth:`~BatchOutput.read` refuses, in one line naming the output, the array and the
sequence, a sequence the batch has not computed yet, a done sequence whose chunk is missing and a corrupt chunk
(zarr itself would give fill values for the first two).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from specgpu.io.recording import Recording, open_zarr_group
from specgpu.pipeline.batch import BATCH_FORMAT, BATCH_OUTPUTS, BATCH_VERSION, _done_flags

__all__ = ["BatchOutput", "open_batch_output"]


@dataclass
class BatchOutput(Recording):
    """A batch output opened and checked: every sequence of its source has a step along ``time``; ``done`` marks
    the computed ones."""

    done: np.ndarray

    @property
    def sequences(self) -> int:
        """The sequences of the source (computed or not)."""
        return int(self.done.size)

    @property
    def pending(self) -> list[int]:
        """The sequences the batch has not computed yet (run it again to resume them)."""
        return [int(i) for i in np.flatnonzero(self.done == 0)]

    def read(self, name: str, index) -> np.ndarray:
        """Sequence(s) ``index`` of array ``name``, as :meth:`Recording.read`; a sequence not computed yet is a
        one-line error naming the output, array and sequence."""
        if name in self.attrs.get("outputs", []):
            first = index[0] if isinstance(index, tuple) else index
            try:
                wanted = range(self.sequences)[first]
            except (TypeError, IndexError):  # an index zarr itself refuses or a fancy one: every sequence
                wanted = range(self.sequences)
            pending = [i for i in ([wanted] if isinstance(wanted, int) else wanted) if not self.done[i]]
            if pending:
                more = f" (and {len(pending) - 1} more)" if len(pending) > 1 else ""
                raise ValueError(f"{self.path}/{name}: sequence {pending[0]}{more} is not computed yet (the batch "
                                 "stopped before it; run the same specgpu batch again to resume it)")
        return super().read(name, index)

    def missing(self, name: str) -> list[int]:
        """The computed sequences whose chunk of array ``name`` is not on disk (empty when it is whole)."""
        return [i for i in super().missing(name) if self.done[i]]


def open_batch_output(path: str | os.PathLike[str]) -> BatchOutput:
    """Open a ``specgpu batch`` output and check its format, version and arrays.

    Parameters
    ----------
    path : str or os.PathLike
        The output folder (``OUT.zarr``).

    Returns
    -------
    BatchOutput
        Its attributes, arrays and ``done`` marks (a mark that cannot be read counts as not done).

    Raises
    ------
    FileNotFoundError
        The folder does not exist.
    ValueError
        One line naming the folder: not a zarr v3 group, not a batch output or of another version, bad outputs,
        an array missing or shorter than the sequences.
    """
    path = Path(path)
    group, attrs = open_zarr_group(path, "batch output", BATCH_FORMAT, BATCH_VERSION)
    outputs = attrs.get("outputs")
    if not isinstance(outputs, list) or not outputs or not all(o in BATCH_OUTPUTS for o in outputs):
        raise ValueError(f"{path}: outputs must be a list of {', '.join(BATCH_OUTPUTS)}, got {str(outputs)[:80]}")
    if "done" not in group:
        raise ValueError(f"{path}: the 'done' array is missing")
    done = _done_flags(group["done"])
    for name in outputs:
        if name not in group:
            raise ValueError(f"{path}: the {name!r} array is missing")
        if group[name].shape[0] != done.size:
            raise ValueError(f"{path}/{name}: holds {group[name].shape[0]} sequences but 'done' marks {done.size}")
    return BatchOutput(path, attrs, group, done)
