"""The guided filter's passes of running sums on every OpenCL device and in both kernel variants, against a float64
reference built on SciPy's box filter: odd sizes, radii up to and past the image's size, one and nine channels,
strips short enough that every work-item starts inside the image; NaN where a window holds a non-finite value
and nowhere else; the device entry point (no host transfer, an output given, the image filtered in place, the
intermediates made once per shape, two threads on one queue)."""

import threading

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

import specgpu.engine.guided as guided
from specgpu.engine.guided import guided_filter, guided_filter_device
from specgpu.engine.runtime import program_cache_size


def guided_scipy(p, g, r, eps):
    """The guided filter in float64, box means by ``scipy.ndimage.uniform_filter`` over the window clipped to the
    image (the sum over the window inside, divided by the count inside)."""
    from scipy.ndimage import uniform_filter

    p, g = np.asarray(p, np.float64), np.asarray(g, np.float64)
    size = 2 * r + 1
    count = uniform_filter(np.ones(g.shape), size, mode="constant")

    def box(a):
        return uniform_filter(a, (size, size, 1), mode="constant") / count[..., None]

    gg = g[..., None]
    mg, mp = box(gg), box(p)
    a = (box(gg * p) - mg * mp) / (np.maximum(box(gg * gg) - mg * mg, 0.0) + eps)
    return box(a) * gg + box(mp - a * mg)


