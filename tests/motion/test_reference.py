"""Motion from a plan's broadband reference frames (``specgpu plan --reference-every``) on the moving twin."""

from __future__ import annotations

import numpy as np
import pytest
from moving_helpers import frames_of, moving_setup

from specgpu.core.mask import Mask
from specgpu.engine.linear_map import apply_linear
from specgpu.motion.reference import check_reference_frames, estimate_reference_motion, interpolate_in_time
from specgpu.pipeline.moving_decode import warped_sigma_rms
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.estimators import NoiseModel, with_estimator
from specgpu.planning.reference_frames import pattern_indices, reference_indices, with_reference_frames
from specgpu.rig.motion import MotionParameters


@pytest.fixture(scope="module")
def setup():
    """(rig description, calibration, the 7-band plan, it with a reference frame every 3, the natural scene)."""
    desc, bundle, plan, scene = moving_setup()
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))  # sigmas
    return desc, bundle, plan, with_reference_frames(plan, bundle, 3), scene


@pytest.mark.parametrize("velocity", [(3.0, 1.0), (-0.37, 1.21), (8.0, -6.0)])
def test_a_translation_registers_from_the_reference_frames_within_a_tenth_of_a_pixel(setup, velocity):
    desc, bundle, _, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=velocity))
    refs = reference_indices(plan)
    assert refs == [0, 4, 8, 10]
    est = estimate_reference_motion(frames, refs, bundle.dark_at(plan.exposure_s), bundle.flat_field)
    # only the reference frames were registered; every frame's displacement is within 0.1 px of the truth
    assert np.flatnonzero(est.registered).tolist() == refs
    assert est.reference_frame == 4  # the reference frame nearest the middle (frame 5) of 11
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)
    assert np.all(est.error[refs] < 0.9)


def test_a_still_scene_registers_at_zero(setup):
    desc, bundle, _, plan, scene = setup
    frames, _ = frames_of(desc, plan, scene, MotionParameters())
    est = estimate_reference_motion(frames, reference_indices(plan), bundle.dark_at(plan.exposure_s),
                                    bundle.flat_field)
    assert np.abs(est.shifts).max() <= 0.05


def test_a_rotation_is_followed_by_the_affine_maps(setup):
    desc, bundle, _, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, MotionParameters(rotation_deg_per_frame=0.2))
    est = estimate_reference_motion(frames, reference_indices(plan), bundle.dark_at(plan.exposure_s),
                                    bundle.flat_field, model="affine")
    h, w = frames.shape[1:]
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float)
    moved = np.abs(np.einsum("kij,cj->kci", truth["maps"] - np.eye(2, 3), corners)).max()
    err = np.abs(np.einsum("kij,cj->kci", est.shifts - truth["maps"], corners)).max()
    # 0.2 deg a frame moves the corners 0.55 px a frame, 2.8 px by the ends; the 4 x 4 tiles of a 320 x 240 field
    # fit the maps to 0.4 px at the corners (registering every frame across spectra: 0.84)
    assert moved > 2.5 and err < 0.45


def test_interpolation_in_time_is_exact_for_steady_and_quadratic_motion():
    t = np.array([0.0, 4.0, 8.0, 10.0])
    at = np.arange(11.0)
    steady = np.stack([2.0 * t + 1.0, -0.5 * t], axis=1)
    for kind in ("cubic", "linear"):
        np.testing.assert_allclose(interpolate_in_time(t, steady, at, kind), np.stack([2.0 * at + 1.0, -0.5 * at], 1),
                                   atol=1e-12)
    np.testing.assert_allclose(interpolate_in_time(t, 0.1 * t**2, at), 0.1 * at**2, atol=1e-12)
    np.testing.assert_allclose(interpolate_in_time(t[:2], t[:2] * 3.0, at), at * 3.0, atol=1e-12)
    with pytest.raises(ValueError, match="cubic or linear"):
        interpolate_in_time(t, steady, at, "nearest")


def test_reference_frames_are_checked():
    assert check_reference_frames([8, 0, 4, 4], 9) == [0, 4, 8]
    for bad in ([3], [0, 9], [-1, 2]):
        with pytest.raises(ValueError, match="at least two frames of the sequence's 9"):
            check_reference_frames(bad, 9)


