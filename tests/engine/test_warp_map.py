"""warp.cl through apply_linear_warped against the float64 NumPy bilinear reference, on every device."""

from __future__ import annotations

import numpy as np
import pytest
from reference import linear_ref, linear_warp_ref
from scipy import ndimage

from specgpu.core.mask import Mask
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.warp_map import apply_linear_warped

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


# (K, B, dtype): each (K, B) is a program of its own (the K samples and the B dot products unrolled), and a large
# one takes seconds to compile cold; the dtype acts only on the sample read (its conversion and saturation), the
# same code whatever K and B. So each dtype meets one output, a few outputs and the blocks of 8 outputs with a
# shifted last one (B = 31, K = 9), and the register-unrolled K = 31 x B = 31 build is run once. The 5 x 4 cases
# take a dark frame per frame and uint16 saturation at 1000: the programs of the rows test and the zero-shift test
# below (a dark frame per frame makes the large programs slower to compile: they take one dark map).
SUB_PIXEL_CASES = [(1, 1, np.uint16), (1, 1, np.float32), (5, 4, np.uint16), (5, 4, np.float32),
                   (9, 31, np.float32), (9, 31, np.uint16), (31, 31, np.uint16)]


def test_the_sub_pixel_cases_meet_each_dtype_with_each_output_count():
    for B in {B for _, B, _ in SUB_PIXEL_CASES}:
        assert {np.dtype(d) for _, b, d in SUB_PIXEL_CASES if b == B} == {np.dtype(np.uint16), np.dtype(np.float32)}
    assert (31, 31) in {(K, B) for K, B, _ in SUB_PIXEL_CASES}


@pytest.mark.parametrize("K,B,dtype", SUB_PIXEL_CASES,
                         ids=[f"{np.dtype(d).name}-{K}-{B}" for K, B, d in SUB_PIXEL_CASES])
def test_sub_pixel_shifts_match_the_bilinear_reference(queue, K, B, dtype):
    rng = np.random.default_rng(K * 7 + B)
    h, w = 23, 37
    frames = (rng.integers(0, 1000, (K, h, w)) if dtype == np.uint16 else rng.uniform(0, 1, (K, h, w))).astype(dtype)
    A = rng.normal(0, 1, (B, K))
    shifts = rng.uniform(-4, 4, (K, 2))
    dark = rng.uniform(0, 5, (K, h, w) if (K, B) == (5, 4) else (h, w)).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, (h, w)).astype(np.float32)
    saturation = 1000.0 if dtype == np.uint16 else None  # above every sample
    got = apply_linear_warped(frames, A, shifts, dark, gain, saturation=saturation, return_mask=True, device=queue)
    ref, outside = linear_warp_ref(frames, A, shifts.astype(np.float32), dark, gain)
    assert got.y.shape == (h, w, B) and got.y.dtype == np.float32
    np.testing.assert_array_equal((got.mask & Mask.OUTSIDE) > 0, outside)
    assert np.all(np.isnan(got.y[outside])) and np.all(np.isfinite(got.y[~outside]))
    assert np.all(np.abs(got.y[~outside] - ref[~outside]) <= tolerance(frames, A, dark, gain)[~outside])
    assert outside.any() and (~outside).any()


