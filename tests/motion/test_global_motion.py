"""Global motion estimation and motion-compensated recovery on the moving twin."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from moving_helpers import frames_of, moving_setup

from specgpu.core.mask import Mask
from specgpu.engine.consistency import consistency_maps_numpy
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.runtime import get_queue
from specgpu.motion import global_motion
from specgpu.motion.consistency import consistency, inconsistent_pixels
from specgpu.motion.global_motion import MAX_SPEED_PX_PER_FRAME, estimate_global_motion
from specgpu.motion.images import frame_gradients, gradient_image
from specgpu.motion.methods import MOTION_METHODS, check_motion_mode
from specgpu.motion.registration import fit_peak_within, second_peak_ratio
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.moving_layers import grow_flags, recover_moving
from specgpu.pipeline.recovery import default_basis, recover
from specgpu.planning.basis_plans import plan_symmetric_basis
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import colorchecker_scene


@pytest.fixture(scope="module")
def setup():
    return moving_setup()


@pytest.fixture(scope="module")
def rendered(setup):
    """``frames_of`` the module's rig, plan and scene under a motion, rendered once per motion for the module
    (several tests take the same motion, and rendering a moving twin's sequence costs seconds); the frames are
    read-only (a test that edits them edits a copy)."""
    desc, _, plan, scene = setup
    made = {}

    def render(motion):
        if motion not in made:
            frames, truth = frames_of(desc, plan, scene, motion)
            frames.setflags(write=False)
            made[motion] = frames, truth
        return made[motion]

    return render


@pytest.mark.parametrize("motion", [MotionParameters(velocity_px_per_frame=(3.0, 1.0)),
                                    MotionParameters(velocity_px_per_frame=(-0.37, 1.21)),
                                    MotionParameters(vibration_rms_px=0.5, vibration_hz=20.0, seed=2)])
def test_registration_recovers_known_shifts_within_a_tenth_of_a_pixel(setup, motion, rendered):
    desc, bundle, plan, scene = setup
    frames, truth = rendered(motion)
    est = estimate_global_motion(frames, bundle.dark_at(plan.exposure_s), bundle.flat_field)
    assert est.registered.all()
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)
    np.testing.assert_array_equal(est.shifts[plan.K // 2], 0.0)  # odd K: the middle frame is at the reference time


def test_a_still_sequence_registers_at_zero(setup, rendered):
    desc, bundle, plan, scene = setup
    frames, _ = rendered(MotionParameters())
    est = estimate_global_motion(frames, bundle.dark_at(plan.exposure_s), bundle.flat_field)
    assert np.abs(est.shifts).max() <= 0.05


def test_a_dark_frame_is_interpolated_not_registered(setup, rendered):
    desc, bundle, plan, scene = setup
    frames, truth = rendered(MotionParameters(velocity_px_per_frame=(2.0, 0.0)))
    dark = bundle.dark_at(plan.exposure_s)
    frames = frames.copy()
    frames[2] = np.rint(dark).astype(frames.dtype)
    est = estimate_global_motion(frames, dark, bundle.flat_field)
    assert est.registered.tolist() == [k != 2 for k in range(plan.K)]
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)


def test_compensation_brings_the_moving_error_back_to_the_still_one(setup, rendered):
    desc, bundle, plan, scene = setup
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    still, _ = rendered(MotionParameters())
    moving, truth = rendered(MotionParameters(velocity_px_per_frame=(3.0, 1.0)))
    idx = [int(np.argmin(np.abs(scene.wavelengths - w))) for w in plan.output_wavelengths]

    def rmse(y, refl):
        return float(np.sqrt(np.nanmean((y[12:-12, 20:-20] - refl[12:-12, 20:-20][..., idx]) ** 2)))

    e_still = rmse(apply_linear(still, plan.A, dark, gain), scene.reflectance)
    e_moving = rmse(apply_linear(moving, plan.A, dark, gain), truth["reflectance"])
    res = recover_moving(moving, plan.A, dark=dark, gain=gain, saturation=float(bundle.max_code))
    e_comp = rmse(res.y, truth["reflectance"])
    assert e_moving > 2 * e_still
    assert e_comp < 1.3 * e_still
    # the field's edges that some frame did not see are NaN and flagged, the rest is finite
    outside = (res.mask & 4) > 0
    assert outside[:, :9].all() and outside[:, -9:].all() and outside[:3].all() and outside[-3:].all()
    assert not outside[4:-4, 10:-10].any()
    assert np.isnan(res.y[outside]).all() and np.isfinite(res.y[res.mask == 0]).all()
    assert ((res.mask & Mask.INCONSISTENT) > 0).mean() < 0.02  # few false alarms where the motion is right


def test_recover_with_motion_is_recover_moving_of_the_same_frames(setup, rendered):
    desc, bundle, plan, scene = setup
    moving, _ = rendered(MotionParameters(velocity_px_per_frame=(1.5, 0.5)))
    folder = SequenceFolder(Path("<memory>"), moving[None], plan, bundle, [], {})
    y = recover(folder, motion="global")
    # recover registers the motion on its device (the default one), as the stream and the batch do
    ref = recover_moving(moving, plan.A, dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field,
                         saturation=float(bundle.max_code), device=get_queue()).y
    np.testing.assert_array_equal(np.isnan(y), np.isnan(ref))
    np.testing.assert_allclose(y, ref, rtol=1e-6, atol=1e-7)
    two = SequenceFolder(Path("two"), np.stack([moving, moving]), plan, bundle, [], {})
    with pytest.raises(ValueError, match="one sequence at a time"):
        recover(two, motion="global")
    assert np.isfinite(recover(two, motion="global", sequence=1)[120, 160]).all()


def test_motion_modes_are_checked():
    assert check_motion_mode("GLOBAL") == "global" and set(MOTION_METHODS) >= {"none", "global", "affine", "flow"}
    with pytest.raises(ValueError, match="motion='optical' is not one of"):
        check_motion_mode("optical")


def test_an_object_moving_on_its_own_is_flagged_not_decoded(setup, rendered):
    """A chart moving over the still scene: the background's motion is found despite it, and the chart's
    textured pixels, whose frames disagree after compensation, are flagged and NaN; elsewhere almost nothing."""
    desc, bundle, plan, scene = setup
    m = MotionParameters(object="colorchecker", object_velocity_px_per_frame=(3.0, 0.0))
    frames, truth = rendered(m)
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    res = recover_moving(frames, plan.A, dark=dark, gain=gain, saturation=float(bundle.max_code), layers=False)
    np.testing.assert_allclose(res.estimates[0].shifts, 0.0, atol=0.1)  # the background stands still
    flagged = (res.mask & Mask.INCONSISTENT) > 0
    inside = truth["object_mask"] > 0.5
    assert flagged[inside].mean() > 0.15 and flagged[~inside].mean() < 0.03
    assert np.isnan(res.y[flagged]).all()
    still, _ = rendered(MotionParameters(velocity_px_per_frame=(1.0, 0.5)))
    est = estimate_global_motion(still, dark, gain)
    assert inconsistent_pixels(still, est.shifts, dark, gain).mean() < 0.03  # 50 nm bands: their edges differ most


@pytest.fixture(scope="module")
def chart_over_drift(setup, rendered):
    """A chart moving 3 px/frame over a scene drifting (1, 0.5) px/frame (it occludes and uncovers the background):
    the frames, dark, flat field and global estimate."""
    desc, bundle, plan, scene = setup
    m = MotionParameters(velocity_px_per_frame=(1.0, 0.5), object="colorchecker",
                         object_velocity_px_per_frame=(3.0, 0.0))
    frames, _ = rendered(m)
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    return frames, dark, gain, estimate_global_motion(frames, dark, gain)


def test_the_check_on_the_estimates_own_gradient_images_is_the_check_on_fresh_ones(setup, chart_over_drift):
    _, bundle, plan, _ = setup
    frames, dark, gain, est = chart_over_drift
    assert len(est.gradients) == plan.K and all(g.shape == (240, 320) for g in est.gradients)
    reused = inconsistent_pixels(frames, est.shifts, dark, gain, gradients=est.gradients)
    fresh = inconsistent_pixels(frames, est.shifts, dark, gain)
    assert reused.any()
    np.testing.assert_array_equal(reused, fresh)
    res = recover_moving(frames, plan.A, dark=dark, gain=gain, saturation=float(bundle.max_code), layers=False)
    # recover flags what the check flags, grown by the pixel a bilinear sample reads about it
    expected = (res.mask & np.uint8(1 | 2 | 4)) | np.where(fresh, np.uint8(Mask.INCONSISTENT), np.uint8(0))
    grow_flags(expected)
    np.testing.assert_array_equal((res.mask & Mask.INCONSISTENT) > 0, (expected & Mask.INCONSISTENT) > 0)
    assert res.estimates[0].gradients is None  # not kept with the result


def test_the_device_check_flags_what_the_scipy_check_flags_around_an_occluding_object(chart_over_drift):
    """The consistency check runs on the device for translations; on a chart moving over a moving scene (it
    occludes and uncovers the background) its maps are those of the straightforward SciPy computation
    (map_coordinates, median, uniform_filter) on the same gradient images, to float32 rounding."""
    frames, dark, gain, est = chart_over_drift
    textured, worst = consistency(frames, est.shifts, dark, gain, gradients=est.gradients)
    want_textured, want_worst = consistency_maps_numpy(np.stack(est.gradients), est.shifts)
    flagged = textured & (worst < 0.3)
    assert flagged.sum() > 1000
    np.testing.assert_array_equal(textured, want_textured)
    np.testing.assert_array_equal(flagged, want_textured & (want_worst < 0.3))
    # to float32 rounding: where two of a pixel's samples are within rounding of each other the median may take
    # the other (one pixel in 76,800 on this scene)
    close = np.abs(worst - want_worst) <= 1e-3
    assert close.mean() >= 1 - 1e-4, np.flatnonzero(~close.ravel())


def test_a_still_chart_whose_patches_repeat_registers_at_zero(setup):
    """A colour chart is a grid of equal patches: the correlation of two frames has a peak at every multiple of
    the patch pitch, and the highest peak of a frame registered to the reference frame alone, anywhere on the
    surface, lies a whole period off on the stream bench's scene (a chart under a 9-frame basis plan). The rival
    peaks send the estimate to the candidates on one steady motion (still, the prior's), so even the reference
    pairs searched anywhere are right; within the displacements the motion can have reached, and where the period
    is within reach of every pair, too."""
    desc, bundle, _, _ = setup
    plan = plan_symmetric_basis(bundle, default_basis(), m=5, max_exposure_s=0.0049)
    frames, _ = frames_of(desc, plan, colorchecker_scene(240, 320, white_tile=0.99), MotionParameters())
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    trap = estimate_global_motion(frames, dark, gain, pairs="reference", max_speed=None)
    assert np.abs(trap.shifts).max() <= 0.1  # the highest peaks: 50 px off
    assert np.abs(estimate_global_motion(frames, dark, gain, pairs="reference").shifts).max() <= 0.1
    assert np.abs(estimate_global_motion(frames, dark, gain).shifts).max() <= 0.1
    # a period within reach of every pair: the other pairs outvote it
    assert np.abs(estimate_global_motion(frames, dark, gain, max_speed=60.0).shifts).max() <= 0.1


@pytest.mark.parametrize("velocity", [(17.0, 0.0), (18.0, 5.0), (20.0, 3.0), (-30.0, 0.0)])
def test_a_motion_faster_than_the_reach_is_looked_for_anywhere(setup, velocity, rendered):
    """A scene moving faster than MAX_SPEED_PX_PER_FRAME leaves within reach of the peak search only noise, or the
    tail of the true peak on the edge of the reach (17 px a frame); the estimate sees that and searches the whole
    surface, so the shifts are right (searched within reach only they came out 1.5 to 60 px off, and the warp took
    them with a fraction of the field flagged), and the compensated decoding is as good as a still one's."""
    desc, bundle, plan, scene = setup
    assert max(abs(v) for v in velocity) > MAX_SPEED_PX_PER_FRAME
    frames, truth = rendered(MotionParameters(velocity_px_per_frame=velocity))
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    est = estimate_global_motion(frames, dark, gain)
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)
    res = recover_moving(frames, plan.A, dark=dark, gain=gain, saturation=float(bundle.max_code))
    idx = [int(np.argmin(np.abs(scene.wavelengths - w))) for w in plan.output_wavelengths]
    seen = res.mask == 0
    still, _ = rendered(MotionParameters())
    e_still = float(np.sqrt(np.mean((apply_linear(still, plan.A, dark, gain) - scene.reflectance[..., idx]) ** 2)))
    e_comp = float(np.sqrt(np.mean((res.y[seen] - truth["reflectance"][..., idx][seen]) ** 2)))
    assert seen.mean() > 0.4 and e_comp < 1.3 * e_still  # 30 px a frame leaves 0.44 of the field in every frame
    assert ((res.mask & Mask.INCONSISTENT) > 0).mean() < 0.1  # few false alarms: 0.8 % of the field at 20 px, 4.9 at 30


def test_an_object_faster_than_the_reach_over_a_still_scene_leaves_the_scene_still(setup, rendered):
    """A chart moving 25 px a frame over the still scene: its peak lies beyond reach and the scene's within, both
    real (the scene's 0.44-0.73 of the chart's, above BEYOND_REACH), so the whole surface is not searched and the
    scene's motion, none, is the estimate (searched everywhere, the chart's motion was taken, 98 px off)."""
    desc, bundle, plan, scene = setup
    frames, truth = rendered(MotionParameters(object="colorchecker",
                                                                  object_velocity_px_per_frame=(25.0, 0.0)))
    est = estimate_global_motion(frames, bundle.dark_at(plan.exposure_s), bundle.flat_field)
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)
    assert np.abs(truth["displacement"]).max() == 0.0


