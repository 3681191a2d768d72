"""Per-patch and per-pixel error metrics against NumPy and colour-science references."""

from __future__ import annotations

import colour
import numpy as np
import pytest

from specgpu.core.spectra import DEFAULT_CMFS
from specgpu.pipeline.evaluate import PixelReport, delta_E_per_patch, evaluate_pixels, evaluate_reflectance, \
    patch_means, rmse_per_patch, truth_cube
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