def test_zero_shift_is_the_plain_linear_map(queue):
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 1000, (5, 30, 40)).astype(np.uint16)
    A = rng.normal(0, 1, (4, 5))
    dark = rng.uniform(0, 5, (5, 30, 40)).astype(np.float32)  # one dark frame per frame
    gain = rng.uniform(0.8, 1.2, (30, 40)).astype(np.float32)
    # 5 frames, 4 outputs, saturation 1000 (above every sample): the program the rows test builds
    got = apply_linear_warped(frames, A, np.zeros((5, 2)), dark, gain, saturation=1000.0, device=queue)
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
    np.testing.assert_array_equal((got.mask & Mask.OUTSIDE) > 0, outside)
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
    np.testing.assert_array_equal((got.mask & Mask.OUTSIDE) > 0, outside)
    assert np.all(np.abs(got.y[~outside] - ref[~outside]) <= tolerance(frames, A, dark)[~outside])
    # a uniform flow is the translation: the per-pixel kernel and the translation path (which sums a tap clamped at
    # the field's edge as two equal taps, and contracts products into FMAs) agree to float32 rounding, with the same
    # NaNs and the same mask
    shifts = np.array([[1.25, -0.5], [0.0, 0.0], [-2.0, 0.75]])
    uniform = np.broadcast_to(shifts[:, :, None, None], (K, 2, h, w))
    per_pixel = apply_linear_warped(frames, A, uniform, dark, return_mask=True, device=queue)
    rows = apply_linear_warped(frames, A, shifts, dark, return_mask=True, device=queue)
    np.testing.assert_array_equal(rows.mask, per_pixel.mask)
    np.testing.assert_array_equal(np.isnan(rows.y), np.isnan(per_pixel.y))
    live = ~np.isnan(rows.y)
    assert np.all(np.abs(rows.y - per_pixel.y)[live] <= tolerance(frames, A, dark)[live])


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_translations_read_as_rows_are_the_per_pixel_warp(queue, dtype):
    """Translations go through the two passes (the frames corrected once, then the warp of the corrected planes 8
    pixels of a row at a time, read as vectors; the taps off the field clamped): the float64 reference, and the
    same flags and NaNs as the per-pixel kernel given the same motion as a flow (a displacement per pixel)."""
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
        shifts = np.array([[0.0, 0.0], [1.3, -0.4], [-2.6, 0.75]], np.float32)  # the two-pass path
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


# ------------------------------------------------------------------------------- the translation path (two passes)

def _per_pixel(frames, A, shifts, dark=None, gain=None, saturation=None, queue=None):
    """The per-pixel kernel (linear_warp) on the same translations given as a uniform flow: the exact semantics of
    the sample points, taps, flags and NaNs the translation path must reproduce."""
    K, h, w = np.shape(frames)
    flow = np.broadcast_to(np.asarray(shifts, np.float64)[:, :, None, None], (K, 2, h, w))
    return apply_linear_warped(frames, A, flow, dark, gain, saturation=saturation, return_mask=True, device=queue)


