"""Where a sequence folder captured on a moving twin keeps each sequence's truth, and which truth file a recovery of
it is scored against: ``motion_truth/sequence_<n>.npz`` (a scene cube at the sequence's reference time with each
frame's true displacement; written by :func:`specgpu.capture.motion_truth.truth_recorder`).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["TRUTH_FOLDER", "truth_name", "sequence_truth"]

#: Sub-folder of a sequence folder captured on a moving twin that holds each sequence's truth.
TRUTH_FOLDER = "motion_truth"


def truth_name(sequence: int) -> str:
    """The file name of sequence ``sequence``'s motion truth in ``motion_truth/``."""
    return f"sequence_{int(sequence):04d}.npz"


def sequence_truth(directory, sequence: int | None = None) -> Path:
    """The truth file a recovery of ``directory`` (a sequence folder captured on a moving twin) is scored against:
    ``motion_truth/sequence_<sequence>.npz``; with ``sequence`` None, the folder's only one. Refused in one line
    when the folder keeps no truth, when ``sequence`` has none, or when several do and none is named."""
    directory = Path(directory)
    try:  # as a recovery's metadata records it (a number, or its text in an EXR header)
        sequence = None if sequence is None else int(sequence)
    except (TypeError, ValueError):
        sequence = None
    folder = directory / TRUTH_FOLDER
    kept = sorted(folder.glob("sequence_*.npz")) if folder.is_dir() else []
    if not kept:
        raise ValueError(f"{directory}: holds no motion truth ({TRUTH_FOLDER}/sequence_NNNN.npz: a capture on a "
                         "moving twin keeps it); give the true scene (colorchecker, white, natural or a cube file)")
    if sequence is not None:
        path = folder / truth_name(sequence)
        if not path.is_file():
            raise ValueError(f"{directory}: holds no motion truth of sequence {int(sequence)} ({len(kept)} kept: "
                             f"{kept[0].name} .. {kept[-1].name})")
        return path
    if len(kept) > 1:
        raise ValueError(f"{directory}: holds the motion truth of {len(kept)} sequences and the recovery does not "
                         f"record which it is; give --truth {folder}/sequence_NNNN.npz")
    return kept[0]
