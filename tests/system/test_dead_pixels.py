"""A dead pixel of the camera (no response to light) through calibration and every decoding path: calibration gives
it the dead-pixel gain (the bundle still loads), and recover, its uncertainty, the stream and the motion-compensated
pass leave its outputs NaN instead of its noise times that gain, while every other pixel is decoded as before."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from specgpu.core.numerics import DEAD_PIXEL_GAIN
from specgpu.pipeline import Stream
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.recovery import recover, uncertainty
from specgpu.pipeline.twin_replay import offline_maps, stream_setup
from specgpu.planning import NoiseModel, smooth_prior, with_estimator
from specgpu.planning.correction import white_gains
from specgpu.rig import camera as camera_module
from specgpu.rig.scene import white_tile_roi

DEAD = (150, 90)  # (row, column) on a patch of the 320 x 240 chart
ROI = white_tile_roi(240, 320)  # the reference white above the chart, with a second dead pixel inside
DEAD_IN_WHITE = (ROI[1] + ROI[3] // 2, ROI[0] + ROI[2] // 2)


@pytest.fixture(scope="module")
def dead():
    """The stream setup's twin (calibration and recording) with one pixel of its camera dead."""
    init = camera_module.Camera.__init__

    def with_a_dead_pixel(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.prnu[DEAD] = 0.0
        self.prnu[DEAD_IN_WHITE] = 0.0

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(camera_module.Camera, "__init__", with_a_dead_pixel)
        s = stream_setup(320, 240, sequences=2, output_step_nm=10.0, white_tile=0.99)
    noise = NoiseModel.from_rig(s.description, s.plan.exposure_s)  # a noise model, for the sigma outputs
    plan = with_estimator(s.plan, s.bundle, "projection", prior=smooth_prior(np.arange(400.0, 700.0 + 1e-9, 5.0)),
                          noise=noise)
    return replace(s, plan=plan)


def only_the_dead_pixels_are_nan(image) -> bool:
    bad = ~np.isfinite(np.asarray(image, np.float64))
    bad = bad.any(axis=-1) if bad.ndim == 3 else bad
    return bool(bad[DEAD]) and bool(bad[DEAD_IN_WHITE]) and int(bad.sum()) == 2


def test_calibration_marks_the_dead_pixel(dead):
    assert dead.bundle.reports["unlit_pixels"] == 2 and dead.bundle.flat_field[DEAD] == DEAD_PIXEL_GAIN
    assert np.sum(dead.bundle.flat_field >= DEAD_PIXEL_GAIN) == 2


def test_recover_and_its_uncertainty_leave_the_dead_pixel_nan(dead):
    maps = offline_maps(dead, 0)
    for name in ("cube", "XYZ", "Lab", "dE"):
        assert only_the_dead_pixels_are_nan(maps[name]), name
    K = dead.plan.K
    folder = SequenceFolder(Path("<memory>"), dead.frames[:K][None], dead.plan, dead.bundle, [], {})
    sigma = uncertainty(folder)[0]
    assert only_the_dead_pixels_are_nan(sigma)


def test_the_stream_leaves_the_dead_pixel_nan_as_recover(dead):
    results = []
    outputs = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma", "sigma_rms", "dE_sigma")

    def keep(result):  # a result's arrays are views of recycled buffers: copied while the sink is called
        results.append(({name: np.array(a) for name, a in result.arrays.items()}, np.array(result.frame_ids)))

    Stream(dead.driver(loops=1), dead.plan, dead.bundle, outputs=outputs, reference=dead.reference, policy="block",
           sinks=[keep]).run()
    assert results
    first, frame_ids = results[0]
    for name in outputs:
        assert only_the_dead_pixels_are_nan(first[name]), name
    expected = offline_maps(dead, dead.recorded_sequence(frame_ids))["cube"]
    np.testing.assert_allclose(np.asarray(first["cube"], np.float32), expected, rtol=2e-3, atol=2e-3)


def test_a_warped_sample_of_the_dead_pixel_is_nan(dead):
    K = dead.plan.K
    frames = dead.frames[:K]
    shifts = np.zeros((K, 2), np.float32)
    shifts[:, 0] = np.linspace(-2.25, 2.25, K)  # frame k seen (k - 4) * 0.56 px to the right
    rec = recover_moving(frames, dead.plan.A, dark=dead.bundle.dark_at(dead.plan.exposure_s),
                         gain=dead.bundle.flat_field, saturation=float(dead.bundle.max_code), shifts=shifts,
                         check=False)
    bad = ~np.isfinite(rec.y).all(axis=-1)
    bad[:, :3] = bad[:, -3:] = False  # samples beyond the field's left and right edges (mask bit 4), not ours
    # an output at x reads frame k at x + d_k (bilinear): it is spoilt where the dead pixel is one of the two
    # columns it interpolates, |x + d_k - c| < 1, for some frame
    reads = {(r, x) for r, c in (DEAD, DEAD_IN_WHITE) for x in range(c - 4, c + 5) for d in shifts[:, 0]
             if abs(x + d - c) < 1.0}
    r, c = DEAD
    assert len(reads) >= 10 and all(bad[p] for p in reads) and int(bad.sum()) == len(reads)
    assert np.isfinite(rec.y[r + 5, c]).all() and np.isfinite(rec.y[r, c + 6]).all()


def test_a_dead_pixel_in_the_reference_white_is_left_out_of_its_mean(dead):
    """Whatever a dead pixel of the white reads (here: near the top of the range, as a stuck one would), it does not
    move the white's gains: the white's mean skips it. Times the dead-pixel gain it would move them by ~15 %."""
    K = dead.plan.K
    frames = dead.frames[:K]
    stuck = frames.copy()
    stuck[(slice(None), *DEAD_IN_WHITE)] = dead.bundle.max_code - 1
    np.testing.assert_allclose(white_gains(stuck, dead.plan, dead.bundle, ROI),
                               white_gains(frames, dead.plan, dead.bundle, ROI), rtol=1e-12)
    folder = SequenceFolder(Path("<memory>"), frames[None], dead.plan, dead.bundle, [], {})
    assert only_the_dead_pixels_are_nan(recover(folder, white_roi=ROI))
