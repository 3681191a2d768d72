"""``specgpu plan --reference-every M`` end to end: the plan file holds the broadband reference frames, its timing
counts them, a budget holds them, what cannot combine is refused in one line, and ``recover --motion global`` of a
moving capture made with it is compensated from them."""

from __future__ import annotations

import re

import numpy as np
import pytest
from cli_helpers import moving_rig, one_line_error, run

from specgpu.planning import load_plan
from specgpu.planning.reference_frames import pattern_indices, reference_indices


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = moving_rig(tmp_path_factory.mktemp("reference-frames"))  # the session's calibration of the moving rig
    run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out",
        d / "bare.npz", "--no-ambient")
    return d


def test_the_plan_file_holds_the_reference_frames(files):
    d = files
    out = run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out",
              d / "ref.npz", "--no-ambient", "--reference-every", "3").output
    plan, bare = load_plan(d / "ref.npz"), load_plan(d / "bare.npz")
    assert reference_indices(plan) == [0, 4, 8, 10] and plan.K == 11
    np.testing.assert_array_equal(plan.patterns[pattern_indices(plan)], bare.patterns)
    np.testing.assert_array_equal(plan.A[:, pattern_indices(plan)], bare.A)
    np.testing.assert_array_equal(plan.A[:, reference_indices(plan)], 0.0)
    assert "11 frames (4 broadband reference frames among them)" in out
    assert f"{plan.sequence_s * 1e3:.1f} ms per sequence" in out
    assert plan.sequence_s == pytest.approx(bare.sequence_s * 11 / 7)


def test_a_budget_holds_the_reference_frames(files):
    d = files
    out = run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out",
              d / "budget.npz", "--no-ambient", "--reference-every", "3", "--sequence-ms", "40").output
    plan = load_plan(d / "budget.npz")
    assert plan.K == 11 and plan.sequence_s <= 0.040 * (1 + 1e-9) and "(budget 40 ms)" in out
    one_line_error(run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml",
                       "--out", d / "short.npz", "--no-ambient", "--reference-every", "1", "--sequence-ms", "1",
                       ok=False), "cannot hold 15 frames")
    assert not (d / "short.npz").exists()


@pytest.mark.parametrize("extra, fragments", [
    (("--reference-every", "0"), ("--reference-every", "0 is not in the range x>=1")),
    (("--reference-every", "2.5"), ("--reference-every", "not a valid integer")),
    (("--reference-every", "3", "--ambient"), ("--reference-every", "--ambient", "--drift-probe")),
    (("--reference-every", "3", "--drift-probe", "430"), ("--reference-every", "--drift-probe")),
])
def test_what_cannot_be_planned_is_refused_in_one_line(files, extra, fragments):
    d = files
    one_line_error(run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml",
                       "--out", d / "bad.npz", *extra, ok=False), *fragments)
    assert not (d / "bad.npz").exists()


def test_recover_with_motion_reads_the_reference_frames(files, tmp_path):
    d = files
    run("plan", "symmetric", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out", d / "sym.npz",
        "--no-ambient", "--reference-every", "3")
    run("capture", "--rig", d / "rig.toml", "--plan", d / "sym.npz", "--calib", d / "calib.npz", "--out",
        d / "seq", "--sequences", "1", "--seed", "3")
    truth = d / "seq" / "motion_truth" / "sequence_0000.npz"
    run("recover", d / "seq", "--out", tmp_path / "plain.hdr")  # ENVI: raw float32, no second compressing it
    run("recover", d / "seq", "--out", tmp_path / "comp.hdr", "--motion", "global")

    def rmse(result):
        return float(re.search(r"rmse mean ([0-9.]+)", result.output).group(1))

    plain = rmse(run("evaluate", tmp_path / "plain.hdr", "--truth", truth))
    comp = rmse(run("evaluate", tmp_path / "comp.hdr", "--truth", truth))
    assert comp < 0.6 * plain


def test_a_moving_stream_with_reference_frames(files, tmp_path):
    import zarr

    d = files
    run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out",
        d / "stream.npz", "--no-ambient", "--reference-every", "3")
    args = ["stream", "--rig", d / "rig.toml", "--plan", d / "stream.npz", "--calib", d / "calib.npz", "--scene",
            "natural", "--pacing", "free", "--seconds", "0.3", "--motion", "global"]
    run(*args, "--outputs", "cube,sigma_rms", "--out", tmp_path / "rec.zarr")
    rec = zarr.open_group(str(tmp_path / "rec.zarr"), mode="r")
    cube = np.asarray(rec["cube"][0], np.float32)
    sigma = np.asarray(rec["sigma_rms"][0], np.float32)
    decoded = np.isfinite(cube).all(axis=2)
    assert 0.8 < decoded.mean() < 1.0  # the moving border (seen outside by some pattern frame) NaN, the rest decoded
    assert np.array_equal(np.isfinite(sigma), decoded) and np.all(sigma[decoded] > 0)
