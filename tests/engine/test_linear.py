"""linear.cl through apply_linear against the float64 NumPy reference, on every device."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest
from hypothesis import given
from hypothesis import strategies as st
from reference import linear_ref, mask_ref

from specgpu.engine import kernels, runtime
from specgpu.engine.linear_map import apply_linear

EPS32 = np.finfo(np.float32).eps

# Each test runs once per kernel variant ("cpu": float8 per work-item, "gpu": a work-item per pixel), forced on each
# device present (tests/conftest.py kernel_variant), or, where a grid of settings is run pairwise, the variant is
# one of the settings and turns with the others (each distinct set of settings is a program, compiled cold in
# seconds on PoCL).
per_variant = pytest.mark.usefixtures("kernel_variant")
VARIANTS = ["cpu", "gpu"]
LAYOUTS = ["planar", "interleaved"]


def assert_every_pair_met(cases, settings):
    """Every pair of values of any two settings occurs in some case (``cases``: tuples, one value per setting)."""
    for a in range(len(settings)):
        for b in range(a + 1, len(settings)):
            seen = {(str(case[a]), str(case[b])) for case in cases}
            assert seen == {(str(x), str(y)) for x in settings[a] for y in settings[b]}, (a, b)


def frames_of(rng, dtype, K, shape):
    if dtype == np.uint8:
        return rng.integers(0, 256, (K, *shape), dtype=np.uint8)
    if dtype == np.uint16:
        return rng.integers(0, 1024, (K, *shape), dtype=np.uint16)
    return rng.uniform(0, 1, (K, *shape)).astype(np.float32)


def bound(frames, A, dark=None, gain=None, out_dtype=np.float32):
    """Error bound of a float32 (or float16-stored) dot product of K terms: a few K eps of sum |A| |o - dark|."""
    o = np.abs(np.asarray(frames, np.float64) - (0 if dark is None else np.asarray(dark, np.float64)))
    scale = np.tensordot(np.abs(np.asarray(A, np.float64)), o, axes=(1, 0))
    if gain is not None:
        scale = scale * np.abs(gain)
    K = A.shape[1]
    tol = (2 * K + 4) * EPS32 * scale + 1e-30
    if np.dtype(out_dtype) == np.float16:
        tol = tol + 2.0**-11 * scale + 6e-8  # round to nearest half, and half's subnormal step
    return tol


def assert_close(got, expected, tol):
    got = np.asarray(got, np.float64)
    excess = np.abs(got - expected) - tol
    assert got.shape == expected.shape
    assert np.all(excess <= 0), f"max error beyond bound by {excess.max():.3g}"


KS, BS = [1, 3, 6, 9, 31, 61], [1, 3, 5, 31, 61]
# every K with every B (K's samples unrolled, B's dot products looped over them), the kernel variant and the layout
# turning with them so that every pair of any two of (K, B, variant, layout) is run: 30 programs, not the 120 of
# the full grid, whose other cells meet no code these pairs miss (the variant and the layout choose the work shape
# and the stores, the same for every K and B)
K_B_CASES = [(K, B, VARIANTS[(i // 2 + j // 2) % 2], LAYOUTS[(j + i // 2) % 2])
             for i, K in enumerate(KS) for j, B in enumerate(BS)]


def test_the_K_and_B_cases_hold_every_pair_of_settings():
    assert_every_pair_met(K_B_CASES, [KS, BS, VARIANTS, LAYOUTS])


@pytest.mark.parametrize("K, B, variant, layout", K_B_CASES, ids=[f"{K}-{B}-{v}-{lo}" for K, B, v, lo in K_B_CASES])
def test_every_K_and_B(queue, monkeypatch, K, B, variant, layout):
    monkeypatch.setenv("SPECGPU_VARIANT", variant)  # the kernel_variant fixture's setting, chosen per case
    rng = np.random.default_rng(K * 100 + B)
    frames = frames_of(rng, np.uint16, K, (21, 11))  # 231 pixels: not a multiple of the vector width
    A = rng.normal(0, 1, (B, K))
    y = apply_linear(frames, A, layout=layout, device=queue)
    expected = linear_ref(frames, A, layout=layout)
    assert y.dtype == np.float32
    tol = bound(frames, A)
    assert_close(y, expected, tol if layout == "planar" else np.moveaxis(tol, 0, -1))


@per_variant
@pytest.mark.parametrize("K, layout", [(81, "interleaved"), (128, "planar"), (129, "interleaved"), (401, "planar")])
def test_many_frames_on_a_large_image(queue, K, layout):
    """Beyond the 61 of the paper (1 nm reflectance cubes go through the same kernel): no private array may
    grow with K (a work-group's worth of them overflowed the CPU device's stack), on an image large enough for
    full work-groups."""
    rng = np.random.default_rng(K)
    frames = frames_of(rng, np.float32, K, (64, 96))
    A = rng.normal(0, 1, (3, K))
    res = apply_linear(frames, A, layout=layout, return_mask=True, saturation=0.999, device=queue)
    expected = linear_ref(frames, A, layout=layout)
    tol = bound(frames, A)
    assert_close(res.y, expected, tol if layout == "planar" else np.moveaxis(tol, 0, -1))
    np.testing.assert_array_equal(res.mask, mask_ref(frames, 0.999))


@per_variant
def test_matrix_beyond_constant_memory_is_a_clear_error(queue):
    too_big = queue.device.max_constant_buffer_size // 4 // 8 + 1
    with pytest.raises(ValueError, match="exceeds the constant memory"):
        apply_linear(np.zeros((8, 2, 2), np.float32), np.zeros((too_big, 8)), device=queue)


IN_DTYPES, OUT_DTYPES = [np.uint8, np.uint16, np.float32], [np.float32, np.float16]
# each input dtype with each output dtype, the layout and the variant turning with them: every pair of any two of
# the four settings in 6 programs (the full grid: 24); the input dtype acts on the sample read, the output dtype
# and the layout on the stores, the variant on the work shape
DTYPE_CASES = [(i, o, LAYOUTS[(a + b) % 2], VARIANTS[(b + (a == 2)) % 2])
               for a, i in enumerate(IN_DTYPES) for b, o in enumerate(OUT_DTYPES)]


def test_the_dtype_cases_hold_every_pair_of_settings():
    assert_every_pair_met(DTYPE_CASES, [IN_DTYPES, OUT_DTYPES, LAYOUTS, VARIANTS])


@pytest.mark.parametrize("in_dtype, out_dtype, layout, variant", DTYPE_CASES,
                         ids=[f"{np.dtype(i).name}-{np.dtype(o).name}-{lo}-{v}" for i, o, lo, v in DTYPE_CASES])
def test_dtypes_and_layouts(queue, monkeypatch, in_dtype, out_dtype, layout, variant):
    monkeypatch.setenv("SPECGPU_VARIANT", variant)
    rng = np.random.default_rng(7)
    frames = frames_of(rng, in_dtype, 9, (17, 5))
    A = rng.normal(0, 0.01, (5, 9))
    y = apply_linear(frames, A, out_dtype=out_dtype, layout=layout, device=queue)
    assert y.dtype == np.dtype(out_dtype)
    assert y.shape == ((5, 17, 5) if layout == "planar" else (17, 5, 5))
    expected = linear_ref(frames, A, layout=layout)
    tol = bound(frames, A, out_dtype=out_dtype)
    assert_close(y, expected, tol if layout == "planar" else np.moveaxis(tol, 0, -1))


CALIBRATIONS = ["dark", "dark+gain", "perframe-dark+gain", "gain"]
# each input dtype with each calibration, the variant turning with them (every pair of the three settings: 12
# programs, not 24)
CALIBRATION_CASES = [(d, c, VARIANTS[(a + b) % 2]) for a, d in enumerate(IN_DTYPES) for b, c in enumerate(CALIBRATIONS)]


def test_the_calibration_cases_hold_every_pair_of_settings():
    assert_every_pair_met(CALIBRATION_CASES, [IN_DTYPES, CALIBRATIONS, VARIANTS])


@pytest.mark.parametrize("in_dtype, calibration, variant", CALIBRATION_CASES,
                         ids=[f"{np.dtype(d).name}-{c}-{v}" for d, c, v in CALIBRATION_CASES])
def test_dark_and_gain(queue, monkeypatch, in_dtype, calibration, variant):
    monkeypatch.setenv("SPECGPU_VARIANT", variant)
    rng = np.random.default_rng(11)
    K, shape = 6, (13, 9)
    frames = frames_of(rng, in_dtype, K, shape)
    top = 1.0 if in_dtype == np.float32 else 50.0
    dark = None
    if "perframe" in calibration:
        dark = rng.uniform(0, 0.1 * top, (K, *shape)).astype(np.float32)
    elif "dark" in calibration:
        dark = rng.uniform(0, 0.1 * top, shape).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, shape).astype(np.float32) if "gain" in calibration else None
    A = rng.normal(0, 1, (3, K))
    y = apply_linear(frames, A, dark, gain, device=queue)
    assert_close(y, linear_ref(frames, A, dark, gain), np.moveaxis(bound(frames, A, dark, gain), 0, -1))


@per_variant
@pytest.mark.parametrize("shape", [(1, 1), (4096, 1), (1, 4097), (7,), (3, 5, 7)])
def test_image_sizes(queue, shape):
    """Odd sizes, single pixels and long rows: the partial last vector is stored exactly, nothing beyond."""
    rng = np.random.default_rng(3)
    frames = frames_of(rng, np.uint16, 9, shape)
    A = rng.normal(0, 1, (4, 9))
    y = apply_linear(frames, A, device=queue)
    assert y.shape == (*shape, 4)
    assert_close(y, linear_ref(frames, A), np.moveaxis(bound(frames, A), 0, -1))


@per_variant
def test_zero_pixels(queue):
    y = apply_linear(np.zeros((3, 0, 4), np.uint16), np.eye(3), device=queue)
    assert y.shape == (0, 4, 3)


@per_variant
def test_saturation_and_nonfinite_mask(queue):
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 1000, (9, 15, 7), dtype=np.uint16)  # below saturation but for the two set below
    frames[4, 2, 3] = 1023
    frames[0, 14, 6] = 1023  # the last pixel, in the partial vector
    A = rng.normal(0, 1, (2, 9))
    res = apply_linear(frames, A, saturation=1023, return_mask=True, device=queue)
    np.testing.assert_array_equal(res.mask, mask_ref(frames, 1023))
    assert res.mask[2, 3] == 1 and res.mask[14, 6] == 1 and res.mask.sum() == 2
    # default saturation of an integer dtype is its maximum code
    frames[1, 0, 0] = 65535
    res = apply_linear(frames, A, return_mask=True, device=queue)
    np.testing.assert_array_equal(res.mask, mask_ref(frames, 65535))


@per_variant
def test_nan_propagates_to_that_pixel_only(queue):
    rng = np.random.default_rng(6)
    frames = rng.uniform(0, 1, (4, 9, 9)).astype(np.float32)
    frames[2, 4, 4] = np.nan
    frames[3, 8, 8] = np.inf
    A = rng.normal(0, 1, (3, 4))
    res = apply_linear(frames, A, return_mask=True, device=queue)
    y = res.y
    assert np.all(np.isnan(y[4, 4]))
    assert not np.any(np.isfinite(y[8, 8]))
    finite = np.ones((9, 9), bool)
    finite[4, 4] = finite[8, 8] = False
    assert np.all(np.isfinite(y[finite]))
    assert res.mask[4, 4] == 2 and res.mask[8, 8] == 2 and res.mask.sum() == 4
    assert_close(y[finite], linear_ref(frames, A)[finite], np.moveaxis(bound(frames, A), 0, -1)[finite])


@per_variant
@pytest.mark.parametrize("layout", ["interleaved", "planar"])
def test_a_nan_gain_leaves_that_pixel_nan_only(queue, layout):
    """NaN in the gain map marks a pixel with no response (a calibration's dead pixel): its outputs are NaN, every
    other pixel as the NumPy reference; inf is still refused in one line."""
    rng = np.random.default_rng(8)
    K, shape = 5, (11, 17)  # the dead pixel in a partial vector of the CPU variant too
    frames = frames_of(rng, np.uint16, K, shape)
    gain = rng.uniform(0.8, 1.2, shape).astype(np.float32)
    gain[3, 16] = np.nan
    A = rng.normal(0, 1, (4, K))
    y = np.asarray(apply_linear(frames, A, None, gain, layout=layout, device=queue))
    y = y if layout == "interleaved" else np.moveaxis(y, 0, -1)
    want = linear_ref(frames, A, None, gain)  # NaN there too: NumPy's product propagates it
    assert np.isnan(y[3, 16]).all() and np.isnan(want[3, 16]).all()
    live = np.isfinite(gain)
    assert np.isfinite(y[live]).all()
    assert_close(y[live], want[live], np.moveaxis(bound(frames, A, None, np.nan_to_num(gain)), 0, -1)[live])
    gain[0, 0] = np.inf
    with pytest.raises(ValueError, match=r"^gain contains inf at 1 pixels$"):
        apply_linear(frames, A, None, gain, device=queue)


@per_variant
def test_float16_overflow_is_inf(queue):
    frames = np.full((1, 2, 9), 1000, np.uint16)
    y = apply_linear(frames, [[100.0]], out_dtype=np.float16, device=queue)
    assert np.all(np.isinf(y)) and np.all(y > 0)


@per_variant
def test_device_arrays_in_and_out(queue):
    rng = np.random.default_rng(8)
    frames = frames_of(rng, np.uint16, 3, (10, 10))
    A = rng.normal(0, 1, (3, 3))
    y_dev = apply_linear(cla.to_device(queue, frames), A)
    assert isinstance(y_dev, cla.Array) and y_dev.queue is queue
    np.testing.assert_array_equal(y_dev.get(), apply_linear(frames, A, device=queue))


@per_variant
@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(frames=np.zeros((9, 4, 4), np.uint16), A=np.zeros((3, 6))), "A has 6 columns but frames has K = 9"),
        (dict(frames=np.zeros((9, 4, 4), np.int32), A=np.zeros((3, 9))), "dtype int32"),
        (dict(frames=np.zeros((9, 4, 4), np.complex64), A=np.zeros((3, 9))), "dtype complex64"),
        (dict(frames=np.zeros(9, np.uint16), A=np.zeros((3, 9))), "shape (K, H, W)"),
        (dict(frames=np.zeros((9, 4, 4), np.uint16), A=np.zeros(9)), "2-D matrix"),
        (dict(frames=np.zeros((2, 4, 4), np.uint16), A=[[np.nan, 1.0]]), "NaN or inf"),
        (dict(frames=np.zeros((2, 4, 4), np.uint16), A=np.ones((1, 2)), dark=np.zeros((4, 5))), "dark has shape"),
        (dict(frames=np.zeros((2, 4, 4), np.uint16), A=np.ones((1, 2)), dark=np.full((4, 4), np.nan)),
         "dark contains NaN"),
        (dict(frames=np.zeros((2, 4, 4), np.uint16), A=np.ones((1, 2)), gain=np.zeros((2, 4, 4))),
         "gain has shape"),
        (dict(frames=np.zeros((2, 4, 4), np.uint16), A=np.ones((1, 2)), layout="bsq"), "layout='bsq'"),
        (dict(frames=np.zeros((2, 4, 4), np.uint16), A=np.ones((1, 2)), out_dtype=np.float64), "float32 or float16"),
        (dict(frames=np.zeros((0, 4, 4), np.uint16), A=np.ones((1, 0))), "no frame"),
    ],
)
def test_bad_input_is_a_clear_error(queue, kwargs, message):
    with pytest.raises((ValueError, TypeError)) as error:
        apply_linear(device=queue, **kwargs)
    assert message in str(error.value)
    assert "\n" not in str(error.value)


@per_variant
@given(data=st.data(), npix=st.integers(1, 40), seed=st.integers(0, 2**16))
def test_random_shapes_property(data, npix, seed):
    """Any K, B and pixel count (covering every remainder modulo the vector width) matches the reference. K, B and
    the layout are drawn from the small cases test_every_K_and_B runs in the same variant: programs it builds (each
    (K, B) is a build), not a dozen more."""
    variant = runtime.kernel_variant(runtime.get_queue().device)
    K, B, _, layout = data.draw(st.sampled_from([c for c in K_B_CASES if c[2] == variant and c[0] <= 9 and c[1] <= 5]))
    rng = np.random.default_rng(seed)
    frames = frames_of(rng, np.uint16, K, (npix,))
    A = rng.normal(0, 1, (B, K))
    y = apply_linear(frames, A, layout=layout)
    expected = linear_ref(frames, A, layout=layout)
    tol = bound(frames, A)
    assert_close(y, expected, tol if layout == "planar" else np.moveaxis(tol, 0, -1))


@per_variant
def test_float16_rounding_is_bit_exact_round_to_nearest_even(queue):
    """Output rounding equals NumPy's float32 -> float16 cast, bit for bit: random bit patterns over the whole
    float32 range, the half subnormal and overflow boundaries, inf and NaN (sums start at +0, so -0 -> +0, and
    float32 denormals are flushed to 0)."""
    rng = np.random.default_rng(16)
    x = np.concatenate([
        np.array([0.0, np.inf, -np.inf, np.nan, 65504, 65519.99, 65520, 65536, 6.1035156e-05, 6.097555e-05,
                  5.9604645e-08, 2.9802322e-08, 2.9802326e-08, 1e-45, -3.0e-08, 1.0, -2.5, 0.1], np.float32),
        rng.integers(0, 2**32, 200_000, dtype=np.uint64).astype(np.uint32).view(np.float32),
        (rng.normal(0, 1, 100_000) * np.exp2(rng.integers(-26, 17, 100_000))).astype(np.float32),
    ])
    # kernels build with -cl-denorms-are-zero: float32 denormals (< 1.2e-38, far below half's range) are 0
    x[np.abs(x) < np.finfo(np.float32).tiny] = 0.0
    with np.errstate(over="ignore"):
        expected = x.astype(np.float16)

    def check(y, what):
        same = (y.view(np.uint16) == expected.view(np.uint16)) | (np.isnan(y) & np.isnan(expected))
        assert same.all(), f"{what}: {x[~same][:5]} -> {y[~same][:5]}, expected {expected[~same][:5]}"

    for layout in ("planar", "interleaved"):
        check(apply_linear(x[None, :], [[1.0]], out_dtype=np.float16, layout=layout, device=queue).ravel(), layout)
    # the portable bit-arithmetic conversion too, where the device would otherwise use a hardware instruction
    kernel = runtime.get_kernel(queue, "linear.cl", "linear_apply", K=1, B=1, IN_T="float", IN_LAYOUT=0, HAS_DARK=0,
                                HAS_GAIN=0, IS_FLOAT_IN=1, OUT_HALF=1, OUT_LAYOUT=0, WRITE_MASK=0, HALF_SOFT=1)
    frames = cla.to_device(queue, x)
    out = cla.empty(queue, x.shape, np.float16)
    A = cla.to_device(queue, np.ones(1, np.float32))
    kernel(queue, (-(-x.size // 8),), None, frames.data, A.data, None, None, out.data, None, np.uint64(x.size))
    check(out.get(), "HALF_SOFT")


@per_variant
def test_sliced_device_arrays(queue):
    """A view into a larger device buffer (non-zero offset) works like the same data in its own buffer."""
    rng = np.random.default_rng(12)
    frames = frames_of(rng, np.uint16, 5, (6, 10))
    dev = cla.to_device(queue, frames)
    A = rng.normal(0, 1, (3, 4))
    np.testing.assert_array_equal(apply_linear(dev[1:], A).get(), apply_linear(frames[1:], A, device=queue))


@per_variant
@pytest.mark.parametrize("npix", [1, 7, 8, 9, 15, 16, 17, 24, 31, 33, 1000])
def test_planar_float16_sixteen_pixel_items(queue, npix):
    """Planar float16 runs 16 pixels per work-item: every remainder modulo 16, with dark, gain and mask."""
    rng = np.random.default_rng(npix)
    K = 6
    frames = rng.integers(0, 1000, (K, npix), dtype=np.uint16)
    frames[2, -1] = 1023
    dark = rng.uniform(0, 20, (npix,)).astype(np.float32)
    gain = rng.uniform(0.9, 1.1, (npix,)).astype(np.float32)
    A = rng.normal(0, 1e-3, (5, K))
    res = apply_linear(frames, A, dark, gain, out_dtype=np.float16, layout="planar", saturation=1023,
                       return_mask=True, device=queue)
    assert res.y.shape == (5, npix) and res.y.dtype == np.float16
    assert_close(res.y, linear_ref(frames, A, dark, gain, layout="planar"),
                 bound(frames, A, dark, gain, out_dtype=np.float16))
    np.testing.assert_array_equal(res.mask, mask_ref(frames, 1023))


@pytest.mark.parametrize("out_dtype", [np.float32, np.float16])
@pytest.mark.parametrize("K, B", [(1, 1), (9, 61), (6, 8), (130, 3)])
def test_gpu_channels_last_without_tile_per_output_element(queue, monkeypatch, K, B, out_dtype):
    """The "gpu" variant writes channels last through a local-memory tile where it fits and with a work-item per
    output element where it does not: the second path, forced, against the reference (dark, gain, mask), and
    equal to the tiled one. It sets the "gpu" variant itself, so it runs once, not once per variant."""
    monkeypatch.setenv("SPECGPU_VARIANT", "gpu")
    rng = np.random.default_rng(K * 1000 + B)
    npix = 67  # a group of 64 and a partial one
    frames = rng.integers(0, 1000, (K, npix), dtype=np.uint16)
    frames[K - 1, 5] = 1023
    dark = rng.uniform(0, 20, (npix,)).astype(np.float32)
    gain = rng.uniform(0.9, 1.1, (npix,)).astype(np.float32)
    A = rng.normal(0, 1e-3, (B, K))
    kwargs = dict(out_dtype=out_dtype, layout="interleaved", saturation=1023, return_mask=True, device=queue)
    tiled = apply_linear(frames, A, dark, gain, **kwargs)
    monkeypatch.setattr(kernels, "_TILE_LOCAL_MAX", 0)
    assert not kernels._tile_fits(queue, B)  # the patch reaches the launcher: the per-element path runs
    res = apply_linear(frames, A, dark, gain, **kwargs)
    assert res.y.shape == (npix, B) and res.y.dtype == np.dtype(out_dtype)
    assert_close(res.y, linear_ref(frames, A, dark, gain),
                 np.moveaxis(bound(frames, A, dark, gain, out_dtype=out_dtype), 0, -1))
    np.testing.assert_array_equal(res.mask, mask_ref(frames, 1023))
    np.testing.assert_allclose(res.y.astype(np.float64), tiled.y, rtol=1e-5, atol=1e-7)  # two programs: FMA may differ
    np.testing.assert_array_equal(res.mask, tiled.mask)


# every pair of (output layout, output dtype, variant): 4 cases of the 8
PREPARED_CASES = [(0, np.float32, "cpu"), (1, np.float32, "gpu"), (0, np.float16, "gpu"), (1, np.float16, "cpu")]


def test_the_prepared_cases_hold_every_pair_of_settings():
    assert_every_pair_met(PREPARED_CASES, [[0, 1], OUT_DTYPES, VARIANTS])


@pytest.mark.parametrize("out_layout, out_dtype, variant", PREPARED_CASES,
                         ids=[f"{lo}-{np.dtype(d).name}-{v}" for lo, d, v in PREPARED_CASES])
def test_prepared_launches_equal_the_direct_launches(queue, monkeypatch, out_layout, out_dtype, variant):
    """The stream's prepared launches (a kernel object of its own, fixed arguments set once) give what the
    direct launches give, launch after launch with new frames, in the variant of the case."""
    monkeypatch.setenv("SPECGPU_VARIANT", variant)
    rng = np.random.default_rng(out_layout * 2 + (out_dtype == np.float16))
    K, B, n = 9, 7, 1001
    A = rng.normal(0, 1e-3, (B, K))
    dark = kernels.to_device(queue, rng.uniform(0, 5, n).astype(np.float32))
    gain = kernels.to_device(queue, rng.uniform(0.9, 1.1, n).astype(np.float32))
    M = rng.uniform(0, 1e-3, (3, K))
    white = (0.95047, 1.0, 1.08883)
    reference = kernels.to_device(queue, rng.uniform(-20, 60, 3 * n).astype(np.float32))
    lin = kernels.prepare_linear(queue, np.uint16, A, n=n, dark=dark, gain=gain, out_dtype=out_dtype,
                                 out_layout=out_layout, want_mask=True, saturation=1023.0)
    fused = kernels.prepare_frames_to_delta_E(queue, np.uint16, M, white, reference, n=n, reference_single=False,
                                              dark=dark, gain=gain, write_XYZ=True, write_Lab=True)
    for seed in range(3):
        frames_host = np.random.default_rng(seed).integers(0, 1024, K * n).astype(np.uint16)
        frames = kernels.to_device(queue, frames_host)
        got = lin.enqueue(frames.data)
        got_f = fused.enqueue(frames.data)
        want, want_mask = kernels.launch_linear(queue, frames, A, n=n, dark=dark, gain=gain, out_dtype=out_dtype,
                                                out_layout=out_layout, want_mask=True, saturation=1023.0)
        want_f = kernels.launch_frames_to_delta_E(queue, frames, M, white, reference, n=n, reference_single=False,
                                                  dark=dark, gain=gain, write_XYZ=True, write_Lab=True)
        y = np.empty(B * n, out_dtype)
        m = np.empty(n, np.uint8)
        cl.enqueue_copy(queue, y, got["out"])
        cl.enqueue_copy(queue, m, got["mask"])
        np.testing.assert_array_equal(y, want.get())
        np.testing.assert_array_equal(m, want_mask.get())
        assert m.sum() > 0
        for key, ref in (("XYZ", want_f.XYZ), ("Lab", want_f.Lab), ("delta_E", want_f.delta_E)):
            host = np.empty(ref.shape, np.float32)
            cl.enqueue_copy(queue, host, got_f[key])
            np.testing.assert_array_equal(host, ref.get())


@per_variant
def test_a_prepared_launch_holds_its_matrix_after_the_upload_cache_lets_it_go(queue):
    """A prepared launch's kernel names its matrix buffer, which OpenCL does not keep alive: after the matrix
    upload cache has evicted it (and the pool handed its memory to other matrices), the launch still decodes
    with its own matrix."""
    import gc

    rng = np.random.default_rng(7)
    K, n = 4, 1000
    A = rng.uniform(-1, 1, (3, K))
    lin = kernels.prepare_linear(queue, np.float32, A, n=n)
    for i in range(kernels._MATRIX_CACHE_SIZE + 8):  # evict it, and reuse its memory for others
        kernels.matrix_on_device(queue, np.full((3, K), 1000.0 + i))
    gc.collect()
    runtime.get_allocator(queue).free_held()
    for i in range(16):
        kernels.to_device(queue, np.full(3 * K, -5.0e6 - i, np.float32))
    frames_host = rng.uniform(0, 1, (K, n)).astype(np.float32)
    frames = kernels.to_device(queue, frames_host.reshape(-1))
    got = np.empty(3 * n, np.float32)
    cl.enqueue_copy(queue, got, lin.enqueue(frames.data)["out"])
    np.testing.assert_allclose(got.reshape(3, n), A @ frames_host, rtol=1e-5, atol=1e-5)