def _frames_of(rng, dtype, K, h, w):
    if dtype == np.float32:
        frames = rng.uniform(0, 100, (K, h, w)).astype(np.float32)
        frames[1, h // 2, w // 2] = np.nan
        frames[2, (h - 1) // 3, (2 * w) // 3] = np.inf
        frames[3, h - 1, 0] = -np.inf  # on the field's edge: read by clamped taps
        return frames, None
    high = 255 if dtype == np.uint8 else 1023
    frames = rng.integers(0, high - 10, (K, h, w)).astype(dtype)
    frames[1, h // 2, w // 2] = high
    frames[2, 0, w - 1] = high  # a corner: read by clamped taps
    return frames, float(high)


SHIFT_SETS = {
    "sub-pixel": [[0.0, 0.0], [0.3, -0.7], [-1.6, 1.25], [2.75, 0.5]],
    "whole pixels": [[0.0, 0.0], [1.0, -2.0], [-3.0, 0.0], [0.0, 1.0]],
    "half pixels and beyond": [[0.0, 0.0], [-0.5, 0.5], [0.5, -0.5], [9.5, -3.25]],
    # within the 1/1024 px tolerance of the field's edge (inside), and just beyond it
    "at the edge's tolerance": [[0.0, 0.0], [-0.5009, 0.0], [0.0, 0.5009], [0.5011, -0.5011]],
}


SHAPES = [(1, 1), (3, 5), (4, 7), (6, 9), (13, 21), (5, 300), (37, 17)]
DTYPES = [np.uint8, np.uint16, np.float32]
VARIANTS = ["cpu", "gpu"]


def _pairwise_cases():
    """Every shape with every shift set (28 cases), the dtype and kernel variant turning with them so that every
    pair of any two settings (shape, dtype, shift set, variant) is run: the settings act on separate parts of the
    kernel (the work shape's edges, the sample type and its saturation, the taps), so the full grid of their 168
    combinations adds no case these pairs miss."""
    sets = list(SHIFT_SETS)
    return [(shape, DTYPES[(i + j) % 3], sets[j], VARIANTS[(i + j // 2) % 2])
            for i, shape in enumerate(SHAPES) for j in range(len(sets))]


TRANSLATION_CASES = _pairwise_cases()


def test_the_translation_cases_hold_every_pair_of_settings():
    settings = [SHAPES, DTYPES, list(SHIFT_SETS), VARIANTS]
    for a, b in [(a, b) for a in range(4) for b in range(a + 1, 4)]:
        seen = {(str(case[a]), str(case[b])) for case in TRANSLATION_CASES}
        assert seen == {(str(x), str(y)) for x in settings[a] for y in settings[b]}, (a, b)


@pytest.mark.parametrize("shape, dtype, shift_set, variant", TRANSLATION_CASES,
                         ids=[f"{h}x{w}-{np.dtype(d).name}-{s}-{v}" for (h, w), d, s, v in TRANSLATION_CASES])
def test_translations_match_the_reference_at_every_size_and_edge(queue, monkeypatch, shape, dtype, shift_set,
                                                                 variant):
    """Every size the work shapes meet (a field smaller than a strip, narrower than 8 pixels, a row that ends within
    a step of 8, more than one work-item along a row), in the "cpu" and "gpu" variants' shapes, sub-pixel,
    whole-pixel, negative and half-pixel shifts and shifts beyond the field: the mask, NaNs and infinities are the
    per-pixel kernel's, the outputs the float64 reference's (where no flag is raised), saturated and non-finite
    samples flagged only where a tap of weight above zero reads them (at the field's corners, through clamped taps,
    too)."""
    monkeypatch.setenv("SPECGPU_VARIANT", variant)  # the kernel_variant fixture's setting, chosen per case
    h, w = shape
    rng = np.random.default_rng(h * 1000 + w)
    K, B = 4, 3
    frames, saturation = _frames_of(rng, dtype, K, h, w)
    A = rng.normal(0, 1, (B, K))
    shifts = np.array(SHIFT_SETS[shift_set])
    dark = rng.uniform(0, 5, (h, w)).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, (h, w)).astype(np.float32)
    got = apply_linear_warped(frames, A, shifts, dark, gain, saturation=saturation, return_mask=True, device=queue)
    exact = _per_pixel(frames, A, shifts, dark, gain, saturation, queue)
    assert got.y.shape == (h, w, B) and got.mask.shape == (h, w)
    np.testing.assert_array_equal(got.mask, exact.mask)
    np.testing.assert_array_equal(np.isnan(got.y), np.isnan(exact.y))
    np.testing.assert_array_equal(np.isposinf(got.y), np.isposinf(exact.y))
    np.testing.assert_array_equal(np.isneginf(got.y), np.isneginf(exact.y))
    # the reference of the frames with their non-finite samples zeroed: what an output that reads none of them (no
    # flag) is, its taps of weight zero included
    finite = np.nan_to_num(frames, nan=0, posinf=0, neginf=0)
    ref, outside = linear_warp_ref(finite, A, shifts.astype(np.float32), dark, gain)
    np.testing.assert_array_equal((got.mask & Mask.OUTSIDE) > 0, outside)
    clean = got.mask == 0
    assert np.all(np.abs(got.y - ref)[clean] <= tolerance(finite, A, dark, gain)[clean])
    if min(h, w) >= 13:  # fields large enough that some output reads the bad samples and some reads none
        assert ((got.mask & 3) > 0).any() and clean.any()


def test_a_bad_sample_at_a_zero_weight_tap_flags_nothing(queue):
    """A saturated, NaN or infinite sample read with weight zero (a whole-pixel shift's right or lower neighbour)
    neither flags nor spoils the output; read with a weight above zero it does, in the interior and at the edge."""
    frames = np.full((2, 6, 20), 50.0, np.float32)
    frames[1, 2, 9] = np.nan
    frames[1, 4, 0] = np.inf
    frames[1, 3, 15] = 1000.0  # saturated at 1000
    got = apply_linear_warped(frames, np.eye(2), [[0.0, 0.0], [1.0, 0.0]], saturation=1000.0, return_mask=True,
                              device=queue)
    # frame 1 sampled at x + 1: pixel x reads x + 1 with weight 1 and x + 2 with weight 0
    assert np.argwhere(got.mask & 2).tolist() == [[2, 8]]
    assert np.argwhere(got.mask & 1).tolist() == [[3, 14]]
    assert np.isnan(got.y[2, 8, 1]) and np.isfinite(got.y[2, 7, 1]) and got.y[3, 13, 1] == 50.0
    # at the left edge the inf is read by no tap of weight above zero; shifted left by a fraction, it is
    edge = apply_linear_warped(frames, np.eye(2), [[0.0, 0.0], [-0.25, 0.0]], saturation=1000.0, return_mask=True,
                               device=queue)
    assert np.isinf(edge.y[4, 0, 1]) and edge.mask[4, 0] & 2 and edge.mask[4, 1] & 2  # the clamped tap, then x - 1/4
    assert np.isinf(edge.y[4, 1, 1]) and not edge.mask[4, 2] & 2
    assert not got.mask[4, 0] & 2 and np.isfinite(got.y[4, 0, 1])


# The output groups of one launch, (rows, layout) each: every interleaved store (1 to 7 outputs, one block of 8,
# blocks of 8 with a last one shifted back: 9 and 13 outputs), planar groups of one and three outputs, most sizes
# in a group after the first (its rows start within A), four groups to a launch (two: the prepared launch test
# below). Each set of group sizes is a program of its own (7-10 s to compile cold), so four sizes share a launch
# rather than one launch each.
OUTPUT_GROUP_CASES = [
    [(1, "interleaved"), (2, "interleaved"), (3, "interleaved"), (4, "interleaved")],
    [(5, "interleaved"), (6, "interleaved"), (7, "interleaved"), (8, "interleaved")],
    [(9, "interleaved"), (1, "planar"), (13, "interleaved"), (3, "planar")],
]


def test_the_output_group_cases_meet_every_store():
    groups = [g for case in OUTPUT_GROUP_CASES for g in case]
    interleaved = {rows for rows, layout in groups if layout == "interleaved"}
    assert set(range(1, 9)) <= interleaved and {r for r in interleaved if r > 8 and r % 8} >= {9, 13}
    assert {rows for rows, layout in groups if layout == "planar"} >= {1, 3}
    assert all(len(case) == 4 for case in OUTPUT_GROUP_CASES)


@pytest.mark.parametrize("case", OUTPUT_GROUP_CASES,
                         ids=["+".join(f"{r}{layout[0]}" for r, layout in case) for case in OUTPUT_GROUP_CASES])
def test_output_groups_hold_the_rows_of_the_decoder(queue, case):
    """The B outputs split into groups, each its own buffer, interleaved or planar: every group size (the
    interleaved stores of 1 to 7 outputs, blocks of 8 with a last one shifted back) holds the outputs
    apply_linear_warped gives for the same rows, bit for bit, on a field whose rows end within a step of 8 and
    whose last strip is partial."""
    import pyopencl as cl

    from specgpu.engine import kernels
    from specgpu.engine.warp_map import PreparedWarp

    rows = [r for r, _ in case]
    rng = np.random.default_rng(sum(rows) * 10 + len(rows))
    K, h, w = 5, 7, 21
    B = sum(rows)
    frames = rng.integers(0, 1000, (K, h, w)).astype(np.uint16)
    A = rng.normal(0, 1, (B, K))
    shifts = rng.uniform(-2, 2, (K, 2))
    groups = [(f"g{g}", r, layout) for g, (r, layout) in enumerate(case)]
    warp = PreparedWarp(queue, np.uint16, A, (h, w), outputs=groups)
    out = warp.enqueue(kernels.to_device(queue, frames.reshape(-1)), shifts)
    whole = apply_linear_warped(frames, A, shifts, return_mask=True, layout="planar", device=queue)
    first = 0
    for (name, r, layout) in groups:
        got = np.empty((h, w, r) if layout == "interleaved" else (r, h, w), np.float32)
        cl.enqueue_copy(queue, got, out[name])
        want = whole.y[first:first + r]
        np.testing.assert_array_equal(np.moveaxis(got, -1, 0) if layout == "interleaved" else got, want)
        first += r
    mask = np.empty((h, w), np.uint8)
    cl.enqueue_copy(queue, mask, out["mask"])
    np.testing.assert_array_equal(mask, whole.mask)


@pytest.mark.parametrize("corrected_planes", [False, True])
def test_a_prepared_launch_is_apply_linear_warped(queue, corrected_planes):
    """PreparedWarp on a device buffer of every frame, reading some of them (a per-frame dark on the device, a gain
    with a dead pixel, float frames with a NaN and saturated samples), in one pass or two (the corrected planes
    kept): the outputs and mask of apply_linear_warped with the same ``read``, bit for bit, from calls enqueued back
    to back with different shifts; the corrected planes (o - dark) * gain of the frames read and their flags; a
    per-launch decoder written to a buffer replaces A."""
    import pyopencl as cl
    import pyopencl.array as cla

    from specgpu.engine import kernels
    from specgpu.engine.warp_map import PreparedWarp

    rng = np.random.default_rng(21)
    K_in, h, w = 6, 19, 45
    read = [4, 0, 2, 5]
    frames = rng.uniform(0, 100, (K_in, h, w)).astype(np.float32)
    frames[0, 9, 20] = np.nan
    frames[3, :, :] = np.nan  # a frame not read: no flag, no NaN from it
    A = rng.normal(0, 1, (7, K_in))
    dark = rng.uniform(0, 5, (K_in, h, w)).astype(np.float32)
    gain = rng.uniform(0.9, 1.1, (h, w)).astype(np.float32)
    gain[5, 30] = np.nan
    dark_dev = cla.to_device(queue, dark)
    warp = PreparedWarp(queue, np.float32, A, (h, w), dark_dev, gain, saturation=90.0, read=read,
                        outputs=[("coefficients", 4, "interleaved"), ("XYZ", 3, "interleaved")],
                        corrected_planes=corrected_planes)
    frames_dev = kernels.to_device(queue, frames.reshape(-1))
    shift_sets = [rng.uniform(-3, 3, (K_in, 2)) for _ in range(3)]
    results = [warp.enqueue(frames_dev, s) for s in shift_sets]  # no wait between: the shifts' writes are queued
    if corrected_planes:
        corrected = np.empty((len(read), h, w), np.float32)
        flags = np.empty((len(read), h, w), np.uint8)
        cl.enqueue_copy(queue, corrected, warp.corrected)
        cl.enqueue_copy(queue, flags, warp.flags)
        sel = frames[read]
        np.testing.assert_array_equal(corrected, (sel - dark[read]) * gain)
        np.testing.assert_array_equal(flags, np.where(np.isnan(sel), 2, 0) | np.where(sel >= 90.0, 1, 0))
    else:
        assert warp.corrected is None and warp.flags is None
    for shifts, out in zip(shift_sets, results):
        want = apply_linear_warped(frames, A, shifts, dark, gain, saturation=90.0, return_mask=True, read=read,
                                   device=queue)
        coefficients = np.empty((h, w, 4), np.float32)
        xyz = np.empty((h, w, 3), np.float32)
        mask = np.empty((h, w), np.uint8)
        for buf, host in ((out["coefficients"], coefficients), (out["XYZ"], xyz), (out["mask"], mask)):
            cl.enqueue_copy(queue, host, buf)
        np.testing.assert_array_equal(np.concatenate([coefficients, xyz], axis=-1), want.y)
        np.testing.assert_array_equal(mask, want.mask)
        assert (mask & 1).any() and (mask & 2).any() and np.isnan(want.y).any() and not np.isnan(want.y).all()
    A2 = rng.normal(0, 1, (7, len(read))).astype(np.float32)
    out = warp.enqueue(frames_dev, shift_sets[0], matrix=cla.to_device(queue, A2).data)
    got = np.empty((h, w, 4), np.float32)
    cl.enqueue_copy(queue, got, out["coefficients"])
    A2_full = np.zeros((7, K_in), np.float32)
    A2_full[:, read] = A2
    want = apply_linear_warped(frames, A2_full, shift_sets[0], dark, gain, read=read, device=queue)
    np.testing.assert_array_equal(got, want[..., :4])


@pytest.mark.parametrize("change,words", [
    (dict(outputs=[("a", 2, "interleaved")]), "add up to"),
    (dict(outputs=[("a", 1, "interleaved")] * 3), "distinct names"),
    (dict(outputs=[(f"g{g}", 1, "planar") for g in range(5)]), "1 to 4 groups"),
    (dict(outputs=[("a", 3, "sideways")]), "layout"),
    (dict(outputs=[("mask", 3, "planar")]), "other than 'mask'"),
    (dict(read=[0, 4]), "read must name"),
    (dict(frames_dtype=np.int32), "frames_dtype"),
    (dict(shape=(0, 4)), "positive"),
    (dict(dark=np.zeros((3, 4))), "dark has shape"),
    (dict(A=np.ones((3, 129))), "at most 128 frames"),
])
def test_a_prepared_launch_refuses_bad_settings(queue, change, words):
    from specgpu.engine.warp_map import PreparedWarp

    kw = dict(frames_dtype=np.uint16, A=np.ones((3, 4)), shape=(4, 6))
    kw.update(change)
    with pytest.raises((ValueError, TypeError), match=words):
        PreparedWarp(queue, kw.pop("frames_dtype"), kw.pop("A"), kw.pop("shape"), **kw)


def test_a_prepared_launch_refuses_bad_calls(queue):
    import pyopencl.array as cla

    from specgpu.engine.warp_map import PreparedWarp

    warp = PreparedWarp(queue, np.uint16, np.ones((3, 4)), (4, 6))
    frames = cla.zeros(queue, 4 * 24, np.uint16)
    with pytest.raises(ValueError, match=r"shape \(4, 2\)"):
        warp.enqueue(frames, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="finite"):
        warp.enqueue(frames, np.full((4, 2), np.inf))
    with pytest.raises(ValueError, match="fewer than the 4 frames"):
        warp.enqueue(cla.zeros(queue, 3 * 24, np.uint16), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="uint16 device array"):
        warp.enqueue(cla.zeros(queue, 4 * 24, np.float32), np.zeros((4, 2)))


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_one_pass_and_two_passes_agree_bit_for_bit(queue, kernel_variant, dtype):
    """The translation kernel reading the raw frames (dark and gain applied as it reads them, the flags found where
    a step's samples may raise some) and reading the corrected planes with their flag planes: the same outputs
    and mask, bit for bit, saturated and non-finite samples in many steps and at the field's edges."""
    import pyopencl as cl

    from specgpu.engine import kernels
    from specgpu.engine.warp_map import PreparedWarp

    rng = np.random.default_rng(31)
    # K = 4 frames, B = 3 outputs interleaved and a uint16 saturation of 1023: the one-pass program of the
    # translation cases above (one compile fewer)
    K, B, h, w = 4, 3, 23, 270
    frames, saturation = _frames_of(rng, dtype, K, h, w)
    if dtype == np.float32:
        saturation = 99.0  # about one sample in a hundred
        frames[0, rng.integers(0, h, 40), rng.integers(0, w, 40)] = np.nan
    else:
        frames[rng.integers(0, K, 200), rng.integers(0, h, 200), rng.integers(0, w, 200)] = 1023
    A = rng.normal(0, 1, (B, K))
    dark = rng.uniform(0, 5, (h, w)).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, (h, w)).astype(np.float32)
    shifts = np.array([[0.0, 0.0], [0.3, -0.7], [2.0, 0.5], [-0.25, -2.0]])  # whole, fractional, and mixed
    frames_dev = kernels.to_device(queue, frames.reshape(-1))
    got = []
    for corrected_planes in (False, True):
        warp = PreparedWarp(queue, dtype, A, (h, w), dark, gain, saturation=saturation,
                            outputs=[("y", B, "interleaved")], corrected_planes=corrected_planes)
        out = warp.enqueue(frames_dev, shifts)
        y, mask = np.empty((h, w, B), np.float32), np.empty((h, w), np.uint8)
        cl.enqueue_copy(queue, y, out["y"])
        cl.enqueue_copy(queue, mask, out["mask"])
        got.append((y, mask))
    (y1, m1), (y2, m2) = got
    np.testing.assert_array_equal(m1, m2)
    np.testing.assert_array_equal(y1, y2)
    assert (m1 & 1).sum() > 100 and (m1 == 0).sum() > 0.3 * h * w
