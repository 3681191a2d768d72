"""A ``specgpu batch`` output (format ``specgpu.batch``): made (:func:`create_output`), and read back checked as a
recording is read (:func:`open_batch_output`).

A batch output is laid out like a recording (:mod:`specgpu.io.recording`: its outputs along ``time``, one chunk per
sequence, CRC32C checksums) but it is filled in any order and may be resumed: a sequence holds results only once
its ``done`` mark is set. Its arrays (:func:`output_arrays`): the outputs asked for, float32 with NaN where a value
is not known (``cube``, ``XYZ``, ``Lab``, ``dE``; the uncertainty outputs ``sigma``, each output's standard
deviation then their RMS, ``sigma_rms``, that RMS alone, and ``dE_sigma``, the first-order CIEDE2000 standard
deviation), and ``mask`` (time, y, x) uint8, the decoder's bits (:class:`specgpu.core.mask.Mask`) saying why a
pixel is NaN (an output made before the mask was written has none). :func:`open_batch_output` checks the format and
each array's dtype, shape and channels and gives a :class:`BatchOutput`, whose :meth:`~BatchOutput.read` refuses,
in one line naming the output, the array and the sequence, a sequence the batch has not computed yet, a done
sequence whose chunk is missing and a corrupt chunk (zarr itself would give fill values for the first two).
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from specgpu.core.locks import pid_alive
from specgpu.core.mask import Mask
from specgpu.io.chunks import checksum_codecs
from specgpu.io.recording import CHANNELS, Recording, open_zarr_group

__all__ = ["BATCH_FORMAT", "BATCH_OUTPUTS", "BATCH_VERSION", "BatchOutput", "open_batch_output"]

BATCH_FORMAT = "specgpu.batch"
BATCH_VERSION = 2  # 2: the source identified by content, every result-changing option in the identity
#: What a batch can write per sequence (:func:`specgpu.pipeline.decoder_outputs.outputs_for` names them alike).
BATCH_OUTPUTS = ("cube", "XYZ", "Lab", "dE", "sigma", "sigma_rms", "dE_sigma")
#: The outputs whose values depend on the illuminant, observer and integration of XYZ.
COLOUR_OUTPUTS = ("XYZ", "Lab", "dE", "dE_sigma")


def done_flags(done) -> np.ndarray:
    """The ``done`` marks, one chunk at a time: a mark that cannot be read (cut by a crash) counts as not done, so
    its sequence is computed again instead of the whole output being refused."""
    try:
        return np.asarray(done[:])
    except Exception:  # noqa: BLE001 (a damaged chunk: read the others one by one)
        flags = np.zeros(done.shape[0], np.uint8)
        for i in range(done.shape[0]):
            try:
                flags[i] = done[i]
            except Exception:  # noqa: BLE001
                flags[i] = 0
        return flags


def creation_name(out: Path, pid: int | None = None) -> Path:
    """The temporary name ``out`` is created under by process ``pid`` (this one by default)."""
    return out.parent / f".{out.name}.{os.getpid() if pid is None else pid}.creating"


def remove_dead_creations(out: Path) -> None:
    """Remove the half-made outputs (``.OUT.<pid>.creating``) of batches killed while creating ``out``."""
    prefix = f".{out.name}."
    try:
        entries = list(os.scandir(out.parent))
    except OSError:
        return
    for entry in entries:
        if entry.name.startswith(prefix) and entry.name.endswith(".creating"):
            pid = entry.name[len(prefix):-len(".creating")]
            if pid.isdigit() and not pid_alive(int(pid)):
                shutil.rmtree(entry.path, ignore_errors=True)


def unfinished_creation(out: Path) -> bool:
    """A batch output whose creation was cut before its ``done`` array existed (an older specgpu created it in
    place): no sequence was computed in it."""
    try:
        doc = json.loads((out / "zarr.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    attrs = doc.get("attributes", {}) if isinstance(doc, dict) else {}
    return (isinstance(attrs, dict) and attrs.get("format") == BATCH_FORMAT and attrs.get("status") == "running"
            and not (out / "done" / "zarr.json").exists())


def output_arrays(plan, outputs, method, h: int, w: int) -> dict[str, tuple]:
    """Per output array of a new batch output (``outputs``, and the ``mask``): its shape after ``time``, dtype,
    dimension names after ``time``, fill value and attributes (channel names, units, what NaN means)."""
    B = plan.A.shape[0]
    reflectance = plan.output == "reflectance"
    units = "reflectance factor" if reflectance else f"the plan's {plan.output} outputs"
    unknown = "NaN where the value is not known (the mask array's bits say why)"
    arrays = {}
    for name in outputs:
        if name == "cube":
            arrays[name] = ((h, w, B), ("y", "x", "wavelength" if reflectance else "output"),
                            {"wavelength_units": "nm"} if reflectance else
                            {"channels": list(map(str, plan.output_labels))})
        elif name in CHANNELS:
            arrays[name] = ((h, w, 3), ("y", "x", f"{name}_channel"), {"channels": list(CHANNELS[name])})
        elif name == "sigma":
            arrays[name] = ((h, w, B + 1), ("y", "x", "sigma_channel"),
                            {"channels": sigma_channels(plan.output_labels), "units": units, "missing": unknown,
                             "long_name": "standard deviation of each output of the cube, then their RMS"})
        elif name == "sigma_rms":
            arrays[name] = ((h, w), ("y", "x"), {"units": units, "missing": unknown,
                                                 "long_name": "RMS over the cube's outputs of their standard "
                                                              "deviation"})
        elif name == "dE_sigma":
            arrays[name] = ((h, w), ("y", "x"), {"units": "CIEDE2000", "missing": unknown,
                                                 "long_name": "first-order standard deviation of CIEDE2000 at the "
                                                              "pixel's XYZ"})
        else:
            arrays[name] = ((h, w), ("y", "x"), {"method": method})
    out = {name: (tail, "float32", dims, np.nan, attrs) for name, (tail, dims, attrs) in arrays.items()}
    out["mask"] = ((h, w), "uint8", ("y", "x"), 0,
                   {"flags": {flag.name: int(flag) for flag in Mask},
                    "long_name": "why a pixel's values are NaN: saturated, not finite, seen outside the field, "
                                 "inconsistent frames; layer: decoded with an object's own motion"})
    return out


def sigma_channels(labels) -> list[str]:
    """The ``sigma`` array's channel names: ``sigma_<label>`` per plan output, then ``sigma_rms``."""
    return [f"sigma_{label}" for label in labels] + ["sigma_rms"]


