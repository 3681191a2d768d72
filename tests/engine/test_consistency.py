"""kernels/consistency.cl through consistency_maps against a float64 NumPy / SciPy reference, on every device."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from specgpu.engine.consistency import consistency_maps, consistency_maps_numpy, exact_median


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


def assert_matches(textured, worst, ref):
    """``textured`` equal and ``worst`` within float32 rounding of the reference, except at pixels whose variance
    lies within 1e-4 (relative) of a threshold (float32 sums put them either side)."""
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
    g = gradient_like(rng, 7, 40, 48)
    maps = motions(rng, 7, "translation")
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
    with pytest.raises(ValueError, match="window must be"):
        consistency_maps(g, np.zeros((3, 2)), window=0)


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
