"""The dense flow (``--motion flow``): tile velocities against known motions, the field, the choice of decoding per
pixel, and the flow recovery on the moving twin against its truth."""

from __future__ import annotations

import numpy as np
import pytest
from moving_helpers import frames_of, moving_setup
from scipy import ndimage

from specgpu.core.mask import Mask
from specgpu.engine import consistency as consistency_module
from specgpu.engine.warp_map import apply_linear_warped
from specgpu.motion.estimate import at_reference_time
from specgpu.motion.flow import TileMotion, choose_flow, flow_field, tile_motion
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.motion.images import frame_gradients
from specgpu.pipeline.moving_decode import check_motion_options
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.planning.registry import make_plan
from specgpu.rig.motion import MotionParameters


@pytest.fixture(scope="module")
def setup():
    return moving_setup()


def textured(rng, h, w):
    return np.abs(ndimage.gaussian_filter(rng.normal(0, 1, (h, w)), 1.2)).astype(np.float32)


def shifted(image, dx, dy):
    """``image`` whose content moved by (dx, dy) px (bilinear; edges repeated)."""
    h, w = image.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return ndimage.map_coordinates(image, [yy - dy, xx - dx], order=1, mode="nearest").astype(np.float32)


@pytest.mark.parametrize("K, ref", [(7, 3), (7, 1), (6, 2), (6, 3)])
def test_tiles_find_the_velocity_of_a_part_that_moves_on_its_own(K, ref):
    """Gradient-like images whose right half moves 2.5 px per frame to the left relative to the left half, which
    drifts with the global translation: the right half's tiles measure -2.5 px/frame, the left half's 0, the error
    of the global translation given is found, and the field is the truth, whichever frame the tiles are cut from
    (the middle one or not, K odd or even)."""
    rng = np.random.default_rng(K + 10 * ref)
    h, w = 192, 288
    base = textured(rng, h, w + 60)
    mid = (K - 1) / 2.0  # the reference time
    shifts = np.array([[0.7 * (k - mid), -0.4 * (k - mid)] for k in range(K)])
    grads = []
    for k in range(K):
        left = shifted(base, *shifts[k])[:, :w]
        right = shifted(base, shifts[k, 0] - 2.5 * (k - mid), shifts[k, 1])[:, 30:w + 30]
        grads.append(np.where(np.arange(w) < w // 2, left, right) + rng.uniform(0, 0.01, (h, w)).astype(np.float32))
    # the global estimate given is off by up to a pixel, differently in each frame (as a rotation's whole-image
    # correlation is), and exact at the reference time, where an estimate's displacements are zero by definition
    error = rng.uniform(-0.9, 0.9, (K, 2))
    error -= at_reference_time(error)
    motion = tile_motion(grads, shifts + error, ref, np.ones(K, bool), tile_px=48)
    v = motion.velocity
    # border tiles the motion takes off the field in the frames furthest from the reference are not measured
    assert v.shape == (4, 6, 2) and motion.measured.mean() > 0.7
    # the tiles straddling the boundary (columns 2 and 3 of 6 hold both halves) take either motion; a motion steady
    # in time can sit in the velocities or in the frames' corrections (the field is the same), so the halves are
    # compared with each other, and the left half's whole motion with the error it corrects
    np.testing.assert_allclose(v[:, :2], np.broadcast_to(v[0, 0], (4, 2, 2)), atol=0.1)
    np.testing.assert_allclose(v[:, 4:, 0] - v[0, 0, 0], -2.5, atol=0.1)
    np.testing.assert_allclose(v[:, 4:, 1] - v[0, 0, 1], 0.0, atol=0.1)
    t = np.arange(K) - ref
    np.testing.assert_allclose(motion.correction + v[0, 0] * t[:, None], -(error - error[ref]), atol=0.1)
    flow = flow_field(motion, shifts + error, (h, w))
    for k in range(K):  # well inside each half, a tile away from the boundary
        np.testing.assert_allclose(flow[k, :, 20:-20, 20:80], shifts[k][:, None, None] + 0 * flow[k, :, 20:-20, 20:80],
                                   atol=0.15)
        np.testing.assert_allclose(flow[k, 0, 20:-20, 220:270], shifts[k, 0] - 2.5 * (k - mid), atol=0.15)


def test_a_tile_without_structure_is_not_measured_and_takes_its_neighbours_velocity():
    """A clipped region (no gradient at all) moves with the rest: its tiles have no peak to trust, so they are not
    measured and take the measured tiles' velocity rather than the rounding of where they were looked for."""
    rng = np.random.default_rng(3)
    K, h, w = 7, 192, 288
    base = textured(rng, h, w)
    shifts = np.array([[1.3 * (k - 3), 0.0] for k in range(K)])
    grads = [shifted(base, shifts[k, 0] - 2.0 * (k - 3), 0.0) for k in range(K)]
    for g in grads:
        g[:, :96] = 0.0
    motion = tile_motion(grads, shifts, 3, np.ones(K, bool), tile_px=48)
    assert not motion.measured[:, :2].any() and motion.measured[:, 3:].all()
    np.testing.assert_allclose(motion.velocity[..., 0], -2.0, atol=0.1)


def test_bad_arguments_of_the_flow_are_refused_in_one_line():
    g = [np.ones((48, 48), np.float32)] * 4
    with pytest.raises(ValueError, match="one gradient image, one"):
        tile_motion(g, np.zeros((3, 2)), 1, np.ones(4, bool))
    with pytest.raises(ValueError, match="reference_frame 5"):
        tile_motion(g, np.zeros((4, 2)), 5, np.ones(4, bool))
    motion = TileMotion((np.array([23.5]), np.array([23.5])), np.zeros((1, 1, 2)), np.ones((1, 1), bool),
                        np.zeros((3, 2)))
    with pytest.raises(ValueError, match="same K"):
        flow_field(motion, np.zeros((4, 2)), (48, 48))


def test_the_field_is_the_global_shift_plus_velocity_times_time():
    K, h, w = 5, 40, 60
    shifts = np.array([[k - 2.0, 0.5 * (k - 2.0)] for k in range(K)])
    velocity = np.zeros((2, 3, 2))
    velocity[:, :, 0] = [[0.0, 1.0, 2.0]] * 2  # a velocity rising along x between the tiles' centres
    motion = TileMotion((np.array([9.5, 29.5]), np.array([9.5, 29.5, 49.5])), velocity, np.ones((2, 3), bool),
                        np.zeros((K, 2)))
    flow = flow_field(motion, shifts, (h, w))
    assert flow.shape == (K, 2, h, w) and flow.dtype == np.float32
    x = np.arange(w)
    v_x = np.clip((x - 9.5) / 20.0, 0.0, 2.0)  # linear between the centres, the outer value beyond them
    for k in range(K):
        np.testing.assert_allclose(flow[k, 0], np.broadcast_to(shifts[k, 0] + v_x * (k - 2), (h, w)), atol=1e-5)
        np.testing.assert_allclose(flow[k, 1], np.full((h, w), shifts[k, 1]), atol=1e-6)
    motion.correction = np.array([[0.3, 0.0]] * K)  # the same for every frame: nothing at the reference time
    np.testing.assert_allclose(flow_field(motion, shifts, (h, w)), flow, atol=1e-6)
    motion.correction = np.zeros((K, 2))
    motion.correction[1] = [0.3, -0.2]  # frame 1 only: it moves by that, the others stay
    moved = flow_field(motion, shifts, (h, w))
    np.testing.assert_allclose(moved[1] - flow[1], np.broadcast_to(np.array([0.3, -0.2])[:, None, None], (2, h, w)),
                               atol=1e-5)
    np.testing.assert_allclose(np.delete(moved, 1, axis=0), np.delete(flow, 1, axis=0), atol=1e-6)


def test_the_flow_is_chosen_where_it_is_consistent_and_the_global_decoding_is_not_clearly_better():
    mask = np.array([[Mask.INCONSISTENT, 0, 0, 0, Mask.INCONSISTENT, 0]], np.uint8)
    textured_g = np.array([[True, True, False, True, True, True]])
    worst_g = np.array([[0.1, 0.9, 1.0, 0.6, 0.1, 0.5]], np.float32)
    textured_f = np.array([[True, True, True, True, True, False]])
    worst_f = np.array([[0.8, 0.65, 0.9, 0.45, 0.2, 1.0]], np.float32)
    mask_f = np.zeros_like(mask)
    held = np.zeros(mask.shape, bool)
    use = choose_flow(mask, (textured_g, worst_g), mask_f, (textured_f, worst_f), held, threshold=0.3,
                      inconsistent=Mask.INCONSISTENT)
    # flagged globally, consistent under the flow: flow; global better correlated by more than the margin (0.2):
    # global; global untextured: flow; global better by less than the margin: flow; inconsistent under both:
    # neither; flow untextured and global textured: global
    assert use.tolist() == [[True, False, True, True, False, False]]
    held[0, 3] = True  # an object layer's pixel: taken by the flow only where its frames agree, textured
    use = choose_flow(mask, (textured_g, worst_g), mask_f, (textured_f, worst_f), held, threshold=0.3,
                      inconsistent=Mask.INCONSISTENT)
    assert use.tolist() == [[True, False, True, True, False, False]]
    textured_f[0, 3] = False  # no evidence under the flow: the layer keeps it
    mask_f[0, 2] = 4  # the flow saw this one outside the field
    use = choose_flow(mask, (textured_g, worst_g), mask_f, (textured_f, worst_f), held, threshold=0.3,
                      inconsistent=Mask.INCONSISTENT)
    assert use.tolist() == [[True, False, False, False, False, False]]


def test_a_rotation_is_followed_by_the_flow_where_a_translation_is_flagged(setup):
    """A rotation of 0.3 deg per frame: the global translation leaves much of the field flagged; the flow decodes
    most of it, and its displacement per pixel is the rotation's."""
    desc, bundle, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, MotionParameters(rotation_deg_per_frame=0.3))
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    kw = dict(dark=dark, gain=gain, saturation=float(bundle.max_code))
    glob = recover_moving(frames, plan.A, **kw)
    flow = recover_moving(frames, plan.A, model="flow", **kw)
    K, h, w = frames.shape
    est = flow.estimates[0]
    assert est.model == "flow" and est.shifts.shape == (K, 2, h, w)
    yy, xx = np.mgrid[0:h, 0:w]
    M = truth["maps"]
    true = np.stack([np.stack([M[k, 0, 0] * xx + M[k, 0, 1] * yy + M[k, 0, 2] - xx,
                               M[k, 1, 0] * xx + M[k, 1, 1] * yy + M[k, 1, 2] - yy]) for k in range(K)])
    decoded = np.isfinite(flow.y[..., 0])
    err = np.abs(est.shifts - true).max(axis=1)[:, decoded]
    err_global = np.abs(glob.estimates[0].shifts[:, :, None] - true[:, :, decoded]).max(axis=1)
    assert np.median(err) < 0.2 and np.percentile(err, 90) < 0.5 * np.percentile(err_global, 90)
    flagged_g, flagged_f = (glob.mask & Mask.INCONSISTENT) > 0, (flow.mask & Mask.INCONSISTENT) > 0
    assert flagged_g.mean() > 0.01 and flagged_f.mean() < 0.5 * flagged_g.mean(), (flagged_g.mean(), flagged_f.mean())
    ow = np.isfinite(flow.y).all(axis=2) & np.isfinite(glob.y).all(axis=2)
    np.testing.assert_array_equal(np.isnan(flow.y[..., 0]), (flow.mask & (1 | 4 | Mask.INCONSISTENT)) > 0)
    assert ow.mean() > 0.5


def test_a_plain_translation_gives_the_same_decoding_as_global(setup):
    """Nothing moves on its own: the tiles measure no velocity of their own, and the flow recovery is the
    global one to within the noise of their velocities (a few hundredths of a px per frame)."""
    desc, bundle, plan, scene = setup
    frames, _ = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=(2.0, 1.0)))
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    kw = dict(dark=dark, gain=gain, saturation=float(bundle.max_code))
    est = estimate_global_motion(frames, dark, gain)
    motion = tile_motion(frame_gradients(frames, dark, gain, est.gradients), est.shifts, est.reference_frame,
                         est.registered)
    assert np.abs(motion.velocity).max() < 0.15
    glob, flow = recover_moving(frames, plan.A, **kw), recover_moving(frames, plan.A, model="flow", **kw)
    both = np.isfinite(glob.y[..., 0]) & np.isfinite(flow.y[..., 0])
    assert both.mean() > 0.9
    diff = np.abs(glob.y[both] - flow.y[both])
    assert np.percentile(diff, 99) < 0.02 * np.abs(glob.y[both]).max() and np.median(diff) < 0.002


