"""The guided filter on every OpenCL device against its NumPy reference; its behaviour at a step edge and on a
flat field (noise averaged down as the mean of box means predicts); one-line refusals."""

import numpy as np
import pyopencl.array as cla
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import guided_filter_numpy

from specgpu.engine.guided import box_box_variance, flat_variance_reduction, guided_filter


@pytest.mark.parametrize("shape, r, eps", [((61, 47, 5), 1, 1e-3), ((40, 70, 31), 3, 1e-2), ((9, 13, 2), 10, 0.5),
                                           ((1, 30, 1), 2, 1e-4)])
def test_against_the_numpy_reference(queue, shape, r, eps):
    rng = np.random.default_rng(sum(shape) + r)
    H, W, B = shape
    g = rng.uniform(0, 1, (H, W)).astype(np.float32)
    g[:, W // 2:] += 1.0
    p = (rng.normal(size=shape) + 0.5 * g[..., None]).astype(np.float32)
    got = guided_filter(p, g, radius=r, eps=eps, device=queue)
    np.testing.assert_allclose(got, guided_filter_numpy(p, g, r, eps), rtol=1e-4, atol=2e-5)


def test_device_arrays_stay_on_the_device(queue):
    rng = np.random.default_rng(1)
    p = rng.normal(size=(20, 30, 3)).astype(np.float32)
    g = rng.uniform(size=(20, 30)).astype(np.float32)
    out = guided_filter(cla.to_device(queue, p), cla.to_device(queue, g), radius=2, eps=1e-2)
    assert isinstance(out, cla.Array)
    np.testing.assert_allclose(out.get(), guided_filter_numpy(p, g, 2, 1e-2), rtol=1e-4, atol=2e-5)


def test_a_step_edge_of_the_guide_stays_sharp_and_flat_noise_goes(queue):
    rng = np.random.default_rng(2)
    H, W, r = 80, 80, 3
    g = np.where(np.arange(W) < 40, 0.3, 1.0)[None, :].repeat(H, 0).astype(np.float32)
    clean = np.stack([g * 0.5, 1.0 - g * 0.4], axis=-1).astype(np.float32)
    sigma = 0.02
    p = (clean + rng.normal(0, sigma, clean.shape)).astype(np.float32)
    q = guided_filter(p, g + rng.normal(0, 1e-3, g.shape).astype(np.float32), radius=r, eps=1e-3, device=queue)
    # the columns either side of the step keep their own level (a box blur would mix them half and half)
    assert np.abs(q[:, 39] - clean[:, 39]).mean() < 0.01 and np.abs(q[:, 40] - clean[:, 40]).mean() < 0.01
    # away from the edge and the borders the noise falls as the mean of box means predicts
    inner = q[10:-10, 5:30] - clean[10:-10, 5:30]
    predicted = np.sqrt(box_box_variance(np.full((H, W, 1), sigma ** 2), r)[40, 20, 0])
    assert inner.std() == pytest.approx(predicted, rel=0.2)
    assert inner.std() < sigma / 4


@settings(max_examples=30, deadline=None)
@given(r=st.one_of(st.integers(-3, 0), st.floats(0.5, 2.5).filter(lambda v: v != int(v))),
       eps=st.one_of(st.floats(-1, 0), st.just(float("nan"))))
def test_bad_radius_or_eps_is_one_line(r, eps):
    p = np.zeros((8, 8, 2), np.float32)
    g = np.zeros((8, 8), np.float32)
    for kw in ({"radius": r, "eps": 1e-3}, {"radius": 2, "eps": eps}):
        with pytest.raises(ValueError) as info:
            guided_filter(p, g, **kw)
        assert "\n" not in str(info.value)


def test_shapes_are_checked():
    with pytest.raises(ValueError, match=r"guide must be \(H, W\)"):
        guided_filter(np.zeros((8, 8, 2), np.float32), np.zeros((8, 9), np.float32), radius=1, eps=1e-3)
    with pytest.raises(ValueError, match="image must be"):
        guided_filter(np.zeros((8, 8), np.float32), np.zeros((8, 8), np.float32), radius=1, eps=1e-3)


def test_box_box_variance_is_the_sum_of_squared_weights():
    r = 2
    v = np.zeros((21, 21, 1))
    v[10, 10] = 1.0  # one pixel's unit variance reaches each output by its weight squared
    out = box_box_variance(v, r)
    t = (2 * r + 1 - np.abs(np.arange(-2 * r, 2 * r + 1))) / (2 * r + 1) ** 2
    np.testing.assert_allclose(out[10 - 2 * r:10 + 2 * r + 1, 10 - 2 * r:10 + 2 * r + 1, 0], np.outer(t, t) ** 2,
                               rtol=1e-5, atol=1e-12)
    assert box_box_variance(np.ones((15, 15, 1)), r)[7, 7, 0] == pytest.approx(np.sum(np.outer(t, t) ** 2), rel=1e-5)


@pytest.mark.parametrize("r", [1, 2, 4])
def test_flat_variance_reduction_is_what_the_filter_does_on_a_flat_guide(queue, r):
    rng = np.random.default_rng(r)
    H = W = 160
    p = rng.normal(0.0, 1.0, (H, W, 2)).astype(np.float32)
    q = guided_filter(p, np.full((H, W), 0.5, np.float32), radius=r, eps=1e-3, device=queue)
    inner = q[3 * r:-3 * r, 3 * r:-3 * r]
    assert 1.0 / inner.var() == pytest.approx(flat_variance_reduction(r), rel=0.12)
    assert flat_variance_reduction(2) == pytest.approx(625.0 ** 2 / 85.0 ** 2)  # (sum of the triangle's squares)^-2
