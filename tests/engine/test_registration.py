"""kernels/register.cl through register_gradients: known sub-pixel shifts and small affine maps recovered on every
device and kernel variant, as scikit-image's upsampled phase correlation and the host's estimate find them; images
with nothing to register reported so; bad input refused in one line."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest
from scipy import ndimage
from skimage.registration import phase_cross_correlation

from specgpu.engine import registration
from specgpu.engine.gradients import gradient_images
from specgpu.engine.registration import register_gradients
from specgpu.motion.global_motion import estimate_global_motion

H, W = 96, 128


def scene(seed: int, margin: int = 24) -> np.ndarray:
    """A textured scene (smoothed noise over a level) larger than the frames by ``margin`` on each side."""
    rng = np.random.default_rng(seed)
    return (ndimage.gaussian_filter(rng.normal(size=(H + 2 * margin, W + 2 * margin)), 2.0) * 400 + 1000)


def frames_seeing(base: np.ndarray, maps: np.ndarray, margin: int = 24) -> np.ndarray:
    """Frames (K, H, W) float32 where frame k sees the scene's point at reference position x (frame px) at
    ``maps[k] @ (x, y, 1)``: frame_k(M_k x) = scene(x), so frame_k(y) = scene(M_k^-1 y) (cubic interpolation)."""
    out = []
    for M in maps:
        inv = np.linalg.inv(M)
        # (row, col) order for ndimage: input index = matrix @ output index + offset, in the scene's padded frame
        A = inv[:2, :2][::-1, ::-1]
        t = inv[:2, 2][::-1] + margin - A @ np.array([margin, margin])
        out.append(ndimage.affine_transform(base, A, offset=t + np.array([0.0, 0.0]), order=3, mode="nearest"))
    return np.stack(out)[:, margin:margin + H, margin:margin + W].astype(np.float32)


def translations(shifts) -> np.ndarray:
    maps = np.tile(np.eye(3), (len(shifts), 1, 1))
    maps[:, :2, 2] = shifts
    return maps


SHIFTS = np.array([[-2.35, 1.6], [-1.1, 0.7], [0.0, 0.0], [0.45, -0.9], [1.3, -1.55], [3.8, 2.25]])


@pytest.fixture(scope="module")
def shifted():
    """Frames of a scene moved by SHIFTS (frame 2 the reference) and their gradient images (host NumPy)."""
    frames = frames_seeing(scene(1), translations(SHIFTS))
    return frames, gradient_images(frames).get()


def test_known_subpixel_shifts_on_every_device_and_variant(queue, kernel_variant, shifted):
    frames, _ = shifted
    grads = gradient_images(frames, device=queue)  # a device array, registered where it is
    got = register_gradients(grads, 2, device=queue)
    assert got.model == "translation" and got.usable.all() and got.reference_frame == 2
    np.testing.assert_allclose(got.to_reference[:, :2, 2], SHIFTS, atol=0.05)
    # MotionEstimate's convention: from the reference time (the middle two frames' mean for K = 6)
    np.testing.assert_allclose(got.shifts, SHIFTS - 0.5 * (SHIFTS[2] + SHIFTS[3]), atol=0.05)
    assert np.all(got.error[[0, 1, 3, 4, 5]] < 0.5) and got.error[2] == 0.0


def test_shifts_agree_with_skimage_and_the_host_estimate(shifted):
    frames, grads = shifted
    got = register_gradients(grads, 2)
    for k in range(len(frames)):
        # skimage's shift registers the moving image to the reference: the content's displacement negated, (y, x)
        shift, _, _ = phase_cross_correlation(grads[2], grads[k], upsample_factor=100, normalization=None)
        np.testing.assert_allclose(got.to_reference[k, :2, 2], -shift[::-1], atol=0.05)
    host = estimate_global_motion(frames, reference_frame=2)
    np.testing.assert_allclose(got.shifts, host.shifts, atol=0.05)


def test_affine_maps_on_every_device(queue):
    angle = np.deg2rad(np.array([-0.6, 0.0, 0.4, 0.8]))
    zoom = np.array([0.995, 1.0, 1.004, 1.008])
    centre = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
    maps = np.tile(np.eye(3), (4, 1, 1))
    for k in range(4):
        c, s = np.cos(angle[k]) * zoom[k], np.sin(angle[k]) * zoom[k]
        maps[k, :2, :2] = [[c, -s], [s, c]]
        maps[k, :2, 2] = centre - maps[k, :2, :2] @ centre + [0.8 * k - 1.2, 0.5 - 0.3 * k]
    maps[1] = np.eye(3)  # the reference
    frames = frames_seeing(scene(2), maps)
    got = register_gradients(gradient_images(frames, device=queue), 1, model="affine", device=queue)
    assert got.usable.all() and got.shifts.shape == (4, 2, 3)
    corners = np.array([[0, 0, 1], [W - 1, 0, 1], [0, H - 1, 1], [W - 1, H - 1, 1]], float).T
    for k in range(4):  # where each map puts the field's corners, within 0.05 px
        np.testing.assert_allclose(got.to_reference[k] @ corners, maps[k] @ corners, atol=0.05)
    # from the reference time: the middle two frames' mean map taken out
    mid = 0.5 * (maps[1] + maps[2])
    np.testing.assert_allclose(got.shifts @ corners, (maps @ np.linalg.inv(mid))[:, :2] @ corners, atol=0.05)


def test_a_shift_beyond_reach_is_found_only_when_looked_for(shifted):
    frames = frames_seeing(scene(3, margin=40), translations([[0.0, 0.0], [19.4, -6.3]]), margin=40)
    grads = gradient_images(frames).get()
    np.testing.assert_allclose(register_gradients(grads, 0, max_speed=None).to_reference[1, :2, 2], [19.4, -6.3],
                               atol=0.05)
    near = register_gradients(grads, 0, max_speed=4.0)  # 4 px per frame: the true shift is out of reach
    assert not (near.usable[1] and np.allclose(near.to_reference[1, :2, 2], [19.4, -6.3], atol=0.5))


def test_a_flat_image_is_reported_unusable_never_shifted(shifted):
    _, grads = shifted
    flat_frame = grads.copy()
    flat_frame[4] = 0.0  # a frame with no structure (the gradient image of a flat frame)
    got = register_gradients(flat_frame, 2)
    assert not got.usable[4] and np.isnan(got.shifts[4]).all() and np.isnan(got.error[4])
    assert got.usable[[0, 1, 2, 3, 5]].all()
    np.testing.assert_allclose(got.to_reference[[0, 1, 3, 5], :2, 2], SHIFTS[[0, 1, 3, 5]], atol=0.05)
    flat_reference = grads.copy()
    flat_reference[2] = 0.0
    got = register_gradients(flat_reference, 2)
    assert not got.usable.any() and np.isnan(got.shifts).all()
    # structure along one direction only (stripes): the motion along them is unknown
    stripes = np.broadcast_to(grads[:, :1, :], grads.shape).copy()
    got = register_gradients(stripes, 2)
    assert not got.usable[[0, 1, 3, 4, 5]].any() and np.isnan(got.shifts[[0, 1, 3, 4, 5]]).all()


@pytest.mark.parametrize("bad, message", [
    (lambda g: g[0], "gradients must be a \\(K, H, W\\)"),
    (lambda g: g[:, :4, :4], "at least 8 x 8"),
    (lambda g: np.where(np.arange(W) == 5, np.nan, g), "gradients hold NaN"),
])
def test_bad_images_are_refused_in_one_line(shifted, bad, message):
    with pytest.raises(ValueError, match=message) as err:
        register_gradients(bad(shifted[1]), 0)
    assert "\n" not in str(err.value)


def test_nan_on_the_device_is_refused(queue, shifted):
    g = shifted[1].copy()
    g[3, 40, 50] = np.inf
    with pytest.raises(ValueError, match="gradients hold NaN or infinite values \\(image 3\\)"):
        register_gradients(cla.to_device(queue, g), 0, device=queue)


@pytest.mark.parametrize("kwargs, message", [
    (dict(reference_frame=6), "reference_frame must be the index of one of the 6"),
    (dict(reference_frame=-1), "reference_frame"),
    (dict(reference_frame=1, model="flow"), "model must be one of translation, affine"),
    (dict(reference_frame=1, max_speed=0.0), "max_speed"),
    (dict(reference_frame=1, finest=9), "finest must be a pyramid level"),
])
def test_bad_arguments_are_named(shifted, kwargs, message):
    with pytest.raises(ValueError, match=message):
        register_gradients(shifted[1], **kwargs)


def test_steady_state_calls_allocate_nothing_on_the_device(queue, shifted, monkeypatch):
    grads = cla.to_device(queue, shifted[1])
    first = register_gradients(grads, 2, device=queue)

    def refuse(*args, **kwargs):
        raise AssertionError("a device buffer was allocated in steady state")

    monkeypatch.setattr(registration.cla, "empty", refuse)
    again = register_gradients(grads, 2, device=queue)
    np.testing.assert_array_equal(again.shifts, first.shifts)
    monkeypatch.undo()
    with pytest.raises(AssertionError, match="allocated"):  # the patch does reach a first call of a new shape
        monkeypatch.setattr(registration.cla, "empty", refuse)
        register_gradients(shifted[1][:, :80, :112], 2, device=queue)
