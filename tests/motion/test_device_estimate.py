"""The motion estimate registered on the device (motion.device_estimate), as estimate_motion takes it when given a
device: as close to the truth as the host's estimate on the moving twin and on known shifts, a repeating pattern
never snapped by a period, frames with nothing to register reported so, an object over the scene not followed."""

from __future__ import annotations

import numpy as np
import pytest
from moving_helpers import frames_of, moving_setup
from scipy import ndimage

from specgpu.engine.gradients import gradient_images
from specgpu.engine.registration import register_gradients
from specgpu.engine.runtime import get_queue
from specgpu.motion import methods
from specgpu.motion.device_estimate import estimate_on_device, start_candidates
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.motion.methods import estimate_motion
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import colorchecker_scene


@pytest.fixture(scope="module")
def setup():
    return moving_setup()


@pytest.fixture(scope="module")
def q():
    return get_queue()


def worst(shifts, truth) -> float:
    return float(np.abs(np.asarray(shifts) - truth).max())


@pytest.mark.parametrize("motion", [MotionParameters(),
                                    MotionParameters(velocity_px_per_frame=(3.0, 1.0)),
                                    MotionParameters(velocity_px_per_frame=(-0.37, 1.21)),
                                    MotionParameters(vibration_rms_px=0.5, vibration_hz=20.0, seed=2)])
def test_the_twins_moving_scene_as_close_to_the_truth_as_the_host(setup, q, motion):
    desc, bundle, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, motion)
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    est = estimate_motion(frames, dark, gain, device=q)
    host = estimate_global_motion(frames, dark, gain)
    assert est.registered.all() and est.model == "translation" and est.shifts.shape == (plan.K, 2)
    assert est.reference_frame == host.reference_frame
    np.testing.assert_array_equal(est.shifts[plan.K // 2], 0.0)  # odd K: the middle frame at the reference time
    assert worst(est.shifts, truth["displacement"]) <= 0.12
    assert worst(est.shifts, truth["displacement"]) <= worst(host.shifts, truth["displacement"]) + 0.05
    assert worst(est.shifts, host.shifts) <= 0.12
    # what the consistency check and the object layers read: every frame's gradient image, as the host's
    assert len(est.gradients) == plan.K
    np.testing.assert_allclose(est.gradients[2], host.gradients[2], rtol=1e-4, atol=1e-4)
    assert np.isfinite(est.error).all() and est.error[est.reference_frame] == 0.0


def textured(h: int, w: int, margin: int = 24) -> np.ndarray:
    rng = np.random.default_rng(4)
    return ndimage.gaussian_filter(rng.normal(size=(h + 2 * margin, w + 2 * margin)), 2.0) * 400 + 1000


def test_known_subpixel_shifts_within_five_hundredths_of_the_truth_and_the_host(q):
    shifts = np.array([[-2.35, 1.6], [-1.1, 0.7], [0.0, 0.0], [0.45, -0.9], [1.3, -1.55]])
    base, m = textured(120, 160), 24
    # frame k sees the point x of the middle frame at x + shifts[k]
    frames = np.stack([ndimage.shift(base, (dy, dx), order=3, mode="nearest")[m:m + 120, m:m + 160]
                       for dx, dy in shifts]).astype(np.float32)
    truth = shifts - shifts[2]
    est = estimate_on_device(frames, device=q)
    host = estimate_global_motion(frames)
    assert est.registered.all()
    assert worst(est.shifts, truth) <= 0.05
    assert worst(est.shifts, host.shifts) <= 0.05


def grid_frames(pitch: float, velocity, K: int = 7, h: int = 240, w: int = 320) -> tuple[np.ndarray, np.ndarray]:
    """A grid of equal squares (``pitch`` px, their gaps a fifth of it) moving ``velocity`` px per frame, rendered
    at 4 x and averaged down, blurred a little, with noise: (frames, truth (K, 2) from the middle frame)."""
    out = []
    truth = (np.arange(K) - K // 2)[:, None] * np.asarray(velocity, np.float64)
    # the 4 x grid's coordinates as a column and a row, broadcast: the same squares as a full mesh, a sixth the time
    y, x = np.arange(4 * h)[:, None] / 4.0, np.arange(4 * w)[None, :] / 4.0
    for dx, dy in truth:
        inside = (np.mod(x - dx, pitch) < 0.8 * pitch) & (np.mod(y - dy, pitch) < 0.8 * pitch)
        out.append(1000 + 800 * ndimage.gaussian_filter(inside.reshape(h, 4, w, 4).mean(axis=(1, 3)), 1.0))
    frames = np.stack(out) + np.random.default_rng(1).normal(0, 3, (K, h, w))
    return frames.astype(np.float32), truth


@pytest.mark.parametrize("pitch, velocity", [(24, (3.0, 1.0)), (40, (3.0, -2.0)), (32, (5.0, 0.0))])
def test_a_repeating_grid_is_not_snapped_by_a_period(q, pitch, velocity):
    """A grid's correlation has peaks of nearly the same height a pitch apart, the truth not always the highest:
    the highest taken, frames come out whole periods off; the device estimate takes the peak the steady motion
    of the frames nearer the reference predicts, or leaves a frame unregistered (filled in time)."""
    frames, truth = grid_frames(pitch, velocity)
    plain = register_gradients(gradient_images(frames, device=q), 3, device=q)
    assert np.nanmax(np.abs(plain.shifts - truth)) > pitch / 2  # the trap: a period off
    est = estimate_on_device(frames, device=q)
    assert est.registered.sum() >= 5
    assert worst(est.shifts, truth) <= 0.05


def test_the_twins_chart_moving_is_not_snapped_by_a_patch_pitch(setup, q):
    desc, bundle, plan, _ = setup
    chart = colorchecker_scene(240, 320, white_tile=0.99)
    frames, truth = frames_of(desc, plan, chart, MotionParameters(velocity_px_per_frame=(3.0, 0.0)))
    est = estimate_motion(frames, bundle.dark_at(plan.exposure_s), bundle.flat_field, device=q)
    assert worst(est.shifts, truth["displacement"]) <= 0.1


def test_the_candidate_nearest_the_steady_motion_is_chosen():
    tie = np.array([[-20.0, 0.0, 0.95], [5.0, 0.0, 0.9]])  # the truth (5, 0) the lower of two near-equal peaks
    lone = np.array([[2.6, 0.1, 0.9], [-30.0, 4.0, 0.3]])  # a peak well above the rest: taken as it is
    got = start_candidates([lone, tie], [1, 2])
    np.testing.assert_allclose(got, [[2.6, 0.1], [5.0, 0.0]])  # the prediction from frame 1: 2 x (2.6, 0.1)
    # no frame nearer to go by and no prior: zero motion predicted, 5 four times nearer it than -20: taken; two
    # candidates as far from the prediction: not registered
    np.testing.assert_allclose(start_candidates([tie], [2]), [[5.0, 0.0]])
    even = np.array([[-12.0, 0.0, 0.9], [12.0, 0.0, 0.9]])
    assert np.isnan(start_candidates([even], [2])).all()
    # a prior (the previous sequence's velocity) tells them apart
    np.testing.assert_allclose(start_candidates([even], [2], prior=(5.0, 0.0)), [[12.0, 0.0]])


def test_flat_frames_are_not_registered(q):
    flat = np.full((5, 64, 80), 900.0, np.float32)
    est = estimate_motion(flat, device=q)
    assert not est.registered.any() and np.all(est.shifts == 0.0) and np.isnan(est.error).all()
    base, m = textured(64, 80), 24
    frames = np.stack([ndimage.shift(base, (0.0, 1.5 * k), order=3, mode="nearest")[m:m + 64, m:m + 80]
                       for k in range(5)]).astype(np.float32)
    frames[4] = 900.0  # one flat frame: filled in time, never a made-up shift
    est = estimate_motion(frames, device=q)
    assert est.registered.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(est.shifts[:, 0], 1.5 * (np.arange(5) - 2), atol=0.05)


def test_a_dark_frame_is_interpolated_not_registered(setup, q):
    desc, bundle, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=(2.0, 0.0)))
    dark = bundle.dark_at(plan.exposure_s)
    frames = frames.copy()
    frames[2] = np.rint(dark).astype(frames.dtype)
    est = estimate_motion(frames, dark, bundle.flat_field, device=q)
    assert est.registered.tolist() == [k != 2 for k in range(plan.K)]
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)


