"""warp.cl through apply_linear_warped against the float64 NumPy bilinear reference, on every device."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from reference import linear_ref, linear_warp_ref
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.warp_map import MASK_OUTSIDE, apply_linear_warped

EPS32 = np.finfo(np.float32).eps


def tolerance(frames, A, dark=None, gain=None):
    """Float32 rounding of the dot product, plus the sample position x + d_k rounded to float32 (a relative error
    of eps on a coordinate up to the frame size, times the largest step between neighbours)."""
    o = np.abs(np.asarray(frames, np.float64)) + (0 if dark is None else np.abs(dark))
    if gain is not None:
        o = o * np.abs(gain)
    absA = np.abs(np.asarray(A, np.float64))
    scale = np.tensordot(o, absA, axes=(0, 1))
    position = 4 * EPS32 * (max(o.shape[1:]) + 8) * 2 * o.max() * absA.sum(axis=1)
    return (2 * A.shape[1] + 12) * EPS32 * scale + position + 1e-6


@pytest.mark.parametrize("K,B", [(1, 1), (3, 5), (9, 31), (31, 31)])
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_sub_pixel_shifts_match_the_bilinear_reference(queue, K, B, dtype):
    rng = np.random.default_rng(K * 7 + B)
    h, w = 23, 37
    frames = (rng.integers(0, 1000, (K, h, w)) if dtype == np.uint16 else rng.uniform(0, 1, (K, h, w))).astype(dtype)
    A = rng.normal(0, 1, (B, K))
    shifts = rng.uniform(-4, 4, (K, 2))
    dark = rng.uniform(0, 5, (h, w)).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, (h, w)).astype(np.float32)
    got = apply_linear_warped(frames, A, shifts, dark, gain, return_mask=True, device=queue)
    ref, outside = linear_warp_ref(frames, A, shifts.astype(np.float32), dark, gain)
    assert got.y.shape == (h, w, B) and got.y.dtype == np.float32
    np.testing.assert_array_equal((got.mask & MASK_OUTSIDE) > 0, outside)
    assert np.all(np.isnan(got.y[outside])) and np.all(np.isfinite(got.y[~outside]))
    assert np.all(np.abs(got.y[~outside] - ref[~outside]) <= tolerance(frames, A, dark, gain)[~outside])
    assert outside.any() and (~outside).any()


def test_zero_shift_is_the_plain_linear_map(queue):
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 1023, (9, 30, 40)).astype(np.uint16)
    A = rng.normal(0, 1, (31, 9))
    dark = rng.uniform(0, 5, (9, 30, 40)).astype(np.float32)  # one dark frame per frame
    gain = rng.uniform(0.8, 1.2, (30, 40)).astype(np.float32)
    got = apply_linear_warped(frames, A, np.zeros((9, 2)), dark, gain, device=queue)
    plain = apply_linear(frames, A, dark, gain, device=queue)
    np.testing.assert_allclose(got, linear_ref(frames, A, dark, gain), rtol=0,
                               atol=float(np.max(tolerance(frames, A, dark, gain))))
    np.testing.assert_allclose(got, plain, rtol=1e-5, atol=1e-3)


def test_whole_pixel_shifts_move_the_samples_exactly(queue):
    rng = np.random.default_rng(4)
    frames = rng.uniform(0, 100, (2, 20, 30)).astype(np.float32)
    got = apply_linear_warped(frames, np.eye(2), [[0, 0], [3, -2]], device=queue)
    np.testing.assert_array_equal(got[2:, :-3, 0], frames[0, 2:, :-3])
    np.testing.assert_allclose(got[2:, :-3, 1], frames[1, :-2, 3:], rtol=1e-6)
    # a pixel that one frame saw outside the field has no measurement at all: every output NaN
    assert np.isnan(got[:2]).all() and np.isnan(got[:, -3:]).all()


def test_the_reference_agrees_with_scipy_map_coordinates():
    rng = np.random.default_rng(5)
    frames = rng.uniform(0, 1, (2, 16, 18))
    shifts = np.array([[0.3, -0.7], [1.25, 2.5]])
    ref, outside = linear_warp_ref(frames, np.eye(2), shifts)
    yy, xx = np.mgrid[0:16, 0:18].astype(float)
    for k in range(2):
        sp = ndimage.map_coordinates(frames[k], [yy + shifts[k, 1], xx + shifts[k, 0]], order=1, mode="nearest")
        np.testing.assert_allclose(ref[..., k][~outside], sp[~outside], atol=1e-12)


def test_saturation_is_flagged_only_where_a_saturated_sample_is_used(queue):
    frames = np.full((2, 10, 10), 100, np.uint16)
    frames[1, 5, 5] = 1023
    got = apply_linear_warped(frames, np.eye(2), [[0, 0], [1.0, 0.0]], saturation=1023, return_mask=True,
                              device=queue)
    flagged = np.argwhere(got.mask & 1)
    assert flagged.tolist() == [[5, 4]]  # frame 1 at x + 1: pixel (5, 4) reads (5, 5) with weight 1
    half = apply_linear_warped(frames, np.eye(2), [[0, 0], [0.5, 0.0]], saturation=1023, return_mask=True,
                               device=queue)
    assert np.argwhere(half.mask & 1).tolist() == [[5, 4], [5, 5]]


@pytest.mark.parametrize("shifts,words", [(np.zeros((3, 2)), r"shape \(2, 2\)"), ([[0, 0], [np.nan, 0]], "finite"),
                                          ("ab", "must be")])
def test_bad_shifts_are_refused(shifts, words):
    with pytest.raises((ValueError, TypeError), match=words):
        apply_linear_warped(np.zeros((2, 4, 4), np.float32), np.eye(2), shifts)


def test_affine_maps_match_the_reference(queue):
    rng = np.random.default_rng(6)
    frames = rng.uniform(0, 100, (3, 40, 50)).astype(np.float32)
    A = rng.normal(0, 1, (4, 3))
    a = np.radians([0.0, 0.7, -1.2])
    M = np.stack([[[np.cos(t), -np.sin(t), 1.5 + 20 * np.sin(t)], [np.sin(t), np.cos(t), -0.5 - 20 * np.sin(t)]]
                  for t in a])
    got = apply_linear_warped(frames, A, M, return_mask=True, device=queue)
    ref, outside = linear_warp_ref(frames, A, M.astype(np.float32))
    np.testing.assert_array_equal((got.mask & MASK_OUTSIDE) > 0, outside)
    assert np.all(np.abs(got.y[~outside] - ref[~outside]) <= tolerance(frames, A)[~outside])
    translation = np.tile(np.eye(2, 3), (3, 1, 1))
    translation[:, :, 2] = [[0, 0], [1.25, -0.5], [2, 3]]
    np.testing.assert_array_equal(apply_linear_warped(frames, A, translation, device=queue),
                                  apply_linear_warped(frames, A, translation[:, :, 2], device=queue))


def test_a_flow_field_matches_the_reference_and_a_uniform_one_the_translation(queue):
    rng = np.random.default_rng(7)
    K, h, w = 3, 30, 40
    frames = rng.integers(0, 1000, (K, h, w)).astype(np.uint16)
    A = rng.normal(0, 1, (5, K))
    dark = rng.uniform(0, 5, (h, w)).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    flow = np.stack([np.stack([2.5 * np.sin(xx / 7.0 + k), 1.5 * np.cos(yy / 5.0 - k)]) for k in range(K)])
    got = apply_linear_warped(frames, A, flow, dark, return_mask=True, device=queue)
    ref, outside = linear_warp_ref(frames, A, flow.astype(np.float32), dark)
    np.testing.assert_array_equal((got.mask & MASK_OUTSIDE) > 0, outside)
    assert np.all(np.abs(got.y[~outside] - ref[~outside]) <= tolerance(frames, A, dark)[~outside])
    shifts = np.array([[1.25, -0.5], [0.0, 0.0], [-2.0, 0.75]])
    uniform = np.broadcast_to(shifts[:, :, None, None], (K, 2, h, w))
    np.testing.assert_array_equal(apply_linear_warped(frames, A, uniform, dark, device=queue),
                                  apply_linear_warped(frames, A, shifts, dark, device=queue))


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_translations_read_as_rows_are_the_per_pixel_warp(queue, dtype):
    """Translations go through the row kernel (8 pixels per work-item, frames read as vectors; the lanes near the
    field's edges, where a sample point leaves the field, per pixel): the float64 reference, and the same samples,
    flags and NaNs as the per-pixel kernel given the same motion as a flow (a displacement per pixel)."""
    rng = np.random.default_rng(11)
    K, B, h, w = 5, 4, 31, 83  # a width not a multiple of 8: the last work-item of each row is partial
    frames = (rng.integers(0, 1000, (K, h, w)) if dtype == np.uint16 else rng.uniform(0, 1, (K, h, w))).astype(dtype)
    frames[2, 10, 40] = 1000 if dtype == np.uint16 else np.nan  # a saturated / non-finite sample inside
    A = rng.normal(0, 1, (B, K))
    shifts = np.array([[0.0, 0.0], [2.5, -1.25], [-3.7, 0.6], [1.0, 2.0], [0.3, -0.9]])
    dark = rng.uniform(0, 5, (K, h, w)).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, (h, w)).astype(np.float32)
    saturation = 1000.0 if dtype == np.uint16 else None
    rows = apply_linear_warped(frames, A, shifts, dark, gain, saturation=saturation, return_mask=True, device=queue)
    flow = np.broadcast_to(shifts[:, :, None, None], (K, 2, h, w))
    pixels = apply_linear_warped(frames, A, flow, dark, gain, saturation=saturation, return_mask=True, device=queue)
    np.testing.assert_array_equal(rows.mask, pixels.mask)
    np.testing.assert_array_equal(np.isnan(rows.y), np.isnan(pixels.y))
    assert ((rows.mask & 3) > 0).sum() >= 2  # the bad sample flags the pixels that use it
    ref, outside = linear_warp_ref(frames, A, shifts.astype(np.float32), dark, gain)
    good = ~outside & (rows.mask == 0)
    assert good.sum() > 0.5 * h * w
    tol = tolerance(np.nan_to_num(frames), A, dark, gain)[good]
    assert np.all(np.abs(rows.y[good] - ref[good]) <= tol) and np.all(np.abs(pixels.y[good] - ref[good]) <= tol)
    # written as (H, W, B) by the kernel, or as planes (B, H, W) when asked: the same numbers
    planes = apply_linear_warped(frames, A, shifts, dark, gain, saturation=saturation, layout="planar", device=queue)
    np.testing.assert_array_equal(np.moveaxis(planes, 0, -1), rows.y)


@pytest.mark.parametrize("motion", ["affine", "translation"])
def test_a_nan_gain_spoils_exactly_the_outputs_that_sample_it(queue, motion):
    """A NaN gain (a dead pixel) makes NaN every output whose bilinear footprint gives it a weight above zero, and
    no other: the reference with that gain huge instead shows which outputs read it."""
    rng = np.random.default_rng(9)
    frames = rng.uniform(0, 100, (3, 30, 41)).astype(np.float32)
    A = rng.normal(0, 1, (2, 3))
    if motion == "affine":
        a = np.radians([0.0, 0.9, -1.3])
        shifts = np.stack([[[np.cos(t), -np.sin(t), 0.4], [np.sin(t), np.cos(t), -0.7]] for t in a]).astype(np.float32)
    else:
        shifts = np.array([[0.0, 0.0], [1.3, -0.4], [-2.6, 0.75]], np.float32)  # the rows of 8 pixels
    gain = rng.uniform(0.9, 1.1, (30, 41)).astype(np.float32)
    gain[14, 20] = np.nan
    got = apply_linear_warped(frames, A, shifts, None, gain, return_mask=True, device=queue)
    huge = np.where(np.isnan(gain), 1e30, gain)
    ref, outside = linear_warp_ref(frames, A, shifts, gain=huge)
    reads = (np.abs(ref) > 1e12).any(axis=-1) & ~outside
    bad = ~np.isfinite(got.y).all(axis=-1) & ~outside
    assert reads.sum() >= 3 and np.array_equal(bad, reads)
    live = ~reads & ~outside
    ref_live, _ = linear_warp_ref(frames, A, shifts, gain=np.nan_to_num(gain))
    assert np.all(np.abs(got.y[live] - ref_live[live]) <= tolerance(frames, A)[live])
