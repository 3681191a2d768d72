"""kernels/consistency.cl through consistency_maps and consistency_from_frames against a float64 NumPy / SciPy
reference, on every device."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from specgpu.engine import consistency as check
from specgpu.engine import kernels
from specgpu.engine.consistency import consistency_from_frames, consistency_maps, consistency_maps_numpy, exact_median
from specgpu.motion.images import gradient_image


def reference(gradients, maps, window=9, texture=0.5, own=4.0):
    """The check in float64: each image sampled at M_k (x, y, 1) (bilinear, coordinates clamped), their median,
    window x window box means (edges repeated), per frame the normalised cross-correlation with the median.
    Returns (vr, level, va (K, H, W), thresholds (K,), ncc (K, H, W))."""
    g = np.asarray(gradients, np.float64)
    K, h, w = g.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    aligned = np.stack([ndimage.map_coordinates(g[k], [m[1, 0] * xx + m[1, 1] * yy + m[1, 2],
                                                      m[0, 0] * xx + m[0, 1] * yy + m[0, 2]], order=1,
                                                mode="nearest") for k, m in enumerate(maps)])
    ref = np.median(aligned, axis=0)

    def box(a):
        return ndimage.uniform_filter(a, window, mode="nearest")

    mr = box(ref)
    vr = np.maximum(box(ref * ref) - mr * mr, 0.0)
    va, ncc = np.empty_like(aligned), np.empty_like(aligned)
    for k in range(K):
        ma = box(aligned[k])
        va[k] = np.maximum(box(aligned[k] ** 2) - ma * ma, 0.0)
        ncc[k] = (box(aligned[k] * ref) - ma * mr) / np.sqrt(np.maximum(va[k] * vr, 1e-30))
    return vr, texture * vr.mean(), va, own * np.median(va.reshape(K, -1), axis=1), ncc


def gradient_like(rng, K, h, w):
    """K positive images with structure at a few pixels' scale (what a gradient image has) and some noise."""
    base = np.abs(ndimage.gaussian_filter(rng.normal(0, 1, (h + 16, w + 16)), 1.5))
    return np.stack([base[8 + dy:8 + dy + h, 8 + dx:8 + dx + w] * rng.uniform(0.5, 2.0)
                     + rng.uniform(0, 0.02, (h, w)) for dy, dx in rng.integers(-3, 4, (K, 2))]).astype(np.float32)


def motions(rng, K, kind):
    maps = np.zeros((K, 2, 3))
    maps[:, 0, 0] = maps[:, 1, 1] = 1.0
    maps[:, :, 2] = rng.uniform(-3.5, 3.5, (K, 2))
    if kind == "affine":
        angle = rng.uniform(-0.02, 0.02, K)
        maps[:, 0, 0] = maps[:, 1, 1] = np.cos(angle)
        maps[:, 0, 1], maps[:, 1, 0] = -np.sin(angle), np.sin(angle)
    return maps


def assert_matches(textured, worst, ref, thorough=True):
    """``textured`` equal and ``worst`` within float32 rounding of the reference, except at pixels whose variance
    lies within 1e-4 (relative) of a threshold (float32 sums put them either side); ``thorough``: the case has
    pixels of every kind (consistent, inconsistent, textured or not)."""
    vr, level, va, thresholds, ncc = ref
    near_texture = np.abs(vr - level) <= 1e-4 * level
    np.testing.assert_array_equal(textured[~near_texture], (vr > level)[~near_texture])
    counts = va > thresholds[:, None, None]
    near_own = (np.abs(va - thresholds[:, None, None]) <= 1e-4 * thresholds[:, None, None]).any(axis=0)
    want = np.where(counts, ncc, 1.0).min(axis=0)
    # a correlation of a frame whose variance is tiny against the reference's is ill-conditioned in float32
    conditioned = ~near_own & (np.where(counts, va, np.inf).min(axis=0) * vr > 1e-6 * vr.max() ** 2)
    assert conditioned.mean() > 0.9 and (~near_own).mean() > 0.99
    assert np.abs(worst - want)[conditioned].max() < 2e-3
    assert worst.dtype == np.float32 and textured.dtype == bool
    if thorough:
        assert (want < 0.3).any() and (want > 0.9).any() and textured.any() and not textured.all()


