"""Whether a capture (or a rig) moved, the one line every command says when it runs one without ``--motion``, and
the motion truth kept in step with the sequences when a killed capture is salvaged.

A capture on a moving twin records that it moved by the truth it keeps beside its frames:
``motion_truth/sequence_<n>.npz`` per sequence (:func:`specgpu.capture.motion_truth.truth_recorder`), written as each
sequence arrives, so a killed and salvaged capture records it too and folders written before this module read
alike. :func:`moved` is the one place that decides; recover, report, view and stream ask it.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

from specgpu.io.motion_truth import TRUTH_FOLDER, truth_name

__all__ = ["moved", "motion_notice", "without_motion", "renumber_truth", "LEFT_OUT_FOLDER"]

#: Sub-folder of ``motion_truth/`` where salvage keeps the truth of the sequences it left out (capture order).
LEFT_OUT_FOLDER = "left_out"
_TRUTH_NAME = re.compile(r"^sequence_(\d{4,})\.npz$")
#: The motion modes the notice points to.
_MODES = "--motion global, affine or flow"


def _truth_files(directory: Path) -> dict:
    """Sequence index -> truth file kept directly in ``directory/motion_truth``."""
    folder = directory / TRUTH_FOLDER
    if not folder.is_dir():
        return {}
    return {int(m.group(1)): p for p in folder.iterdir() if (m := _TRUTH_NAME.match(p.name)) and p.is_file()}


def _rig_motion(source):
    """The ``[motion]`` parameters of a rig description, or None for anything else (a sequence folder)."""
    motion = getattr(source, "motion", None)
    return motion if motion is not None and hasattr(motion, "any") else None


def moved(source) -> bool:
    """Whether ``source`` moved while it was captured: a rig description (its ``[motion]`` table moves the twin's
    world), or a sequence folder (a path or a :class:`~specgpu.pipeline.capture_folder.SequenceFolder`: it keeps the
    motion truth of its sequences, which a capture on a moving twin records)."""
    motion = _rig_motion(source)
    if motion is not None:
        return bool(motion.any)
    return bool(_truth_files(Path(getattr(source, "path", source))))


def motion_notice(source, doing: str) -> str | None:
    """The one line that says ``source`` (as :func:`moved` takes it) moved, and what ``doing`` (the command's
    words for what it does about it) means; None when it did not move. Each command that reads a capture or
    streams a rig says it when the motion is not compensated, and the report and the viewer when they compensate
    on their own."""
    if not moved(source):
        return None
    if _rig_motion(source) is not None:
        what = "the rig's [motion] table moves the scene during each sequence"
    else:
        what = (f"{Path(getattr(source, 'path', source))}: captured while the scene moved (its {TRUTH_FOLDER}/ "
                "records each sequence's truth)")
    return f"{what}; {doing}"


def without_motion(source, *, averaged: bool) -> str | None:
    """:func:`motion_notice` of a command run without ``--motion``: its frames decoded as if the scene stood
    still (and the sequences averaged, ``averaged``), with the way to compensate."""
    also = " and its sequences averaged" if averaged else ""
    return motion_notice(source, f"without --motion each sequence is decoded as if still{also}, blurring what "
                                 f"moved: give {_MODES}" + (" with --sequence N" if averaged else ""))


def renumber_truth(directory, kept) -> None:
    """Keep ``motion_truth/`` in step with a salvaged capture's sequences: ``kept`` lists, in order, the capture-order
    index of each sequence the index holds (sequence ``n`` of the folder is captured sequence ``kept[n]``), so
    ``sequence_<kept[n]>.npz`` becomes ``sequence_<n>.npz``; the truth of a sequence left out (or never completed)
    moves to ``motion_truth/left_out/`` under its capture-order name: nothing recorded is lost.

    The new folder is built beside the old one (hard links, or copies where the file system has none) and put in
    its place by two renames; a salvage stopped between them finds the old one as ``motion_truth.captured`` and
    starts again from it. A folder that keeps no truth is left alone."""
    directory = Path(directory)
    folder, staged, old = (directory / TRUTH_FOLDER, directory / f"{TRUTH_FOLDER}.salvage",
                           directory / f"{TRUTH_FOLDER}.captured")
    if old.is_dir() and not folder.is_dir():  # a salvage stopped between the two renames
        old.rename(folder)
    files = _truth_files(directory)
    if not files:
        return
    shutil.rmtree(staged, ignore_errors=True)  # what a stopped salvage staged: built again
    (staged / LEFT_OUT_FOLDER).mkdir(parents=True)
    new_index = {int(c): n for n, c in enumerate(kept)}
    for captured, path in sorted(files.items()):
        n = new_index.get(captured)
        _link(path, staged / truth_name(n) if n is not None else staged / LEFT_OUT_FOLDER / path.name)
    earlier = folder / LEFT_OUT_FOLDER
    if earlier.is_dir():
        for path in earlier.iterdir():
            if not (staged / LEFT_OUT_FOLDER / path.name).exists():
                _link(path, staged / LEFT_OUT_FOLDER / path.name)
    if not any((staged / LEFT_OUT_FOLDER).iterdir()):
        (staged / LEFT_OUT_FOLDER).rmdir()
    folder.rename(old)
    staged.rename(folder)
    shutil.rmtree(old, ignore_errors=True)  # every file of it is linked (or copied) into the new folder


def _link(source: Path, target: Path) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)
