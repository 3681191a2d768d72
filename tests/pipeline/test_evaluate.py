"""Per-patch and per-pixel error metrics against NumPy and colour-science references, the pixels a report leaves
out (counted by cause), and a truth that is not the capture a cube records."""

from __future__ import annotations

import json
import warnings
from types import SimpleNamespace

import colour
import numpy as np
import pytest

from specgpu.core.spectra import DEFAULT_CMFS
from specgpu.io.motion_truth import TRUTH_FOLDER
from specgpu.io.npz import write_cube_npz
from specgpu.io.sequence import capture_hash, read_sequence_header, write_sequence
from specgpu.pipeline.evaluate import (
    PLAUSIBLE_RANGE,
    PixelReport,
    delta_E_per_patch,
    evaluate_pixels,
    evaluate_reflectance,
    patch_means,
    rmse_per_patch,
    screen_estimate,
    truth_cube,
)
from specgpu.pipeline.evaluation_report import evaluation_report, headline_line, patch_table, pixel_line, truth_mismatch
from specgpu.rig.scene import colorchecker_scene

GRID = np.arange(400.0, 701.0, 10.0)


def test_patch_means_leave_out_non_finite_pixels():
    img = np.ones((4, 4, 2))
    img[0, 0] = np.nan
    img[0, 1] = 3.0
    masks = {"top": np.zeros((4, 4), bool), "empty": np.zeros((4, 4), bool)}
    masks["top"][0, :2] = True
    masks["empty"][1, 1] = True
    img[1, 1, 0] = np.inf
    names, means = patch_means(img, masks)
    assert names == ("top", "empty")
    np.testing.assert_array_equal(means[0], [3.0, 3.0])
    assert np.isnan(means[1]).all()
    with pytest.raises(ValueError, match="mask 'bad' has shape"):
        patch_means(img, {"bad": np.zeros((3, 4), bool)})


