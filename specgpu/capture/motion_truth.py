"""The truth of each sequence captured on a moving twin, written beside its frames as it arrives: the scene at the
sequence's reference time and each frame's true displacement (the file layout: :mod:`specgpu.io.motion_truth`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from specgpu.io.motion_truth import TRUTH_FOLDER, truth_name
from specgpu.io.npz import write_cube_npz
from specgpu.rig.twin import TwinRig

__all__ = ["truth_recorder"]


def truth_recorder(directory, description, plan, scene):
    """A callable ``(index, sequence)`` that writes the truth of each sequence captured on a moving twin into
    ``directory/motion_truth/sequence_<index>.npz``: a scene cube (``wavelengths``, ``reflectance``: the scene at
    the sequence's reference time, so ``specgpu evaluate CUBE --truth`` reads it), with ``displacement`` (K, 2),
    each frame's true displacement from the reference time, px, and ``reference_time_s``."""
    rig = TwinRig(plan.rig_description(description), scene=scene)
    rig.load_sequence(plan.patterns)
    folder = Path(directory) / TRUTH_FOLDER
    folder.mkdir(parents=True, exist_ok=True)

    def record(index: int, sequence) -> Path:
        truth = rig.motion_truth(sequence.timestamps_s)
        return write_cube_npz(folder / truth_name(index), truth["reflectance"], rig.scene.wavelengths,
                              extra={"displacement": truth["displacement"],
                                     "reference_time_s": np.array(truth["reference_time_s"])})

    return record