def image_and_guide(shape, seed, level=0.6):
    """A guide with a step edge and texture about ``level``, and an image following it plus noise."""
    rng = np.random.default_rng(seed)
    H, W, C = shape
    g = (level + 0.2 * rng.uniform(-1, 1, (H, W))).astype(np.float32)
    g[:, W // 2:] += 0.5
    p = (g[..., None] * rng.uniform(0.2, 1.0, C) + rng.normal(0, 0.05, shape)).astype(np.float32)
    return p, g


@pytest.mark.parametrize("shape, r, eps, strip", [
    ((37, 53, 9), 2, 1e-3, None),   # odd sizes, nine channels (the stream's coefficients)
    ((37, 53, 9), 2, 1e-3, 5),      # many strips: every work-item's first windows inside the image
    ((29, 41, 1), 3, 1e-2, 4),      # one channel
    ((13, 17, 2), 7, 1e-2, None),   # windows wider than half the image
    ((11, 9, 3), 12, 0.5, 3),       # windows wider than the image: every window is the whole image
    ((1, 31, 1), 2, 1e-4, None),    # one row
    ((33, 1, 2), 4, 1e-3, 8),       # one column
])
def test_against_the_scipy_reference(queue, kernel_variant, shape, r, eps, strip):
    p, g = image_and_guide(shape, sum(shape) + r)
    out = guided_filter_device(queue, cla.to_device(queue, p), cla.to_device(queue, g), r, eps, strip=strip)
    np.testing.assert_allclose(out.get(), guided_scipy(p, g, r, eps), rtol=1e-4, atol=2e-5)


def test_a_flat_guide_of_large_level_keeps_float32_precision(queue):
    """Statistics taken about the guide's own level: a nearly flat guide far from zero (var g ~ eps) still gives
    the filter within float32 rounding of the reference."""
    rng = np.random.default_rng(5)
    H, W, C = 48, 64, 3
    g = (1000.0 + rng.normal(0, 0.01, (H, W))).astype(np.float32)
    p = rng.normal(0.5, 0.1, (H, W, C)).astype(np.float32)
    got = guided_filter(p, g, radius=2, eps=1e-4, device=queue)
    np.testing.assert_allclose(got, guided_scipy(p, g, 2, 1e-4), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("where", ["image", "guide"])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_a_non_finite_value_reaches_exactly_the_windows_that_hold_it(queue, kernel_variant, where, value):
    """NaN covers the (4r + 1)^2 pixels about a non-finite input (clipped to the image), in its channel for the
    image and in every channel for the guide; every other output equals the reference, so the running sums
    recover once the value has left their windows."""
    H, W, C, r = 30, 40, 3, 2
    p, g = image_and_guide((H, W, C), 11)
    spots = [(5, 7), (20, 38), (0, 0)]
    bad_p, bad_g = p.copy(), g.copy()
    for y, x in spots:
        if where == "image":
            bad_p[y, x, 1] = value
        else:
            bad_g[y, x] = value
    got = guided_filter_device(queue, cla.to_device(queue, bad_p), cla.to_device(queue, bad_g), r, 1e-3,
                               strip=7).get()
    expected_nan = np.zeros((H, W, C), bool)
    for y, x in spots:
        window = (slice(max(y - 2 * r, 0), y + 2 * r + 1), slice(max(x - 2 * r, 0), x + 2 * r + 1))
        expected_nan[window + ((1,) if where == "image" else (slice(None),))] = True
    assert np.array_equal(np.isnan(got), expected_nan)
    # outside those windows the bad values count for nothing: the reference of the clean inputs
    reference = guided_scipy(p, g, r, 1e-3)
    np.testing.assert_allclose(got[~expected_nan], reference[~expected_nan], rtol=1e-4, atol=2e-5)


def test_the_device_entry_point_stays_on_the_device_and_writes_where_asked(queue):
    p, g = image_and_guide((24, 35, 4), 3)
    p_dev, g_dev = cla.to_device(queue, p), cla.to_device(queue, g)
    expected = guided_scipy(p, g, 2, 1e-3)
    out = cla.empty(queue, p.shape, np.float32)
    got = guided_filter_device(queue, p_dev, g_dev, 2, 1e-3, out=out)
    assert got is out and isinstance(got, cla.Array)
    np.testing.assert_allclose(out.get(), expected, rtol=1e-4, atol=2e-5)
    # the image itself as the output: only the first pass reads it
    guided_filter_device(queue, p_dev, g_dev, 2, 1e-3, out=p_dev)
    np.testing.assert_allclose(p_dev.get(), expected, rtol=1e-4, atol=2e-5)


def test_bad_device_arguments_are_one_line(queue):
    p = cla.zeros(queue, (8, 9, 2), np.float32)
    g = cla.zeros(queue, (8, 9), np.float32)
    cases = [
        (dict(image=p, guide=cla.zeros(queue, (8, 8), np.float32)), r"guide must be float32 of shape \(8, 9\)"),
        (dict(image=p.astype(np.float64), guide=g), "image must be float32"),
        (dict(image=p, guide=g, out=cla.zeros(queue, (8, 9, 3), np.float32)), r"out must be float32 of shape"),
        (dict(image=np.zeros((8, 9, 2), np.float32), guide=g), "image must be a pyopencl array"),
    ]
    for kwargs, message in cases:
        with pytest.raises((ValueError, TypeError), match=message) as info:
            guided_filter_device(queue, radius=2, eps=1e-3, **kwargs)
        assert "\n" not in str(info.value)
    g1 = cla.zeros(queue, (8, 9, 1), np.float32)
    with pytest.raises(ValueError, match="out must not be the guide"):
        guided_filter_device(queue, g1, g1.reshape(8, 9), 2, 1e-3, out=g1)


def test_intermediates_and_program_are_made_once_per_shape(queue, monkeypatch):
    made = []
    real = guided._Intermediates

    def counting(*args):
        made.append(args[1:])
        return real(*args)

    monkeypatch.setattr(guided, "_Intermediates", counting)
    monkeypatch.setattr(guided, "_cache", type(guided._cache)())
    p, g = image_and_guide((19, 23, 3), 8)
    p_dev, g_dev = cla.to_device(queue, p), cla.to_device(queue, g)
    guided_filter_device(queue, p_dev, g_dev, 2, 1e-3)
    programs = program_cache_size()
    for _ in range(3):
        out = guided_filter_device(queue, p_dev, g_dev, 2, 1e-3)
    assert [m[:4] for m in made] == [(19, 23, 3, 2)]  # one set of buffers for the shape (H, W, C, r)
    assert program_cache_size() == programs  # and no program built again
    np.testing.assert_allclose(out.get(), guided_scipy(p, g, 2, 1e-3), rtol=1e-4, atol=2e-5)
    q, h = image_and_guide((19, 24, 3), 9)  # another shape: buffers of its own
    guided_filter_device(queue, cla.to_device(queue, q), cla.to_device(queue, h), 2, 1e-3)
    assert len(made) == 2


def test_two_threads_on_one_queue_each_get_their_own_result(queue):
    """The intermediates are shared by calls of one shape: a call's three passes are enqueued as one unit."""
    inputs = [image_and_guide((26, 31, 2), seed) for seed in range(4)]
    expected = [guided_scipy(p, g, 2, 1e-3) for p, g in inputs]
    results = [None] * len(inputs)

    def work(i):
        p, g = inputs[i]
        outs = [guided_filter_device(queue, cla.to_device(queue, p), cla.to_device(queue, g), 2, 1e-3)
                for _ in range(10)]
        results[i] = [o.get() for o in outs]

    threads = [threading.Thread(target=work, args=(i,)) for i in range(len(inputs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for got, want in zip(results, expected):
        for g in got:
            np.testing.assert_allclose(g, want, rtol=1e-4, atol=2e-5)


@pytest.mark.parametrize("shape, r, strip", [((45, 23, 9), 2, 8), ((20, 30, 4), 9, 6)])
def test_filtering_in_place_reads_the_image_as_it_was(queue, kernel_variant, shape, r, strip):
    """out=image, the image the start of a larger buffer (as a pooled output is): every strip of rows reads the
    image unfiltered, its neighbours' rows included, so the result is the reference's."""
    p, g = image_and_guide(shape, 21)
    image = cla.Array(queue, shape, np.float32, data=cl.Buffer(queue.context, cl.mem_flags.READ_WRITE, p.nbytes + 4096))
    image.set(p)
    got = guided_filter_device(queue, image, cla.to_device(queue, g), r, 1e-3, out=image, strip=strip)
    assert got is image
    np.testing.assert_allclose(image.get(), guided_scipy(p, g, r, 1e-3), rtol=1e-4, atol=2e-5)


@pytest.mark.parametrize("H, strip", [(64, 16), (61, 7), (9, 64)])
def test_strips_agree_with_the_reference_where_windows_cross_them(queue, kernel_variant, H, strip):
    """Strips of rows (the "cpu" form's work-items, the column passes' of the "gpu" form) whose windows reach into
    their neighbours' rows, a last strip shorter than the others, and one strip taller than the image; non-finite
    values on the rows where two strips meet, whose NaN must cross into the next strip and end there."""
    W, C, r = 37, 9, 3
    p, g = image_and_guide((H, W, C), H + strip)
    bad_p, bad_g = p.copy(), g.copy()
    y = min(strip, H - 1)
    bad_p[y - 1, 5, 4], bad_g[y, W - 3] = np.nan, np.inf
    got = guided_filter_device(queue, cla.to_device(queue, bad_p), cla.to_device(queue, bad_g), r, 1e-3,
                               strip=strip).get()
    expected_nan = np.zeros((H, W, C), bool)
    expected_nan[max(y - 1 - 2 * r, 0):y + 2 * r, max(5 - 2 * r, 0):5 + 2 * r + 1, 4] = True
    expected_nan[max(y - 2 * r, 0):y + 2 * r + 1, W - 3 - 2 * r:, :] = True
    assert np.array_equal(np.isnan(got), expected_nan)
    reference = guided_scipy(p, g, r, 1e-3)
    np.testing.assert_allclose(got[~expected_nan], reference[~expected_nan], rtol=1e-4, atol=2e-5)
