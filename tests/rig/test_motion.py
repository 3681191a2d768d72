"""The moving twin: the [motion] table, the trajectory, frames of a moving world against analytic shifts."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.rig import CameraParameters, RigDescription, rig_from_dict
from specgpu.rig.config import dump_rig, load_rig
from specgpu.rig.motion import MOTION_KEYS, MotionParameters, Trajectory, motion_from_table, warp_image
from specgpu.rig.twin import TwinRig

SMALL = CameraParameters(roi_width=320, roi_height=240)


def patterns(rig, k=3):
    return np.arange(k)[:, None] * 40 + np.full((k, rig.light.params.columns), 60, np.int32)


def test_a_still_world_renders_bit_identical_to_the_twin_before_motion_existed():
    """Digest of six frames recorded with the twin as it was before the [motion] table: the static path is
    untouched, with the default table and with an explicit all-zero one."""
    for motion in (MotionParameters(), MotionParameters(vibration_hz=5.0, blur=True)):
        rig = TwinRig(RigDescription(camera=SMALL, scene="natural", motion=motion))
        rig.load_sequence(patterns(rig))
        h = hashlib.sha256()
        for i in range(6):
            h.update(rig.render(i % 3, i, i * rig.frame_period_s)[0].tobytes())
        assert h.hexdigest() == "1b7cd9304532db918a3c7109a66afe991c0486a6ec08ef4e4b1eef74ccc56842"


@pytest.mark.parametrize("v", [(2.0, -1.0), (-3.0, 4.0)])
def test_moving_frames_are_the_still_frames_shifted(v):
    """At a time where the displacement is a whole number of pixels, a moving frame's noise-free signal is the
    still one's shifted (the light's field and the PRNU stay on the sensor)."""
    still = TwinRig(RigDescription(camera=SMALL, scene="natural"))
    moving = TwinRig(RigDescription(camera=SMALL, scene="natural", motion=MotionParameters(velocity_px_per_frame=v)))
    for rig in (still, moving):
        rig.load_sequence(patterns(rig))
    sensor = still.field * still.camera.prnu
    n = 3  # mid-exposure at 3 frame periods: the scene has moved by 3 v
    t = n * moving.frame_period_s - moving.exposure_s / 2
    for k in range(3):
        got = moving.moving_mean(k, t) / sensor
        ref = still.moving_mean(k, t) / sensor
        dx, dy = int(n * v[0]), int(n * v[1])
        shifted = np.roll(ref, (dy, dx), axis=(0, 1))
        inner = (slice(20, -20), slice(20, -20))
        np.testing.assert_allclose(got[inner], shifted[inner], rtol=2e-5, atol=1e-4)
        assert not np.allclose(got[inner], ref[inner], rtol=1e-3)


def test_the_truth_holds_each_frames_displacement_from_the_reference_time():
    rig = TwinRig(RigDescription(camera=SMALL, scene="natural",
                                 motion=MotionParameters(velocity_px_per_frame=(3.0, 1.0))))
    rig.load_sequence(patterns(rig, 5))
    ts = np.arange(5) * rig.frame_period_s
    truth = rig.motion_truth(ts)
    np.testing.assert_allclose(truth["displacement"], (np.arange(5) - 2)[:, None] * [3.0, 1.0], atol=1e-9)
    assert truth["reference_time_s"] == pytest.approx(2 * rig.frame_period_s + rig.exposure_s / 2)
    # the cube at the reference time is the scene shifted by the displacement there
    t_ref = truth["reference_time_s"] / rig.frame_period_s
    d = np.array([3.0, 1.0]) * t_ref
    expected = warp_image(np.ascontiguousarray(rig.scene.reflectance[..., 7]), d)
    np.testing.assert_allclose(truth["reflectance"][..., 7], expected, atol=1e-6)
    still = TwinRig(RigDescription(camera=SMALL, scene="natural")).motion_truth(ts)
    assert np.all(still["displacement"] == 0)


def test_the_object_occludes_the_background_and_moves_with_its_own_velocity():
    m = MotionParameters(object="white", object_size_px=(60, 80), object_velocity_px_per_frame=(4.0, 0.0))
    rig = TwinRig(RigDescription(camera=SMALL, scene="natural", motion=m))
    rig.load_sequence(patterns(rig))
    t = 2 * rig.frame_period_s - rig.exposure_s / 2  # mid-exposure at 2 periods: the object moved 8 px right
    sig = rig.moving_mean(0, t) / (rig.field * rig.camera.prnu)
    white = TwinRig(RigDescription(camera=SMALL, scene="white"))
    white.load_sequence(patterns(white))
    ref = white.moving_mean(0, t) / (white.field * white.camera.prnu)
    inside = (slice(120 - 30 + 1, 120 + 30 - 1), slice(160 - 40 + 8 + 1, 160 + 40 + 8 - 1))
    np.testing.assert_allclose(sig[inside], ref[inside], rtol=1e-4)
    mask = rig.motion_truth([t])["object_mask"]
    assert mask.sum() == pytest.approx(60 * 80, rel=0.02)


def test_vibration_has_the_asked_rms_and_starts_at_rest():
    tr = Trajectory(MotionParameters(vibration_rms_px=0.5, vibration_hz=20.0, seed=3), 200.0)
    d = tr.displacement(np.arange(200_000) * 0.1)
    assert np.all(tr.displacement(0.0) == 0)
    rms = float(np.sqrt(np.mean(np.sum((d - d.mean(axis=0)) ** 2, axis=1))))
    assert rms == pytest.approx(0.5, rel=0.15)
    # band-limited: nothing changes faster than the band allows (|d'| <= sum of 2 pi f a)
    step = np.abs(np.diff(tr.displacement(np.arange(0, 50, 0.01)), axis=0)).max()
    assert step < 0.05


def test_blur_averages_over_the_exposure():
    m = MotionParameters(velocity_px_per_frame=(8.0, 0.0), blur=True)
    tr = Trajectory(m, 200.0)
    times = tr.sample_times(0.0, 0.8)
    assert len(times) == 16 and times.min() > 0 and times.max() < 0.8
    assert len(Trajectory(replace(m, blur=False), 200.0).sample_times(0.0, 0.8)) == 1


def test_motion_round_trips_through_the_rig_toml(tmp_path):
    m = MotionParameters(velocity_px_per_frame=(3.0, 1.0), vibration_rms_px=0.5, blur=True)
    text = dump_rig(RigDescription(motion=m))
    assert "[motion]" in text
    path = tmp_path / "rig.toml"
    path.write_text(text)
    assert load_rig(path).motion == m
    still = dump_rig(RigDescription()).split("[motion]")[1].split("\n[")[0]
    assert "\nvelocity_px_per_frame" not in still and "\n# velocity_px_per_frame = [0.0, 0.0]" in still


def test_motion_errors_name_the_file_and_key(tmp_path):
    for table, words in (({"velocity_px_per_frame": 3.0}, "motion.velocity_px_per_frame"),
                         ({"speed": 1}, "unknown key motion.speed"),
                         ({"blur": 1}, "motion.blur must be true or false"),
                         ({"vibration_hz": 0}, "motion.vibration_hz must be > 0"),
                         ({"object": "missing.npz"}, "motion.object file not found")):
        with pytest.raises(ValueError, match=words) as err:
            rig_from_dict({"motion": table}, source="rig.toml", base_dir=tmp_path)
        assert str(err.value).startswith("rig.toml: ") and "\n" not in str(err.value)


values = st.one_of(st.none(), st.booleans(), st.integers(-1000, 1000), st.floats(allow_nan=True),
                   st.text(max_size=5), st.lists(st.one_of(st.floats(-300, 300), st.booleans(), st.text(max_size=2)),
                                                 max_size=3))


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from(MOTION_KEYS + ("bogus",)), values, max_size=4))
def test_the_motion_parser_accepts_or_names_the_key(table):
    table = {k: v for k, v in table.items() if v is not None}
    try:
        m = motion_from_table(table, "r.toml")
    except ValueError as exc:
        msg = str(exc)
        assert msg.startswith("r.toml: ") and "\n" not in msg
        assert any(f"motion.{k}" in msg for k in table), msg
        return
    assert isinstance(m, MotionParameters)
    assert all(abs(c) <= 200 for c in m.velocity_px_per_frame + m.object_velocity_px_per_frame)


def test_the_true_maps_carry_a_reference_time_point_to_where_each_frame_sees_it():
    """A bright dot rendered at the reference time lands, in frame k's image, where the true map sends it."""
    m = MotionParameters(velocity_px_per_frame=(1.0, -0.5), rotation_deg_per_frame=1.0)
    tr = Trajectory(m, 200.0)
    h, w = 120, 160
    img = np.zeros((h, w), np.float32)
    img[30, 40] = 1.0  # the dot at t = 0 (scene coordinates = image coordinates at t = 0)
    t_ref, t_k = 0.0, 4.0
    seen = warp_image(img, tr.displacement(t_k), float(tr.angle(t_k)))
    y, x = np.unravel_index(np.argmax(seen), seen.shape)
    cy, cx = ndimage_centroid(seen, y, x)
    M = tr.maps([t_k], t_ref, (h, w))[0]
    np.testing.assert_allclose(M @ [40.0, 30.0, 1.0], [cx, cy], atol=0.1)


