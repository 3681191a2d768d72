"""Whether a capture or a rig moved (one decision for every command), and the motion truth renumbered with the
sequences a salvage keeps, including after a salvage stopped half-way."""

from __future__ import annotations

import numpy as np

from specgpu.io.npz import read_cube_npz, write_cube_npz
from specgpu.pipeline.motion_record import motion_notice, moved, renumber_truth, without_motion
from specgpu.rig.config import rig_from_dict


def truth_folder(root, indices):
    folder = root / "motion_truth"
    folder.mkdir(parents=True)
    for s in indices:  # each file tells its capture-order index by its value
        write_cube_npz(folder / f"sequence_{s:04d}.npz", np.full((2, 3, 2), s, np.float32), [500.0, 600.0])
    return folder


def value(path) -> float:
    return float(read_cube_npz(path)[0][0, 0, 0])


def test_a_folder_moved_when_it_keeps_motion_truth_and_a_rig_when_its_motion_table_moves(tmp_path):
    assert not moved(tmp_path) and without_motion(tmp_path, averaged=True) is None
    (tmp_path / "motion_truth").mkdir()
    assert not moved(tmp_path)  # an empty truth folder records nothing
    write_cube_npz(tmp_path / "motion_truth" / "sequence_0000.npz", np.zeros((2, 2, 2), np.float32), [500, 600])
    assert moved(tmp_path) and moved(type("Folder", (), {"path": tmp_path})())
    line = without_motion(tmp_path, averaged=True)
    assert "\n" not in line and str(tmp_path) in line and "averaged" in line and "--motion" in line
    still = rig_from_dict({}, source="<still>")
    moving = rig_from_dict({"motion": {"velocity_px_per_frame": [1.0, 0.0]}}, source="<moving>")
    assert not moved(still) and moved(moving)
    assert motion_notice(still, "x") is None and motion_notice(moving, "x").endswith("; x")


def test_renumber_truth_follows_the_kept_sequences_and_keeps_the_rest_aside(tmp_path):
    folder = truth_folder(tmp_path, range(5))
    renumber_truth(tmp_path, [0, 2, 3])
    assert [value(folder / f"sequence_{n:04d}.npz") for n in range(3)] == [0, 2, 3]
    assert sorted(p.name for p in folder.glob("sequence_*.npz")) == [f"sequence_{n:04d}.npz" for n in range(3)]
    assert [value(folder / "left_out" / f"sequence_{s:04d}.npz") for s in (1, 4)] == [1, 4]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["motion_truth"]


def test_renumber_truth_after_a_salvage_stopped_between_its_renames(tmp_path):
    truth_folder(tmp_path, range(3))
    (tmp_path / "motion_truth").rename(tmp_path / "motion_truth.captured")  # the old folder moved aside, then stop
    (tmp_path / "motion_truth.salvage").mkdir()  # and a half-built new one
    renumber_truth(tmp_path, [1, 2])
    folder = tmp_path / "motion_truth"
    assert [value(folder / f"sequence_{n:04d}.npz") for n in range(2)] == [1, 2]
    assert value(folder / "left_out" / "sequence_0000.npz") == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["motion_truth"]


def test_renumber_truth_leaves_a_folder_without_truth_alone(tmp_path):
    renumber_truth(tmp_path, [0, 1])
    assert list(tmp_path.iterdir()) == []
