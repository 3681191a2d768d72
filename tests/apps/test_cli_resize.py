"""Scenes and truths of another size than the frame: fitted only as asked (--resize), said on stderr and recorded;
another aspect ratio is refused unless a mode that handles it is chosen."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import one_line_error, run, tristimulus_rig

from specgpu import io
from specgpu.pipeline.evaluate import truth_cube
from specgpu.rig.scene import colorchecker_scene, write_scene

STRETCH = "resampled 100 x 120 -> 320 x 240 pixels (stretch, nearest neighbour; aspect ratio 0.8333 -> 1.333)"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """The small twin rig (320 x 240) with a tristimulus plan, a portrait chart file (100 x 120, W x H), a chart
    file of the frame's aspect ratio at half its size, and one capture of the built-in chart."""
    d = tristimulus_rig(tmp_path_factory.mktemp("resize"))
    write_scene(d / "tall.npz", colorchecker_scene(120, 100))
    write_scene(d / "half.npz", colorchecker_scene(120, 160))
    run("capture", "--rig", d / "rig.toml", "--plan", d / "tri.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", d / "seq", "--seed", "1")
    return d


def capture_args(d, scene, out):
    return ["capture", "--rig", d / "rig.toml", "--plan", d / "tri.npz", "--calib", d / "calib.npz", "--scene",
            scene, "--out", out]


def test_capture_refuses_a_scene_of_another_aspect_ratio(bench, tmp_path):
    result = run(*capture_args(bench, bench / "tall.npz", tmp_path / "seq"), ok=False)
    one_line_error(result, f"{bench / 'tall.npz'} is 100 x 120 pixels, the frame 320 x 240: another aspect ratio",
                   "--resize stretch, crop or pad", code=1)
    assert not (tmp_path / "seq" / "sequence.json").exists()


def test_capture_stretches_when_asked_and_says_so_on_stderr_and_in_the_sequence(bench, tmp_path):
    result = run(*capture_args(bench, bench / "tall.npz", tmp_path / "seq"), "--resize", "stretch")
    assert f"specgpu: --scene {bench / 'tall.npz'}: {STRETCH}" in result.stderr.splitlines()
    doc = json.loads((tmp_path / "seq" / "sequence.json").read_text())
    assert doc["metadata"]["scene_resampled"] == STRETCH.removeprefix("resampled ")


def test_capture_scales_a_scene_of_the_frame_aspect_ratio_and_says_so(bench, tmp_path):
    result = run(*capture_args(bench, bench / "half.npz", tmp_path / "seq"))
    assert (f"specgpu: --scene {bench / 'half.npz'}: resampled 160 x 120 -> 320 x 240 pixels (scale, nearest "
            "neighbour)") in result.stderr.splitlines()
    assert "scene_resampled" in json.loads((tmp_path / "seq" / "sequence.json").read_text())["metadata"]
    # the built-in chart is drawn at the frame's size: nothing to say
    assert "resampled" not in run(*capture_args(bench, "colorchecker", tmp_path / "seq2")).stderr


@pytest.fixture(scope="module")
def cube(bench):
    """A 320 x 240 reflectance cube: the chart itself on 400-700 nm."""
    wl = np.arange(400.0, 701.0, 10.0)
    path = bench / "cube.exr"
    io.write_cube(path, truth_cube(colorchecker_scene(240, 320), wl), wl)
    return path


def test_evaluate_refuses_a_truth_of_another_aspect_ratio_unless_asked(bench, cube, tmp_path):
    result = run("evaluate", cube, "--truth", bench / "tall.npz", ok=False)
    one_line_error(result, f"{bench / 'tall.npz'} is 100 x 120 pixels, the frame 320 x 240", "--resize", code=1)
    result = run("evaluate", cube, "--truth", bench / "tall.npz", "--resize", "stretch", "--json", tmp_path / "r.json")
    assert f"specgpu: --truth {bench / 'tall.npz'}: {STRETCH}" in result.stderr.splitlines()
    assert json.loads((tmp_path / "r.json").read_text())["truth_resampled"] == STRETCH.removeprefix("resampled ")


def test_evaluate_says_when_it_scales_the_truth(bench, cube, tmp_path):
    result = run("evaluate", cube, "--truth", bench / "half.npz", "--json", tmp_path / "r.json")
    assert "resampled 160 x 120 -> 320 x 240 pixels (scale, nearest neighbour)" in result.stderr
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["truth_resampled"] == "160 x 120 -> 320 x 240 pixels (scale, nearest neighbour)"
    assert report["rmse_mean"] < 0.01  # the same chart, twice the size: the patches' spectra agree
    result = run("evaluate", cube, "--truth", bench / "half.npz", "--resize", "exact", ok=False)
    one_line_error(result, "half.npz is 160 x 120 pixels, the frame 320 x 240; give a scene of the frame's size",
                   code=1)


def test_an_unknown_resize_mode_is_a_usage_error_naming_the_modes(bench, cube):
    result = run("evaluate", cube, "--truth", "colorchecker", "--resize", "squash", ok=False)
    assert result.exit_code == 2
    assert "resize mode 'squash' is not one of scale, exact, stretch, crop, pad" in result.output


def test_recover_fits_a_delta_e_reference_file_as_asked(bench, tmp_path):
    args = ["recover", bench / "seq", "--out", tmp_path / "xyz.exr", "--delta-e-ref", bench / "tall.npz",
            "--delta-e", tmp_path / "dE.exr"]
    one_line_error(run(*args, ok=False), "tall.npz is 100 x 120 pixels", code=1)
    result = run(*args, "--resize", "crop")
    note = "100 x 120 -> 320 x 240 pixels (crop, nearest neighbour; 0 source columns and 45 rows cropped)"
    assert f"specgpu: --delta-e-ref {bench / 'tall.npz'}: resampled {note}" in result.stderr.splitlines()
    assert io.read_map(tmp_path / "dE.exr")[2]["reference_resampled"] == note