def test_what_a_flow_cannot_take_is_refused_in_one_line(setup):
    desc, bundle, plan, scene = setup
    frames, _ = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=(1.0, 0.0)))
    with pytest.raises(ValueError, match="reference frames"):
        recover_moving(frames, plan.A, model="flow", reference_frames=[0])
    with pytest.raises(ValueError, match="at least 4 frames"):
        recover_moving(frames[:3], plan.A[:, :3], model="flow")
    with pytest.raises(ValueError, match="give shifts with the translation or affine"):
        recover_moving(frames, plan.A, model="flow", shifts=np.zeros((plan.K, 2)))


def test_without_the_check_every_pixel_takes_the_flow(setup):
    desc, bundle, plan, scene = setup
    frames, _ = frames_of(desc, plan, scene, MotionParameters(rotation_deg_per_frame=0.3))
    dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
    res = recover_moving(frames, plan.A, dark=dark, gain=gain, model="flow", check=False)
    est = res.estimates[0]
    want = apply_linear_warped(frames, plan.A, est.shifts, dark, gain, return_mask=True)
    np.testing.assert_array_equal(res.mask, want.mask)
    np.testing.assert_allclose(res.y, np.where((want.mask & 1)[..., None] > 0, np.nan, want.y), rtol=1e-6,
                               atol=1e-7)
    assert np.ptp(est.shifts[0, 0]) > 1.0  # a rotation: the displacement varies over the field


def test_the_flow_check_runs_on_the_device(monkeypatch, setup):
    """A flow recovery's consistency checks (the global one and the flow's) are the device's: the host's reference
    computation is never called."""
    def refuse(*_a, **_k):
        raise AssertionError("the host's consistency check ran")

    monkeypatch.setattr(consistency_module, "consistency_maps_numpy", refuse)
    desc, bundle, plan, scene = setup
    frames, _ = frames_of(desc, plan, scene, MotionParameters(rotation_deg_per_frame=0.3))
    res = recover_moving(frames, plan.A, dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field,
                         model="flow")
    assert res.estimates[0].model == "flow" and np.isfinite(res.y[..., 0]).mean() > 0.9


def test_a_plan_too_short_for_a_flow_is_refused_in_one_line(setup):
    _, bundle, _, _ = setup
    short = make_plan("narrowband", bundle, step_nm=150.0, max_exposure_s=0.0049)
    assert short.K == 3
    with pytest.raises(ValueError, match="--motion flow needs a plan of at least 4 frames"):
        check_motion_options("flow", short)
    assert check_motion_options("global", short) == "global"