def test_a_still_decode_with_reference_frames_is_the_decode_of_the_pattern_frames_alone(setup):
    desc, bundle, bare, plan, scene = setup
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    frames, _ = frames_of(desc, plan, scene, MotionParameters())
    pats = pattern_indices(plan)
    alone = apply_linear(frames[pats], bare.A, dark, gain)
    np.testing.assert_allclose(apply_linear(frames, plan.A, dark, gain), alone, rtol=1e-5, atol=1e-6)
    # the compensated decode at no motion reads the same samples: no pixel outside, saturated or flagged
    res = recover_moving(frames, plan.A, dark=dark, gain=gain, saturation=float(bundle.max_code),
                         shifts=np.zeros((plan.K, 2)), reference_frames=reference_indices(plan))
    assert not res.mask.any()
    np.testing.assert_allclose(res.y, alone, rtol=1e-4, atol=1e-5)


def test_the_moving_decoder_compensates_from_the_reference_frames(setup):
    desc, bundle, bare, plan, scene = setup
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    frames, truth = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=(3.0, 1.0)))
    still, _ = frames_of(desc, plan, scene, MotionParameters())
    out = SequenceDecoder(plan, bundle, ("cube", "sigma_rms"), motion="global").maps(frames)
    est = out["estimate"]
    assert np.flatnonzero(est.registered).tolist() == reference_indices(plan)
    np.testing.assert_allclose(est.shifts, truth["displacement"], atol=0.1)
    idx = [int(np.argmin(np.abs(scene.wavelengths - w))) for w in plan.output_wavelengths]

    def rmse(y, refl):
        return float(np.sqrt(np.nanmean((y[16:-16, 24:-24] - refl[16:-16, 24:-24][..., idx]) ** 2)))

    e_still = rmse(apply_linear(still, plan.A, dark, gain), scene.reflectance)
    e_moving = rmse(apply_linear(frames, plan.A, dark, gain), truth["reflectance"])
    e_comp = rmse(out["cube"], truth["reflectance"])
    assert e_moving > 2 * e_still and e_comp < 1.3 * e_still
    # the consistency check reads the pattern frames only: few false alarms where the motion is right
    assert ((out["mask"] & Mask.INCONSISTENT) > 0).mean() < 0.02
    # the field's edge is masked as far as the pattern frames (1..9 of 11) saw outside it, not the reference frames
    # (0 and 10 went further: the decoder does not read them)
    outside = (out["mask"] & 4) > 0
    d = truth["displacement"][:, 0]
    pats, refs = d[pattern_indices(plan)], d[reference_indices(plan)]
    lo_pattern, lo_reference = int(np.ceil(-pats.min())) + 1, int(np.floor(-refs.min()))
    assert lo_reference - lo_pattern >= 1
    assert outside[:, : int(np.floor(-pats.min()))].all()
    assert not outside[40:-40, lo_pattern:lo_reference].any()
    assert np.isnan(out["cube"][outside]).all()
    # the noise of the outputs: where they are, and the reference frames' zero columns add none
    decoded = np.isfinite(out["cube"]).all(axis=2)
    assert np.array_equal(np.isfinite(out["sigma_rms"]), decoded)
    bare_sigma = warped_sigma_rms(frames[pattern_indices(plan)], bare, dark, gain,
                                  _Rec(out["estimate"].shifts[pattern_indices(plan)], out["mask"]))
    np.testing.assert_allclose(out["sigma_rms"][decoded], bare_sigma[decoded], rtol=1e-4)


class _Rec:
    """The parts of a MovingRecovery that warped_sigma_rms reads."""

    def __init__(self, shifts, mask):
        self.estimates = [type("E", (), {"shifts": shifts})()]
        self.mask, self.layers = mask, []


@pytest.mark.parametrize("every", [3, 7])
def test_an_object_over_the_scene_gets_its_own_layer_with_reference_frames(setup, every):
    """With two reference frames only (M >= K) as with four: the object is registered in every frame."""
    desc, bundle, bare, _, scene = setup
    plan = with_reference_frames(bare, bundle, every)
    motion = MotionParameters(object="colorchecker", object_velocity_px_per_frame=(3.0, 0.0),
                              object_size_px=(100, 140))
    frames, truth = frames_of(desc, plan, scene, motion)
    res = recover_moving(frames, plan.A, dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field,
                         saturation=float(bundle.max_code), reference_frames=reference_indices(plan))
    assert len(res.layers) == 1
    t = np.arange(plan.K) - (plan.K - 1) / 2.0  # frame periods from the reference time
    np.testing.assert_allclose(res.layers[0].shifts, np.c_[3.0 * t, np.zeros(plan.K)], atol=0.2)
    obj = truth["object_mask"] > 0.5
    # most of the object decoded with its own motion (less the ring the flags grow by about the pixels it cannot
    # decode), as without reference frames
    assert ((res.mask & Mask.LAYER) > 0)[obj].mean() > 0.65
