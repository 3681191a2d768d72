"""A moving scene through the command line: a rig TOML with [motion], capture (the truth kept beside the frames),
recover --motion global, evaluate against the truth at the reference time."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from cli_helpers import moving_rig, one_line_error, run

from specgpu import io
from specgpu.io.npz import read_cube_npz


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    d = moving_rig(tmp_path_factory.mktemp("moving"))  # the session's calibration of the moving rig
    run("plan", "symmetric", "--calib", d / "calib.npz", "--out", d / "plan.npz")
    run("capture", "--rig", d / "rig.toml", "--plan", d / "plan.npz", "--calib", d / "calib.npz", "--out", d / "seq",
        "--sequences", "2", "--seed", "3")
    return d


#: recover's cubes here are ENVI (raw float32): the cube is all these tests read back, and compressing an npz
#: cube costs a second each
def mean_rmse(result) -> float:
    return float(re.search(r"rmse mean ([0-9.]+)", result.output).group(1))


def test_the_capture_keeps_each_sequences_truth(moving):
    seq = moving / "seq"
    times = [r["timestamp_s"] for r in json.loads((seq / "sequence.json").read_text())["frames"]]
    K = len(times) // 2
    for s in range(2):
        cube, wl, extra = read_cube_npz(seq / "motion_truth" / f"sequence_{s:04d}.npz")
        assert cube.shape[:2] == (240, 320) and extra["displacement"].shape == (K, 2)
        # 2 px per frame period in x, 1 in y, from the middle frame of the sequence
        np.testing.assert_allclose(extra["displacement"], (np.arange(K) - K // 2)[:, None] * [2.0, 1.0], atol=1e-9)
        assert float(extra["reference_time_s"]) == pytest.approx(times[s * K + K // 2] + float(
            json.loads((seq / "sequence.json").read_text())["frames"][0]["exposure_s"]) / 2)


def test_recover_with_motion_compensation_scores_better_against_the_truth(moving, tmp_path):
    seq, truth = moving / "seq", moving / "seq" / "motion_truth" / "sequence_0001.npz"
    run("recover", seq, "--out", tmp_path / "plain.hdr", "--sequence", "1")
    done = run("recover", seq, "--out", tmp_path / "comp.hdr", "--sequence", "1", "--motion", "global")
    assert "out-of-field pixels left NaN" in done.output
    plain = mean_rmse(run("evaluate", tmp_path / "plain.hdr", "--truth", truth))
    comp = mean_rmse(run("evaluate", tmp_path / "comp.hdr", "--truth", truth))
    assert comp < 0.6 * plain


def test_motion_needs_one_sequence(moving, tmp_path):
    one_line_error(run("recover", moving / "seq", "--out", tmp_path / "c.npz", "--motion", "global", ok=False),
                   "one sequence at a time", "--sequence")
    one_line_error(run("recover", moving / "seq", "--out", tmp_path / "c.npz", "--motion", "optical", ok=False),
                   "--motion", code=2)


def test_denoise_with_motion_scores_better_against_the_truth(moving, tmp_path):
    """recover --motion --denoise: the filter guided by the warped frames' sum lowers the error of the compensated
    cube against the truth at the reference time."""
    seq, truth = moving / "seq", moving / "seq" / "motion_truth" / "sequence_0000.npz"
    run("recover", seq, "--out", tmp_path / "comp.hdr", "--sequence", "0", "--motion", "global")
    run("recover", seq, "--out", tmp_path / "den.hdr", "--sequence", "0", "--motion", "global", "--denoise")
    comp = mean_rmse(run("evaluate", tmp_path / "comp.hdr", "--truth", truth))
    assert mean_rmse(run("evaluate", tmp_path / "den.hdr", "--truth", truth)) < 0.95 * comp


def test_evaluate_takes_the_sequence_folder_as_truth(moving, tmp_path):
    seq = moving / "seq"
    run("recover", seq, "--out", tmp_path / "comp.hdr", "--sequence", "1", "--motion", "global")
    by_file = run("evaluate", tmp_path / "comp.hdr", "--truth", seq / "motion_truth" / "sequence_0001.npz")
    by_folder = run("evaluate", tmp_path / "comp.hdr", "--truth", seq)
    assert mean_rmse(by_folder) == mean_rmse(by_file)
    other = run("evaluate", tmp_path / "comp.hdr", "--truth", seq / "motion_truth" / "sequence_0000.npz")
    assert mean_rmse(other) > mean_rmse(by_folder)  # the scene moved between the sequences: the right one counts


def test_evaluate_refuses_a_folder_without_the_truth_it_needs(moving, tmp_path):
    seq = moving / "seq"
    run("recover", seq, "--out", tmp_path / "mean.hdr")  # both sequences averaged: no one truth
    one_line_error(run("evaluate", tmp_path / "mean.hdr", "--truth", seq, ok=False), "2 sequences",
                   "sequence_NNNN.npz")
    (tmp_path / "still").mkdir()
    one_line_error(run("evaluate", tmp_path / "mean.hdr", "--truth", tmp_path / "still", ok=False),
                   "holds no motion truth")


def motion_lines(result):
    return [line for line in result.output.splitlines() if "--motion" in line]


def test_recover_without_motion_says_in_one_line_that_the_capture_moved(moving, tmp_path):
    seq = moving / "seq"
    mean = run("recover", seq, "--out", tmp_path / "mean.hdr")
    said, = motion_lines(mean)
    assert said.startswith("Warning: ") and f"{seq}: captured while the scene moved" in said
    assert "averaged" in said and "--sequence N" in said
    assert io.read_cube(tmp_path / "mean.hdr")[2]["motion"] == "none: the capture moved, decoded as if still"
    one, = motion_lines(run("recover", seq, "--out", tmp_path / "one.hdr", "--sequence", "1"))
    assert "averaged" not in one and "give --motion" in one
    assert motion_lines(run("recover", seq, "--out", tmp_path / "c.hdr", "--sequence", "1", "--motion", "global")) \
        == []


def test_stream_of_a_moving_rig_without_motion_says_so_in_one_line(moving):
    args = ["stream", "--rig", moving / "rig.toml", "--plan", moving / "plan.npz", "--calib", moving / "calib.npz",
            "--seconds", "0.1", "--pacing", "free", "--outputs", "XYZ"]
    said, = motion_lines(run(*args))
    assert said.startswith("Warning: the rig's [motion] table moves the scene") and "give --motion" in said
