"""The denoised sigmas of a moving sequence computed on less: the filter's guide noise read through the span of the
decoder's rows (at most K slope images, not B + 3) and ``sigma_rms`` alone as one channel, each equal to the full
computation."""

from __future__ import annotations

import numpy as np
import pytest
from moving_helpers import CAM, moving_setup

import specgpu.pipeline.moving_decode as moving_decode
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.rig import RigDescription
from specgpu.rig.motion import MotionParameters

DENOISE = (2, 1e-4)


@pytest.fixture(scope="module")
def moving_chart():
    """One sequence of a chart drifting (2, 1) px per frame, the 7-band plan with its noise model."""
    from specgpu.pipeline.twin_capture import capture_plan
    from specgpu.rig.scene import colorchecker_scene

    desc, bundle, plan, _ = moving_setup()
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
    moving = RigDescription(camera=CAM, motion=MotionParameters(velocity_px_per_frame=(2.0, 1.0)))
    frames = capture_plan(moving, plan, colorchecker_scene(240, 320, white_tile=0.99), noise_seed=3,
                          calibration=bundle).sequences[0].frames
    return plan, bundle, frames


def maps(plan, bundle, frames, outputs):
    return SequenceDecoder(plan, bundle, outputs, motion="global", denoise=DENOISE).maps(frames)


def test_the_slopes_read_in_the_rows_span_give_the_sigmas_of_every_slope(moving_chart, monkeypatch):
    plan, bundle, frames = moving_chart
    outputs = ("cube", "XYZ", "sigma", "dE_sigma")
    reduced = maps(plan, bundle, frames, outputs)

    def every_slope(rows, terms):  # the identity basis: each of the D slopes read as it is
        return np.eye(rows.shape[0]), terms

    monkeypatch.setattr(moving_decode, "_slope_basis", every_slope)
    full = maps(plan, bundle, frames, outputs)
    for name in ("sigma", "dE_sigma"):
        a, b = reduced[name], full[name]
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        assert np.isfinite(a).mean() > 0.5
        np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), rtol=2e-4, atol=1e-7)


def test_sigma_rms_alone_is_the_rms_of_the_sigma_map(moving_chart):
    plan, bundle, frames = moving_chart
    alone = maps(plan, bundle, frames, ("cube", "sigma_rms"))["sigma_rms"]
    every = maps(plan, bundle, frames, ("cube", "sigma"))["sigma"][..., -1]
    np.testing.assert_array_equal(np.isnan(alone), np.isnan(every))
    assert np.isfinite(alone).mean() > 0.5
    np.testing.assert_allclose(np.nan_to_num(alone), np.nan_to_num(every), rtol=2e-4, atol=1e-7)


@pytest.mark.parametrize("terms", [
    [[(0, 0, 1.0), (3, 5, 0.5)], [(b, b, 1 / 12) for b in range(12)]],
    [[(b, b, 1 / 12) for b in range(12)]],  # sigma_rms alone: the basis turned to its form's eigenvectors
    [[(0, 0, 1.0), (3, 5, 0.5), (2, 2, -0.25)]],  # one channel, not symmetric, of rank below the span's
])
def test_the_rows_span_holds_every_slope(terms):
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(12, 4)) @ rng.normal(size=(4, 9))  # rank 4
    U, reduced = moving_decode._slope_basis(rows, terms)
    assert U.shape[0] == 12 and U.shape[1] <= 4
    np.testing.assert_allclose(U.T @ U, np.eye(U.shape[1]), atol=1e-12)
    if len(terms) == 1:  # a diagonal form: one product per image
        assert all(i == j for i, j, _ in reduced[0]) and len(reduced[0]) == U.shape[1]
    slopes = rng.normal(size=(50, 9)) @ rows.T  # every slope image in the rows' span
    z = slopes @ U
    for channel, mine in zip(terms, reduced):
        want = sum(w * slopes[:, d] * slopes[:, e] for d, e, w in channel)
        got = sum(w * z[:, i] * z[:, j] for i, j, w in mine)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