@pytest.mark.parametrize("K", [5, 6])
@pytest.mark.parametrize("kind", ["translation", "affine"])
def test_device_maps_are_the_float64_check(queue, K, kind):
    rng = np.random.default_rng(K + (kind == "affine"))
    h, w = 57, 83  # a width not a multiple of 8
    g = gradient_like(rng, K, h, w)
    g[1, 20:40, 30:60] = rng.uniform(0, 3, (20, 30))  # an occluder in one frame: some pixels must disagree
    maps = motions(rng, K, kind)
    ref = reference(g, maps)
    assert_matches(*consistency_maps(g, maps, device=queue), ref)
    assert_matches(*consistency_maps_numpy(g, maps), ref)


@pytest.mark.parametrize("window", [5, 7, 11])
def test_other_odd_windows_are_the_float64_check(queue, window):
    rng = np.random.default_rng(window)
    g = gradient_like(rng, 5, 48, 70)
    g[2, 10:30, 20:50] = rng.uniform(0, 3, (20, 30))
    maps = motions(rng, 5, "translation")
    assert_matches(*consistency_maps(list(g), maps, window=window, device=queue), reference(g, maps, window))


def test_translations_given_as_displacements_are_the_maps(queue):
    rng = np.random.default_rng(3)
    g = gradient_like(rng, 5, 40, 83)  # K and width of a program test_device_maps_are_the_float64_check builds
    maps = motions(rng, 5, "translation")
    a = consistency_maps(g, maps[:, :, 2], device=queue)
    b = consistency_maps(g, maps, device=queue)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def flow_reference(gradients, flow, window=9, texture=0.5, own=4.0):
    """:func:`reference` of a dense flow: frame k sampled at (x + flow[k, 0], y + flow[k, 1])."""
    g = np.asarray(gradients, np.float64)
    K, h, w = g.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    # each pixel's own affine map: the identity plus its displacement, sampled through reference's formula
    aligned = np.stack([ndimage.map_coordinates(g[k], [yy + flow[k, 1], xx + flow[k, 0]], order=1, mode="nearest")
                        for k in range(K)])
    flat = np.tile(np.eye(2, 3), (K, 1, 1))  # the aligned images as they are: the rest of reference's check
    return reference(aligned, flat, window, texture, own)


@pytest.mark.parametrize("K", [5, 6])
def test_a_dense_flow_on_the_device_is_the_float64_check(queue, K):
    rng = np.random.default_rng(40 + K)
    h, w = 45, 77
    g = gradient_like(rng, K, h, w)
    g[2, 10:30, 20:50] = rng.uniform(0, 3, (20, 30))
    yy, xx = np.mgrid[0:h, 0:w]
    # a smooth field with a step (two motions), reaching outside the field at the borders
    flow = np.stack([np.stack([rng.uniform(-3, 3) + 0.03 * xx * rng.uniform(-1, 1) + 2.5 * (xx > 40),
                               rng.uniform(-3, 3) + 0.02 * yy * rng.uniform(-1, 1)]) for _ in range(K)])
    ref = flow_reference(g, flow)
    assert_matches(*consistency_maps(g, flow, device=queue), ref)
    assert_matches(*consistency_maps_numpy(g, flow), ref)