@pytest.mark.parametrize("velocity", [(12.0, -4.0), (20.0, 3.0)])
def test_a_fast_motion_is_found_or_filled_in_time(setup, q, velocity):
    desc, bundle, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=velocity))
    est = estimate_motion(frames, bundle.dark_at(plan.exposure_s), bundle.flat_field, device=q)
    assert est.registered.sum() >= plan.K - 2
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.15)


@pytest.mark.parametrize("motion", [MotionParameters(object="colorchecker", object_velocity_px_per_frame=(3.0, 0.0)),
                                    MotionParameters(velocity_px_per_frame=(1.0, 0.5), object="colorchecker",
                                                     object_velocity_px_per_frame=(3.0, 0.0))])
def test_an_object_over_the_scene_does_not_take_the_estimate_over(setup, q, motion):
    """A chart moving on its own over the scene leads the device's unwhitened correlation; the rival peak of the
    whitened one sends every frame to its tiles, most of which see the scene."""
    desc, bundle, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, motion)
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    plain = register_gradients(gradient_images(frames, dark, gain, device=q), 3, device=q)
    assert np.nanmax(np.abs(plain.shifts - truth["displacement"])) > 2.0  # the chart's motion, unchecked
    est = estimate_motion(frames, dark, gain, device=q)
    assert worst(est.shifts, truth["displacement"]) <= 0.15


def test_the_device_is_used_when_given_and_the_host_without(setup, q, monkeypatch):
    desc, bundle, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=(2.0, 1.0)))
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field

    def refused(*args, **kwargs):
        raise AssertionError("the host estimate ran")

    monkeypatch.setattr(methods, "estimate_global_motion", refused)
    for method in ("global", "flow"):
        est = estimate_motion(frames, dark, gain, method=method, device=q)
        np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)
    affine = estimate_motion(frames, dark, gain, method="affine", device=q)
    assert affine.model == "affine" and affine.shifts.shape == (plan.K, 2, 3)
    np.testing.assert_allclose(affine.shifts[:, :, 2], truth["displacement"], atol=0.15)
    np.testing.assert_allclose(affine.shifts[:, :, :2], np.tile(np.eye(2), (plan.K, 1, 1)), atol=2e-3)
    with pytest.raises(AssertionError, match="the host estimate ran"):
        estimate_motion(frames, dark, gain)  # no device: the host's estimate
    monkeypatch.undo()
    monkeypatch.setattr(methods, "estimate_on_device", lambda *a, **k: None)  # inputs the device cannot take
    est = estimate_motion(frames, dark, gain, device=q)
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.15)
