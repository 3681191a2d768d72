"""``specgpu evaluate`` through the command line: the pixels it leaves out counted by cause (stdout and JSON), a
cube holding values no recovery writes refused, a truth that is not the capture the cube records named, per-pixel
figures beside the per-patch ones, and no stray warning."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import hadamard_rig, one_line_error, python_path, run

from specgpu import io
from specgpu.io.motion_truth import TRUTH_FOLDER
from specgpu.io.npz import write_cube_npz
from specgpu.io.sequence import capture_hash, read_sequence_header
from specgpu.pipeline.evaluate import truth_cube
from specgpu.rig.scene import colorchecker_scene

GRID = np.arange(400.0, 701.0, 10.0)
#: a 72 x 48 chart: its first 16 rows hold the first row of patches and some border (1152 pixels)
H, W, ROWS = 48, 72, 16


def chart_cube(path, fill=None, metadata=None):
    """The chart's truth, 0.01 too reflective, with its first ROWS rows set to ``fill``; written to ``path``."""
    cube = truth_cube(colorchecker_scene(H, W), GRID) + 0.01
    if fill is not None:
        cube[:ROWS] = fill
    io.write_cube(path, cube, GRID, metadata=metadata)
    return path


def no_runtime_warning(*args, ok=True):
    """``run`` with every warning recorded; asserts none is a RuntimeWarning (NumPy's overflow, empty slice ...)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run(*args, ok=ok)
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in caught]
    return result


@pytest.mark.parametrize("fill, words", [(np.inf, "1152 infinite, 0 outside"), (-np.inf, "1152 infinite, 0 outside"),
                                         (1e30, "0 infinite, 1152 outside the plausible range -1 to 10")])
def test_a_cube_holding_values_no_recovery_writes_is_refused(tmp_path, fill, words):
    cube = chart_cube(tmp_path / "bad.npz", fill)
    result = no_runtime_warning("evaluate", cube, "--truth", "colorchecker", "--json", tmp_path / "r.json", ok=False)
    one_line_error(result, f"{cube}: 1152 pixels hold values no recovery writes ({words}", "row 0, column 0",
                   "--exclude-invalid", code=1)
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("fill, cause, words", [(np.nan, "flagged", "1152 NaN (flagged by the recovery)"),
                                                (np.inf, "non_finite", "1152 infinite"),
                                                (1e30, "out_of_range", "1152 outside -1 to 10")])
def test_pixels_left_out_are_counted_by_cause_on_stdout_and_in_json(tmp_path, fill, cause, words):
    chart_cube(tmp_path / "clean.npz")
    run("evaluate", tmp_path / "clean.npz", "--truth", "colorchecker", "--json", tmp_path / "clean.json")
    chart_cube(tmp_path / "bad.npz", fill)
    result = no_runtime_warning("evaluate", tmp_path / "bad.npz", "--truth", "colorchecker", "--exclude-invalid",
                                "--json", tmp_path / "bad.json")
    clean, bad = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("clean", "bad"))
    assert clean["pixels_scored"] == clean["pixels_total"] == H * W
    assert sum(clean["excluded"].values()) == 0 and clean["patches_scored"] == 24
    assert bad["pixels_total"] == H * W and bad["pixels_scored"] == H * W - 1152
    assert bad["excluded"] == {"flagged": 0, "non_finite": 0, "out_of_range": 0, "unscored": 0, cause: 1152}
    assert bad["patches_scored"] == 18 and bad["rmse_mean"] == pytest.approx(0.01, rel=1e-4)
    assert f"{H * W - 1152} of {H * W} pixels scored, left out: {words}" in result.stdout
    assert "18 of 24 patches scored" in result.stdout
    assert "Warning" not in result.stderr


def test_a_chart_prints_its_per_pixel_figures_beside_the_per_patch_ones(tmp_path):
    cube = chart_cube(tmp_path / "c.npz")
    result = run("evaluate", cube, "--truth", "colorchecker", "--json", tmp_path / "r.json")
    report = json.loads((tmp_path / "r.json").read_text())
    lines = result.stdout.splitlines()
    patch = next(i for i, line in enumerate(lines) if line.startswith("per patch under D65: rmse mean"))
    pixel = lines[patch + 1]
    assert pixel.startswith("per pixel under D65: rmse mean")
    stats = report["pixels"]
    for short, key in (("rmse", "rmse"), ("dE76", "delta_E_ab"), ("dE2000", "delta_E_2000")):
        figures = {name: stats[key][name] for name in ("mean", "median", "p95", "max")}
        assert (f"{short} mean {figures['mean']:.4g} median {figures['median']:.4g} p95 {figures['p95']:.4g} max "
                f"{figures['max']:.4g}") in pixel
    assert pixel.endswith(f"{H * W} of {H * W} pixels scored")


def test_a_natural_scene_prints_the_median_and_p95_with_the_counts(tmp_path):
    scene = colorchecker_scene(H, W)
    io.write_cube(tmp_path / "truth.npz", scene.reflectance, scene.wavelengths)  # a truth without patches
    cube = chart_cube(tmp_path / "c.npz", np.nan)
    result = run("evaluate", cube, "--truth", tmp_path / "truth.npz", "--json", tmp_path / "r.json")
    report = json.loads((tmp_path / "r.json").read_text())
    assert "patches" not in report and report["excluded"]["flagged"] == 1152
    median = report["pixels"]["rmse"]["median"]
    assert f"per pixel: rmse median {median:.4g} p95" in result.stdout
    assert "left out: 1152 NaN (flagged by the recovery)" in result.stdout


def test_the_command_writes_nothing_on_stderr_but_its_progress(tmp_path):
    cube = chart_cube(tmp_path / "huge.npz", 1e30)
    done = subprocess.run([sys.executable, "-m", "specgpu", "evaluate", str(cube), "--truth", "colorchecker",
                           "--exclude-invalid"], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": python_path(Path(__file__).parents[2])})
    assert done.returncode == 0, done.stderr
    left = [part for part in done.stderr.replace("\n", "\r").split("\r")
            if part.strip() and not part.startswith("evaluating: ")]
    assert left == [], done.stderr
    assert "1152 outside -1 to 10" in done.stdout


# ---- the truth against the capture the cube records ---------------------------------------------------------------
@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """A Hadamard capture of the chart recovered to a cube, and a second capture of it with other noise; each
    folder holds the chart as its motion truth, as a capture on a moving twin does."""
    d = tmp_path_factory.mktemp("evaluate")
    rig, cal, plan = hadamard_rig(d)
    for seq, seed in (("seq", 1), ("again", 2)):
        run("capture", "--rig", rig, "--plan", plan, "--calib", cal, "--scene", "colorchecker", "--out", d / seq,
            "--seed", seed)
        scene = colorchecker_scene(240, 320)
        (d / seq / TRUTH_FOLDER).mkdir()
        write_cube_npz(d / seq / TRUTH_FOLDER / "sequence_0000.npz", scene.reflectance, scene.wavelengths)
    run("recover", d / "seq", "--out", d / "cube.npz")
    return d


def test_recover_records_the_capture_and_the_scene(captured):
    meta = io.read_cube(captured / "cube.npz")[2]
    assert meta["capture"] == capture_hash(read_sequence_header(captured / "seq")[0])
    assert meta["capture"] != capture_hash(read_sequence_header(captured / "again")[0])
    assert meta["scene"] == "colorchecker" and meta["sequence_folder"] == str(captured / "seq")


def test_evaluate_names_a_truth_of_another_scene(captured, tmp_path):
    cube = captured / "cube.npz"
    same = run("evaluate", cube, "--truth", "colorchecker", "--json", tmp_path / "same.json")
    assert "Warning" not in same.stderr and "truth_mismatch" not in json.loads((tmp_path / "same.json").read_text())
    other = run("evaluate", cube, "--truth", "white", "--json", tmp_path / "other.json")
    said = f"{cube} was recovered from {captured / 'seq'}, a capture of scene 'colorchecker', not of --truth white"
    assert f"Warning: {said}" in other.stderr.splitlines()
    assert json.loads((tmp_path / "other.json").read_text())["truth_mismatch"] == said


def test_evaluate_names_a_truth_of_another_capture(captured, tmp_path):
    cube = captured / "cube.npz"
    shutil.copytree(captured / "seq", tmp_path / "copy")  # a copy of the capture is that capture
    for truth in (captured / "seq", tmp_path / "copy", tmp_path / "copy" / TRUTH_FOLDER / "sequence_0000.npz"):
        assert "Warning" not in run("evaluate", cube, "--truth", truth).stderr, truth
    other = run("evaluate", cube, "--truth", captured / "again", "--json", tmp_path / "r.json")
    warning = [line for line in other.stderr.splitlines() if line.startswith("Warning:")]
    assert len(warning) == 1 and f"not from the capture --truth {captured / 'again'} belongs to" in warning[0]
    assert json.loads((tmp_path / "r.json").read_text())["truth_mismatch"] == warning[0][len("Warning: "):]