def test_a_motion_within_reach_is_estimated_once(setup, monkeypatch, rendered):
    """A scene moving within reach never sends the estimate to the whole surface: one estimate, not two."""
    desc, bundle, plan, scene = setup
    frames, truth = rendered(MotionParameters(velocity_px_per_frame=(12.0, -4.0)))
    calls = []
    inner = global_motion.estimate_with_options

    def counted(*args, **kwargs):
        calls.append(args[3].max_speed)  # the options of each search
        return inner(*args, **kwargs)

    monkeypatch.setattr(global_motion, "estimate_with_options", counted)
    est = global_motion.estimate_global_motion(frames, bundle.dark_at(plan.exposure_s), bundle.flat_field)
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.2)  # 36 px out: 0.10 off
    assert calls == [MAX_SPEED_PX_PER_FRAME]
    fast, _ = rendered(MotionParameters(velocity_px_per_frame=(20.0, 3.0)))
    calls.clear()
    global_motion.estimate_global_motion(fast, bundle.dark_at(plan.exposure_s), bundle.flat_field)
    assert calls == [MAX_SPEED_PX_PER_FRAME, None]  # the counter sees the second search


def _two_peaks(h=96, w=128, near=(3.3, -2.6), far=(-40.0, 21.0), far_height=1.5):
    """A periodic surface with a Gaussian peak near zero displacement and a higher one far from it."""
    y = (np.arange(h) + h // 2) % h - h // 2
    x = (np.arange(w) + w // 2) % w - w // 2

    def bump(c, height):
        return height * np.exp(-((x[None, :] - c[0]) ** 2 + (y[:, None] - c[1]) ** 2) / (2 * 1.3 ** 2))

    return (bump(near, 1.0) + bump(far, far_height)).astype(np.float32)


def test_the_peak_is_sought_within_reach_of_the_motion():
    """Within a window of displacements the near peak is found to a hundredth of a pixel and the far, higher one is
    neither taken nor a rival; with no window (or one wide enough to hold it) the far one wins or competes."""
    surface = _two_peaks()
    d, top = fit_peak_within(surface, 10)
    np.testing.assert_allclose(d, [3.3, -2.6], atol=0.01)
    assert top == surface[-3, 3]  # its highest sample, (3, -3)
    assert second_peak_ratio(surface, d, 2, within=10) < 0.2  # its own tail only
    far, _ = fit_peak_within(surface, None)
    np.testing.assert_allclose(far, [-40.0, 21.0], atol=0.01)
    np.testing.assert_allclose(fit_peak_within(surface, 60)[0], far)
    assert second_peak_ratio(surface, d, 2, within=60) == pytest.approx(surface.max() / top)
    assert second_peak_ratio(surface, d, 2) == pytest.approx(second_peak_ratio(surface, d, 2, within=200))


@pytest.mark.parametrize("bad", [0.0, -3.0, float("nan"), float("inf")])
def test_a_max_speed_that_is_not_a_positive_number_is_refused(bad):
    frames = np.ones((3, 16, 16), np.float32)
    with pytest.raises(ValueError, match="max_speed"):
        estimate_global_motion(frames, max_speed=bad)


def test_the_estimate_of_given_gradient_images_is_the_estimate_of_its_own(setup, rendered):
    """Gradient images made elsewhere (the device) are registered as they are: the same shifts as those the
    estimate makes itself, and a set of the wrong length or size is refused in one line."""
    desc, bundle, plan, scene = setup
    frames, _ = rendered(MotionParameters(velocity_px_per_frame=(1.7, -0.6)))
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    own = estimate_global_motion(frames, dark, gain)
    host = [gradient_image(f, dark, gain) for f in frames]  # what the estimate makes itself: the same shifts
    np.testing.assert_array_equal(estimate_global_motion(frames, dark, gain, gradients=host).shifts, own.shifts)
    made = frame_gradients(frames, dark, gain)  # on the device: its own rounding, so close, not equal
    given = estimate_global_motion(frames, dark, gain, gradients=made)
    np.testing.assert_allclose(given.shifts, own.shifts, rtol=0, atol=1e-4)
    with pytest.raises(ValueError, match="one image"):
        estimate_global_motion(frames, dark, gain, gradients=made[:-1])
    with pytest.raises(ValueError, match=r"gradients\[0\]"):
        estimate_global_motion(frames, dark, gain, gradients=[m[:-1] for m in made])


def test_a_nan_gain_reads_as_zero_in_the_registration_image():
    """A gain map whose NaN marks a dead pixel (what the decoders take) gives a finite registration image: one NaN
    would spoil every FFT of the estimate."""
    rng = np.random.default_rng(4)
    frame = rng.uniform(100, 900, (40, 50)).astype(np.float32)
    gain = np.ones((40, 50), np.float32)
    gain[20, 25] = np.nan
    got = gradient_image(frame, None, gain)
    zero = gain.copy()
    zero[20, 25] = 0.0
    assert np.isfinite(got).all()
    np.testing.assert_array_equal(got, gradient_image(frame, None, zero))