def test_an_even_window_is_checked_on_the_host():
    rng = np.random.default_rng(4)
    g = gradient_like(rng, 5, 30, 40)
    motion = rng.uniform(-2, 2, (5, 2))
    got, want = consistency_maps(g, motion, window=8), consistency_maps_numpy(g, motion, window=8)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_bad_arguments_are_refused():
    g = np.ones((3, 10, 12), np.float32)
    with pytest.raises(ValueError, match="motion must be"):
        consistency_maps(g, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="gradients must be"):
        consistency_maps(g[0], np.zeros((3, 2)))
    with pytest.raises(ValueError, match="gradients must be"):
        consistency_maps([g[0], g[1, :5]], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="window must be"):
        consistency_maps(g, np.zeros((3, 2)), window=0)
    frames = np.ones((3, 10, 12), np.uint16)
    with pytest.raises(ValueError, match=r"motion must be \(3, 2\)"):
        consistency_from_frames(frames, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="motion must be finite"):
        consistency_from_frames(frames, np.array([[0.0, 0.0], [np.nan, 1.0], [0.0, 0.0]]))
    with pytest.raises(ValueError, match="frames must be"):
        consistency_from_frames(frames[0], np.zeros((3, 2)))
    with pytest.raises(ValueError, match="dark has shape"):
        consistency_from_frames(frames, np.zeros((3, 2)), dark=np.zeros((10, 13), np.float32))


def strips_launched(monkeypatch) -> list:
    """The names of the consistency kernels launched from now on, in order."""
    names = []
    launch = kernels.launch_range

    def counting(queue, kernel, *args):
        names.append(kernel.function_name)
        return launch(queue, kernel, *args)

    monkeypatch.setattr(kernels, "launch_range", counting)
    return names


def test_gradients_on_the_device_are_read_where_they_are(queue, monkeypatch):
    """A device array is checked in place: the same maps as from NumPy, bit for bit (the same kernels), and the
    field's medians found from the sample's bracket in one pass of the strips."""
    rng = np.random.default_rng(11)
    g = gradient_like(rng, 6, 150, 130)  # sampled in strips (not the whole field)
    g[2, 40:90, 30:80] = rng.uniform(0, 3, (50, 50))
    maps = motions(rng, 6, "translation")
    launched = strips_launched(monkeypatch)
    on_host = consistency_maps(g, maps, device=queue)
    on_device = consistency_maps(cla.to_device(queue, g), maps)
    np.testing.assert_array_equal(on_device[0], on_host[0])
    np.testing.assert_array_equal(on_device[1], on_host[1])
    assert launched.count("consistency_strips") == 2  # once per call: no sample misled
    assert_matches(*on_host, reference(g, maps))


