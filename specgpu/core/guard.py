"""The output guard: nothing a command writes may land on what it reads.

A command names its outputs and everything it reads: files, and folders read whole (a zarr recording, a moving
capture's ``motion_truth`` folder). An output clashes with an input when

- both name one file: the same path once every symbolic link and ``..`` is resolved, or one file under two
  names (a hard link);
- the output lies inside an input folder, by its resolved path or by the path as given (an output reached
  through a link inside the folder would change what reading the folder sees), or inside what a symbolic link
  in the folder points to (reading the folder reads it too);
- the output is an existing folder that holds an input (a folder output is written into).

Two outputs naming one file clash too: the second would replace the first. Commands call it before any work, so
a refused command has written nothing; the error names both paths.
"""

from __future__ import annotations

import os
from pathlib import Path

from specgpu.core.validate import BadArgument

__all__ = ["OutputClash", "check_outputs"]


class OutputClash(BadArgument):
    """An output that would replace or change an input or another output.

    Attributes
    ----------
    output, other : pathlib.Path
        The output refused, and the input (or earlier output) it clashes with.
    """

    def __init__(self, message: str, output, other):
        super().__init__(message)
        self.output = Path(output)
        self.other = Path(other)


def _forms(path) -> tuple[Path, Path]:
    """``path`` absolute as given (links kept, ``..`` folded) and resolved (every link followed)."""
    return Path(os.path.normpath(os.path.abspath(path))), Path(os.path.realpath(path))


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def _same_file(a, b) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet): equal only as resolved paths
        return Path(os.path.realpath(a)) == Path(os.path.realpath(b))


def _extent(source) -> list:
    """What reading ``source`` reads: the file, or the folder and whatever the symbolic links under it point to
    (each once, so a link cycle ends)."""
    found = [source]
    if not os.path.isdir(source):
        return found
    seen, todo = {os.path.realpath(source)}, [source]
    while todo:
        try:
            entries = list(os.scandir(todo.pop()))
        except OSError:
            continue
        for entry in entries:
            if entry.is_symlink():
                target = os.path.realpath(entry.path)
                if target not in seen:
                    seen.add(target)
                    found.append(target)
                    if os.path.isdir(target):
                        todo.append(target)
            elif entry.is_dir(follow_symlinks=False):
                todo.append(entry.path)
    return found


def _clash(output, source, extent) -> str | None:
    """How writing ``output`` would change what reading ``source`` (its :func:`_extent`) reads (None: it would
    not)."""
    for part in extent:
        if _same_file(output, part):
            return "is" if part is source else "inside"
        if os.path.isdir(part) and any(_within(o, s) for o, s in zip(_forms(output), _forms(part))):
            return "inside"
        if os.path.isdir(output) and any(_within(s, o) for o, s in zip(_forms(output), _forms(part))):
            return "holds"
    return None


def check_outputs(outputs, inputs=()) -> None:
    """Refuse outputs that would overwrite or change what the command reads, or each other.

    Parameters
    ----------
    outputs : iterable of (str, path-like or None)
        Each output with the name the user knows it by (an option, ``"--out"``); None entries are skipped.
    inputs : iterable of (str, path-like or None)
        Everything the command reads, with its name (``"--calib"``, ``"SEQ's plan.npz"``): files, and folders
        read whole; None entries are skipped. A file a read file refers to (an ENVI header's data file, a
        capture's frames) is an input of its own: the caller lists it.

    Raises
    ------
    OutputClash
        One line naming the output and the input (or the other output) with both paths, for the first clash.
    """
    outputs = [(label, Path(p)) for label, p in outputs if p is not None]
    inputs = [(label, Path(p)) for label, p in inputs if p is not None]
    extents = [_extent(p) for _, p in inputs]  # a folder walked once, however many outputs
    for i, (label, path) in enumerate(outputs):
        for other, other_path in outputs[:i]:
            if _same_file(path, other_path):
                raise OutputClash(f"{other} and {label} both name {path}; give each output its own file", path,
                                  other_path)
        for (source, source_path), extent in zip(inputs, extents):
            how = _clash(path, source_path, extent)
            if how == "is":
                message = (f"{label} {path} is the input {source} ({source_path}); writing it would destroy that "
                           "input, choose another file")
            elif how == "inside":
                message = (f"{label} {path} lies inside the input {source} ({source_path}); writing it would "
                           "change that input, choose a path outside it")
            elif how == "holds":
                message = (f"{label} {path} holds the input {source} ({source_path}); writing into it could "
                           "replace that input, choose another folder")
            else:
                continue
            raise OutputClash(message, path, source_path)