def test_rmse_and_colour_differences_per_patch_equal_the_references():
    rng = np.random.default_rng(3)
    truth, estimate = rng.uniform(0, 1, (6, 31)), rng.uniform(0, 1, (6, 31))
    np.testing.assert_allclose(rmse_per_patch(estimate, truth), np.sqrt(((estimate - truth) ** 2).mean(1)))
    XYZ_t, XYZ_e = rng.uniform(0.05, 0.9, (6, 3)), rng.uniform(0.05, 0.9, (6, 3))
    xy = colour.CCS_ILLUMINANTS[DEFAULT_CMFS]["D65"]
    ab, de2000 = delta_E_per_patch(XYZ_e, XYZ_t, xy)
    lab_t, lab_e = colour.XYZ_to_Lab(XYZ_t, xy), colour.XYZ_to_Lab(XYZ_e, xy)
    np.testing.assert_allclose(ab, colour.delta_E(lab_t, lab_e, method="CIE 1976"), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(de2000, colour.delta_E(lab_t, lab_e, method="CIE 2000"), rtol=1e-4, atol=1e-4)


def test_the_truth_scores_zero_and_a_uniform_bias_scores_the_bias():
    scene = colorchecker_scene(48, 72)
    truth = truth_cube(scene, GRID)
    exact = evaluate_reflectance(truth, GRID, scene)
    assert exact.summary()["rmse"][1] < 1e-6 and exact.summary()["delta_E_2000"][1] < 1e-3
    biased = evaluate_reflectance(truth + 0.02, GRID, scene)
    np.testing.assert_allclose(biased.rmse, 0.02, rtol=1e-4)
    assert biased.worst("delta_E_ab") in biased.names


def test_pixel_statistics_ignore_nan_and_say_nan_when_nothing_is_valid():
    scene = colorchecker_scene(24, 36)
    cube = truth_cube(scene, GRID) + 0.01
    cube[:4] = np.nan
    stats = evaluate_pixels(cube, scene, wavelengths=GRID).statistics()
    assert stats["rmse"]["median"] == pytest.approx(0.01, rel=1e-3)
    empty = PixelReport(np.full((2, 2), np.nan), np.full((2, 2), np.nan), np.full((2, 2), np.nan), "D65")
    assert all(np.isnan(v) for v in empty.statistics()["delta_E_2000"].values())


# ---- pixels left out, by cause ------------------------------------------------------------------------------------
def test_screening_counts_each_left_out_pixel_once_by_its_first_cause():
    est = np.full((4, 5, 3), 0.5, np.float32)
    est[0, 0] = np.nan                      # flagged
    est[0, 1, 2] = np.inf                   # non-finite
    est[0, 2] = [np.nan, np.inf, 1e30]      # NaN first: flagged
    est[1, 0, 1] = 1e30                     # out of range
    est[1, 1, 0] = PLAUSIBLE_RANGE[0] - 0.1
    est[1, 2] = [PLAUSIBLE_RANGE[0], PLAUSIBLE_RANGE[1], 0.0]  # the bounds themselves are plausible
    valid, counts = screen_estimate(est)
    assert counts == {"flagged": 2, "non_finite": 1, "out_of_range": 2}
    assert valid.sum() == 20 - 5 and valid[1, 2] and not valid[0, 1]
    with pytest.raises(ValueError, match=r"^cube\.npz: 3 pixels hold values no recovery writes \(1 infinite, 2 "
                                         r"outside the plausible range -1 to 10\), first at row 0, column 1; "):
        screen_estimate(est, invalid="refuse", name="cube.npz")
    assert screen_estimate(np.where(np.isnan(est), est, 0.5), invalid="refuse")[1]["flagged"] == 2  # NaN: fine


@pytest.mark.parametrize("fill", [np.inf, -np.inf, 1e30, -3.0])
def test_rows_no_recovery_writes_are_refused_or_left_out_and_counted_never_scored(fill):
    scene = colorchecker_scene(24, 36)
    cube = truth_cube(scene, GRID) + 0.01
    cube[12, 5:9] += 0.5  # a few bad estimates where the rows will go: leaving the rows out lowers the mean
    flagged = cube.copy()
    flagged[10:] = np.nan
    broken = cube.copy()
    broken[10:] = fill
    with pytest.raises(ValueError, match=r"^c\.exr: 504 pixels hold values no recovery writes"):
        evaluate_pixels(broken, scene, wavelengths=GRID, invalid="refuse", name="c.exr")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow or empty-slice warning on the way
        kept = evaluate_pixels(broken, scene, wavelengths=GRID)
        reference = evaluate_pixels(flagged, scene, wavelengths=GRID)
    cause = "non_finite" if np.isinf(fill) else "out_of_range"
    counts = kept.counts()
    assert counts["pixels"] == 864 and counts["scored"] == 360
    assert counts["excluded"] == {"flagged": 0, "non_finite": 0, "out_of_range": 0, "unscored": 0, cause: 504}
    assert reference.counts()["excluded"]["flagged"] == 504
    for metric, stats in kept.statistics().items():
        for name, value in stats.items():
            assert value == pytest.approx(reference.statistics()[metric][name], rel=1e-6), (metric, name)
    assert np.isnan(kept.rmse[10:]).all() and np.isfinite(kept.rmse[:10]).all()


def test_a_truth_without_a_value_leaves_the_pixel_unscored_and_says_so():
    scene = colorchecker_scene(24, 36)
    cube = truth_cube(scene, GRID)
    scene.reflectance[0, :3] = np.nan
    counts = evaluate_pixels(cube, scene, wavelengths=GRID).counts()
    assert counts["scored"] == 864 - 3 and counts["excluded"]["unscored"] == 3
    assert sum(counts["excluded"].values()) + counts["scored"] == counts["pixels"]


def test_the_report_counts_what_it_left_out_per_pixel_and_per_patch():
    scene = colorchecker_scene(48, 72)
    cube = truth_cube(scene, GRID) + 0.01
    cube[:16] = np.inf  # the first row of patches, all of it, and some border
    with pytest.raises(ValueError, match="first at row 0, column 0"):
        evaluation_report("c.npz", cube, GRID, {}, scene, "D65", DEFAULT_CMFS)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = evaluation_report("c.npz", cube, GRID, {}, scene, "D65", DEFAULT_CMFS, invalid="exclude")
    report = json.loads(json.dumps(result["report"], allow_nan=False))  # no NaN in the JSON: null
    assert report["pixels_total"] == 48 * 72 and report["pixels_scored"] == 32 * 72
    assert report["excluded"] == {"flagged": 0, "non_finite": 16 * 72, "out_of_range": 0, "unscored": 0}
    assert report["plausible_range"] == list(PLAUSIBLE_RANGE)
    rows = {row["patch"]: row for row in report["patches"]}
    assert rows["dark skin"]["rmse"] is None and rows["dark skin"]["pixels"] == 0 and rows["dark skin"]["excluded"] > 0
    assert rows["white 9.5 (.05 D)"]["excluded"] == 0 and rows["white 9.5 (.05 D)"]["rmse"] == pytest.approx(0.01)
    assert report["patches_scored"] == 18 and report["rmse_mean"] == pytest.approx(0.01, rel=1e-4)
    assert report["pixels"]["rmse"]["median"] == pytest.approx(0.01, rel=1e-3)
    line = headline_line(report, result["headline"], True)
    assert "18 of 24 patches scored" in line
    pixels = pixel_line(report, result["pixel_statistics"], True)
    assert pixels.startswith("per pixel under D65: rmse mean 0.01 median 0.01")
    assert pixels.endswith("2304 of 3456 pixels scored, left out: 1152 infinite")
    assert patch_table(report["patches"])[1].split()[-4:] == ["-", "-", "-", str(rows["dark skin"]["excluded"])]


# ---- the truth against the capture the cube records ---------------------------------------------------------------
@pytest.fixture
def captures(tmp_path):
    """Two tiny capture folders, the first with a motion truth per sequence (two sequences)."""
    records = [{"frame_id": i, "pattern_index": i % 2, "exposure_s": 0.01, "timestamp_s": 0.02 * i} for i in range(4)]
    folders = []
    for name, value in (("one", 7), ("two", 9)):
        folders.append(write_sequence(tmp_path / name, np.full((4, 2, 3), value, np.uint16), records, plan_hash="ab"))
    (folders[0] / TRUTH_FOLDER).mkdir()
    for s in range(2):
        write_cube_npz(folders[0] / TRUTH_FOLDER / f"sequence_{s:04d}.npz", np.zeros((2, 3, 2), np.float32),
                       np.array([400.0, 700.0]))
    return folders


def test_a_truth_from_another_capture_or_sequence_or_scene_is_named(captures):
    one, two = captures
    meta = {"sequence_folder": "one", "capture": capture_hash(read_sequence_header(one)[0]), "sequence": 1,
            "sequences_averaged": 1, "scene": "natural:chelsea"}
    moved = SimpleNamespace(name="sequence_0001")
    assert truth_mismatch("c.npz", meta, one, moved) is None
    assert truth_mismatch("c.npz", meta, one / TRUTH_FOLDER / "sequence_0001.npz", moved) is None
    other = truth_mismatch("c.npz", meta, two, moved)
    assert other.startswith(f"c.npz was recovered from one (capture {meta['capture'][:12]}), not from the capture "
                            f"--truth {two} belongs to") and capture_hash([])[:12] not in other
    assert truth_mismatch("c.npz", meta, one / TRUTH_FOLDER / "sequence_0000.npz", moved) == (
        f"c.npz holds sequence 1 of its capture, --truth {one / TRUTH_FOLDER / 'sequence_0000.npz'} is the truth of "
        "sequence 0")
    mean = {**meta, "sequence": None, "sequences_averaged": 2}
    assert "averages 2 sequences" in truth_mismatch("c.npz", mean, one / TRUTH_FOLDER / "sequence_0000.npz", moved)
    scene = SimpleNamespace(name="colorchecker")
    assert truth_mismatch("c.npz", meta, "colorchecker", scene) == (
        "c.npz was recovered from one, a capture of scene 'natural:chelsea', not of --truth colorchecker")
    assert truth_mismatch("c.npz", {**meta, "scene": "colorchecker"}, "colorchecker", scene) is None
    assert truth_mismatch("c.npz", {}, two, moved) is None  # a cube that records nothing is taken as it is