def test_a_misleading_sample_still_gives_the_exact_medians(queue, monkeypatch):
    """Where the sample's strips are not like the field (here the only rows with texture), the field's median of
    some frame's variance is not within the sample's bracket: the strips run again with every value kept, and the
    maps are the exact check's."""
    rng = np.random.default_rng(12)
    K, h, w = 5, 160, 72
    g = rng.uniform(0.0, 0.01, (K, h, w)).astype(np.float32)
    full = h // check._SAMPLE_ROWS
    step = full // check._SAMPLE_STRIPS
    for i in range(check._SAMPLE_STRIPS):  # the sampled strips get all the texture
        y0 = (step // 2 + i * step) * check._SAMPLE_ROWS
        g[:, y0:y0 + check._SAMPLE_ROWS] += np.abs(rng.normal(0, 1, (K, check._SAMPLE_ROWS, w))).astype(np.float32)
    g[1, 30:60, 10:40] = rng.uniform(0, 3, (30, 30))
    maps = motions(rng, K, "translation")
    launched = strips_launched(monkeypatch)
    got = consistency_maps(g, maps, device=queue)
    assert launched.count("consistency_strips") == 2
    assert_matches(*got, reference(g, maps), thorough=False)


@pytest.mark.parametrize("K, window, shape", [(1, 9, (30, 40)), (2, 9, (30, 40)), (16, 9, (70, 90)),
                                              (9, 15, (50, 70)), (9, 3, (50, 70)), (5, 9, (5, 3))])
def test_frame_counts_windows_and_tiny_fields(queue, K, window, shape):
    rng = np.random.default_rng(K * 100 + window)
    g = gradient_like(rng, K, *shape)
    maps = motions(rng, K, "translation")
    textured, worst = consistency_maps(g, maps, window=window, device=queue)
    vr, level, va, thresholds, ncc = reference(g, maps, window)
    np.testing.assert_array_equal(textured, vr > level)
    want = np.where(va > thresholds[:, None, None], ncc, 1.0).min(axis=0)
    assert np.abs(worst - want).max() < 2e-3


@pytest.mark.parametrize("kind", ["translation", "affine", "flow"])
def test_the_check_from_frames_is_the_check_of_their_gradient_images(queue, kind):
    """consistency_from_frames (the gradient images made on the device and never read back; the check's samples
    scaled by each frame's 1 / mean) against the float64 check of the host's gradient_image."""
    rng = np.random.default_rng({"translation": 21, "affine": 22, "flow": 23}[kind])
    K, h, w = 5, 61, 75
    scene = np.abs(ndimage.gaussian_filter(rng.normal(0, 1, (h + 16, w + 16)), 1.5)) * 3000
    frames = np.stack([scene[8 + dy:8 + dy + h, 8 + dx:8 + dx + w] * rng.uniform(0.5, 1.5) + 200
                       + rng.normal(0, 5, (h, w)) for dy, dx in rng.integers(-3, 4, (K, 2))])
    frames[2, 20:40, 25:55] = rng.uniform(200, 6000, (20, 30))
    frames = frames.astype(np.uint16)
    dark = rng.uniform(150, 250, (h, w)).astype(np.float32)
    gain = rng.uniform(0.9, 1.1, (h, w)).astype(np.float32)
    gain[10, 10] = np.nan
    if kind == "flow":
        yy, xx = np.mgrid[0:h, 0:w]
        motion = np.stack([np.stack([rng.uniform(-3, 3) + 0.02 * xx, rng.uniform(-3, 3) + 0.01 * yy])
                           for _ in range(K)])
    else:
        motion = motions(rng, K, kind)
    grads = np.stack([gradient_image(f, dark, gain) for f in frames])
    ref = flow_reference(grads, motion) if kind == "flow" else reference(grads, motion)
    textured, worst, images = consistency_from_frames(frames, motion, dark, gain, return_gradients=True,
                                                      device=queue)
    assert_matches(textured, worst, ref)
    np.testing.assert_allclose(images.get(), grads, rtol=2e-6, atol=2e-6 * float(grads.max()))
    # with the images scaled on the device first (return_gradients): the same maps as without, to rounding
    again = consistency_from_frames(frames, motion, dark, gain, device=queue)
    assert_matches(*again, ref)


def test_frames_on_the_device_and_an_even_window(queue):
    rng = np.random.default_rng(24)
    frames = (rng.uniform(0, 1000, (5, 40, 44)) + 2000 * (np.arange(44) % 7 < 2)).astype(np.float32)
    frames[1, 10:30, 5:25] = rng.uniform(0, 9000, (20, 20))  # an occluder: some pixels disagree
    motion = rng.uniform(-2, 2, (5, 2))
    grads = np.stack([gradient_image(f) for f in frames])
    buffer = cl.Buffer(queue.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=frames)
    got = consistency_from_frames(buffer, motion, shape=frames.shape, dtype=np.float32, device=queue)
    assert_matches(*got, reference(grads, motion_maps(motion)), thorough=False)
    assert (got[1] < 0.3).any() and got[0].any()
    even = consistency_from_frames(cla.to_device(queue, frames), motion, window=8)
    want = consistency_maps_numpy(grads, motion, window=8)
    np.testing.assert_array_equal(even[0], want[0])
    np.testing.assert_allclose(even[1], want[1], atol=1e-4)


def motion_maps(shifts):
    maps = np.tile(np.eye(2, 3), (len(shifts), 1, 1))
    maps[:, :, 2] = shifts
    return maps


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 40000),
       kind=st.sampled_from(["exponential", "few values", "constant", "spikes"]))
def test_exact_median_is_numpys(seed, n, kind):
    rng = np.random.default_rng(seed)
    v = {"exponential": lambda: rng.exponential(1.0, n), "few values": lambda: rng.integers(0, 3, n),
         "constant": lambda: np.full(n, 2.5), "spikes": lambda: np.where(rng.random(n) < 0.5, 0.0, 1e6)}[kind]()
    v = v.astype(np.float32)
    assert exact_median(v) == float(np.median(v))
    assert exact_median(v.reshape(1, -1)[:, ::-1]) == float(np.median(v))