def create_output(out: Path, identity: dict, plan, method, outputs, source, n, h, w) -> None:
    """The output group made whole under a temporary name beside ``out`` (the arrays of :func:`output_arrays`),
    then renamed to it: a batch killed while creating it leaves no ``out`` (its temporary is removed by the next
    run)."""
    import zarr

    tmp = creation_name(out)
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        group = zarr.open_group(str(tmp), mode="w-", zarr_format=3)
        group.update_attributes({**identity, "plan_method": plan.method, "status": "running"})  # one write
        for name, (tail, dtype, dims, fill, attrs) in output_arrays(plan, outputs, method, h, w).items():
            group.create_array(name, shape=(n, *tail), chunks=(1, *tail), dtype=dtype, compressors=checksum_codecs(),
                               fill_value=fill, dimension_names=("time", *dims), attributes=attrs,
                               config={"write_empty_chunks": True})
        if "cube" in outputs and plan.output == "reflectance":
            group.create_array("wavelength", data=np.asarray(plan.output_wavelengths, np.float64),
                               dimension_names=("wavelength",), attributes={"units": "nm"},
                               compressors=checksum_codecs())
        group.create_array("frame_id", data=source.frame_ids(), chunks=(1, source.K),
                           dimension_names=("time", "pattern"), compressors=checksum_codecs())
        group.create_array("time", data=source.times(), chunks=(1,), dimension_names=("time",),
                           attributes={"units": "s"}, compressors=checksum_codecs())
        group.create_array("done", shape=(n,), chunks=(1,), dtype="uint8", fill_value=0, dimension_names=("time",),
                           compressors=checksum_codecs(), config={"write_empty_chunks": True})
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

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
        an array missing, shorter than the sequences, of another dtype or frame size, or with channels that do not
        match (a ``sigma`` array has one per cube output and their RMS).
    """
    path = Path(path)
    group, attrs = open_zarr_group(path, "batch output", BATCH_FORMAT, BATCH_VERSION)
    outputs = attrs.get("outputs")
    if not isinstance(outputs, list) or not outputs or not all(o in BATCH_OUTPUTS for o in outputs):
        raise ValueError(f"{path}: outputs must be a list of {', '.join(BATCH_OUTPUTS)}, got {str(outputs)[:80]}")
    if "done" not in group:
        raise ValueError(f"{path}: the 'done' array is missing")
    done = done_flags(group["done"])
    frame = None
    for name in [*outputs, *(["mask"] if "mask" in group else [])]:
        if name not in group:
            raise ValueError(f"{path}: the {name!r} array is missing")
        frame = _check_array(path, name, group[name], done.size, frame)
    if "sigma" in outputs and "cube" in outputs and group["sigma"].shape[-1] != group["cube"].shape[-1] + 1:
        raise ValueError(f"{path}/sigma: holds {group['sigma'].shape[-1]} channels for {group['cube'].shape[-1]} "
                         "cube outputs (one per output, then their RMS)")
    return BatchOutput(path, attrs, group, done)


def _check_array(path: Path, name: str, arr, sequences: int, frame) -> tuple:
    """Array ``name`` of a batch output checked: ``sequences`` steps along ``time``, its dtype and dimensions, the
    frame size ``frame`` (H, W) of the arrays checked before it, and its channels; returns its frame size."""
    where = f"{path}/{name}"
    if arr.shape[:1] != (sequences,):
        raise ValueError(f"{where}: holds {arr.shape[0] if arr.shape else 0} sequences but 'done' marks {sequences}")
    dtype = np.dtype("uint8" if name == "mask" else "float32")
    if arr.dtype != dtype:
        raise ValueError(f"{where}: is {arr.dtype}, a batch output's {name} is {dtype}")
    ndim = 4 if name in ("cube", "sigma", *CHANNELS) else 3
    if arr.ndim != ndim:
        raise ValueError(f"{where}: has {arr.ndim} dimensions, a batch output's {name} has {ndim} (time, y, x"
                         f"{', channel' if ndim == 4 else ''})")
    if frame is not None and tuple(arr.shape[1:3]) != frame:
        raise ValueError(f"{where}: frames of {arr.shape[1]} x {arr.shape[2]} pixels, the other arrays' are "
                         f"{frame[0]} x {frame[1]}")
    channels = dict(arr.attrs).get("channels")
    if name in CHANNELS and arr.shape[-1] != 3:
        raise ValueError(f"{where}: holds {arr.shape[-1]} channels, {name} has 3")
    if name == "sigma" and (not isinstance(channels, list) or len(channels) != arr.shape[-1] or arr.shape[-1] < 2
                            or channels[-1] != "sigma_rms"):
        raise ValueError(f"{where}: its channels {str(channels)[:80]} do not name its {arr.shape[-1]} channels "
                         "(sigma_<output>..., then sigma_rms)")
    return tuple(arr.shape[1:3])
