"""The device estimate's full-resolution steps over a share of the rows (bands of whole rows, not every n-th row):
as close to the truth as every row on scenes whose structure has a period of two rows (a still chart on the twin
at 640 x 480, a texture rendered at half the resolution), which rows taken one in two registered px away."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from specgpu.calibration.bundle import oracle_calibration
from specgpu.engine.registration import _rows_summed
from specgpu.engine.runtime import get_queue
from specgpu.motion import device_estimate
from specgpu.motion.device_estimate import estimate_on_device
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import colorchecker_scene
from specgpu.rig.twin import TwinRig


@pytest.fixture(scope="module")
def q():
    return get_queue()


def worst(shifts, truth) -> float:
    return float(np.abs(np.asarray(shifts, np.float64) - truth).max())


def every_row(frames, dark=None, gain=None, *, device):
    rows = device_estimate.FULL_ROWS_SUMMED
    device_estimate.FULL_ROWS_SUMMED = 1 << 30
    try:
        return estimate_on_device(frames, dark, gain, device=device)
    finally:
        device_estimate.FULL_ROWS_SUMMED = rows


def test_the_estimate_sums_a_share_of_the_rows_at_this_size():
    # what the tests below rely on: at 480 rows the full-resolution steps take about half of them
    stride = max(1, 480 // device_estimate.FULL_ROWS_SUMMED)
    assert stride == 2
    assert 0.4 * 478 <= _rows_summed(480, stride) <= 0.6 * 478
    assert _rows_summed(480, 1) == 478


def test_a_texture_rendered_at_half_resolution_registers_still(q):
    rng = np.random.default_rng(1)
    half = ndimage.gaussian_filter(rng.normal(size=(240, 320)), 1.5) + 3.0
    base = np.repeat(np.repeat(half, 2, axis=0), 2, axis=1)  # each value over 2 x 2 px: edges between row pairs
    frames = np.stack([base * (40.0 + 20.0 * k) + rng.normal(0, 1.0, base.shape) for k in range(9)])
    est = estimate_on_device(frames.astype(np.float32), device=q)
    assert est.registered.all()
    assert worst(est.shifts, 0.0) <= 0.05
    assert worst(est.shifts, every_row(frames.astype(np.float32), device=q).shifts) <= 0.05


@pytest.mark.parametrize("velocity", [(0.0, 0.0), (0.6, -0.9)])
def test_the_twins_chart_at_640_x_480_within_five_hundredths_of_the_truth(q, velocity):
    cam = CameraParameters(roi_width=640, roi_height=480, frame_rate_hz=200.0, exposure_s=0.0049)
    desc = RigDescription(camera=cam)
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=50.0, max_exposure_s=0.0049)
    motion = MotionParameters(velocity_px_per_frame=velocity)
    rig = TwinRig(plan.rig_description(replace(desc, motion=motion)), scene=colorchecker_scene(480, 640), seed=3)
    rig.load_sequence(plan.patterns)
    ts = np.arange(plan.K) * rig.frame_period_s
    frames = np.stack([rig.render(k, k, ts[k])[0] for k in range(plan.K)])
    truth = rig.motion_truth(ts)["displacement"]
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    est = estimate_on_device(frames, dark, gain, device=q)
    host = estimate_global_motion(frames, dark, gain)
    ok = est.registered & host.registered
    assert ok.sum() >= plan.K - 2
    assert worst(est.shifts[ok], truth[ok]) <= 0.05
    assert worst(est.shifts[ok], truth[ok]) <= worst(host.shifts[ok], truth[ok]) + 0.02