def ndimage_centroid(img, y, x, r=2):
    win = img[y - r:y + r + 1, x - r:x + r + 1]
    yy, xx = np.mgrid[y - r:y + r + 1, x - r:x + r + 1]
    return float((win * yy).sum() / win.sum()), float((win * xx).sum() / win.sum())


def test_an_object_too_small_for_its_layout_names_the_key_and_the_rig_file(tmp_path):
    """The chart needs 24 x 36 px: a 1 x 1 object is refused with the key and the rig file, not a bare 'height'."""
    desc = rig_from_dict({"camera": {"roi_width": 320, "roi_height": 240},
                          "motion": {"object": "colorchecker", "object_size_px": [1, 1]}}, source="my-rig.toml")
    rig = TwinRig(desc)
    with pytest.raises(ValueError) as err:
        rig.load_sequence(patterns(rig))
        rig.render(0, 0, 0.0)
    msg = str(err.value)
    assert msg.startswith("my-rig.toml: [motion] object 'colorchecker' at object_size_px = [1, 1]: ")
    assert msg.endswith("height must be >= 24, got 1") and "\n" not in msg


@settings(max_examples=60, deadline=None)
@given(h=st.integers(1, 24), w=st.integers(1, 24), dx=st.floats(-40, 40), dy=st.floats(-40, 40),
       whole=st.booleans(), seed=st.integers(0, 2**16))
def test_a_translation_equals_scipys_bilinear_shift_with_the_edges_repeated(h, w, dx, dy, whole, seed):
    """The twin's translation (two linear interpolations by slicing) against scipy's ``ndimage.shift`` at order 1,
    ``mode="nearest"``: shifts past the border, whole and fractional, one image and every channel of a cube."""
    from scipy import ndimage

    if whole:
        dx, dy = float(round(dx)), float(round(dy))
    rng = np.random.default_rng(seed)
    cube = rng.uniform(0.0, 100.0, (h, w, 3)).astype(np.float32)
    moved = warp_image(cube, (dx, dy))
    assert moved.shape == cube.shape and moved.dtype == np.float32
    for c in range(3):
        expected = ndimage.shift(cube[..., c], (dy, dx), order=1, mode="nearest", prefilter=False)
        np.testing.assert_allclose(warp_image(np.ascontiguousarray(cube[..., c]), (dx, dy)), expected, rtol=0,
                                   atol=1e-4)
        np.testing.assert_allclose(moved[..., c], expected, rtol=0, atol=1e-4)


def test_a_turned_cube_moves_every_channel_as_its_own_image():
    rng = np.random.default_rng(3)
    cube = rng.random((30, 40, 4)).astype(np.float32)
    out = np.full_like(cube, np.nan)
    assert warp_image(cube, (1.3, -2.2), 4.0, out) is out
    for c in range(4):
        np.testing.assert_array_equal(out[..., c], warp_image(np.ascontiguousarray(cube[..., c]), (1.3, -2.2), 4.0))


def test_the_truth_cube_is_the_moved_world_band_by_band():
    """The truth of a moving scene with an object (every band moved at once, the object laid over through its
    footprint) is, band by band, the band composed as an image."""
    from specgpu.rig.motion import MovingScene

    rng = np.random.default_rng(5)
    h, w, b = 36, 48, 5
    cube = rng.random((h, w, b)).astype(np.float32)
    obj = np.zeros_like(cube)
    obj[10:20, 12:30] = rng.random((10, 18, b))
    alpha = np.zeros((h, w), np.float32)
    alpha[10:20, 12:30] = 1.0
    params = MotionParameters(velocity_px_per_frame=(1.7, -0.6), object="square",
                              object_velocity_px_per_frame=(-2.3, 1.1))
    scene = MovingScene(Trajectory(params, 100.0), np.zeros((1, h, w), np.float32), None,
                        np.zeros((1, h, w), np.float32), None, alpha)
    for t in (-1.5, 0.0, 2.25):
        truth = scene.reflectance(cube, obj, t)
        assert truth.shape == cube.shape
        for band in range(b):
            np.testing.assert_allclose(
                truth[..., band], scene.compose((cube[..., band].copy(), obj[..., band].copy()), t), atol=1e-6)
        moved_object = truth[np.nonzero(scene._pose(alpha, t, True) == 1.0)]
        assert moved_object.size and not np.allclose(moved_object, scene._pose(cube, t, False)[
            np.nonzero(scene._pose(alpha, t, True) == 1.0)])


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 30), w=st.integers(1, 30), scale=st.floats(0.4, 2.5), seed=st.integers(0, 2**16))
def test_a_magnification_equals_scipys_bilinear_affine_transform(h, w, scale, seed):
    """The twin's lateral colour (a magnification about the centre, one linear interpolation per axis) against
    scipy's ``ndimage.affine_transform`` with the diagonal matrix at order 1, ``mode="nearest"``; every plane of a
    stack magnified alike."""
    from scipy import ndimage

    from specgpu.rig.motion import magnify_image

    stack = np.random.default_rng(seed).uniform(0.0, 100.0, (2, h, w)).astype(np.float32)
    centre = np.array([(h - 1) / 2.0, (w - 1) / 2.0])
    moved = magnify_image(stack, scale)
    assert moved.shape == stack.shape and moved.dtype == np.float32
    for k in range(2):
        expected = ndimage.affine_transform(stack[k], np.array([1.0 / scale, 1.0 / scale]),
                                            offset=centre - centre / scale, order=1, mode="nearest")
        np.testing.assert_allclose(moved[k], expected, rtol=0, atol=1e-4)
        np.testing.assert_allclose(magnify_image(stack[k], scale), expected, rtol=0, atol=1e-4)
