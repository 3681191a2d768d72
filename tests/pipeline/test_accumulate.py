"""Temporal accumulation: on a still scene the running estimate is the mean of the sequences so far (up to N),
its noise falling as 1 / sqrt(N); where a pixel changes beyond its noise it restarts from the new value; outputs
it cannot average are refused in one line; ``stream --accumulate`` runs."""

from types import SimpleNamespace

import numpy as np
import pytest

from specgpu.pipeline.accumulate import AccumulateSink, sequence_displacement, shift_image


def _result(cube, sigma):
    return SimpleNamespace(arrays={"cube": cube.copy(), "XYZ": cube[..., :3].copy() * 2.0,
                                   "sigma_rms": np.full(cube.shape[:2] + (1,), sigma, np.float32)})


def test_a_still_scene_is_averaged_and_a_change_restarts():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.1, 0.9, (30, 40, 8)).astype(np.float32)
    sigma = 0.02
    sink = AccumulateSink(4, ("cube", "XYZ", "sigma_rms"))
    raw, out = [], []
    for k in range(12):
        scene = truth.copy()
        if k >= 8:
            scene[:10, :10] += 0.5  # an object arrives: 25 x the noise
        y = (scene + rng.normal(0, sigma, scene.shape)).astype(np.float32)
        r = _result(y, sigma)
        sink.write(r)
        raw.append(y)
        out.append(r.arrays["cube"].copy())
        np.testing.assert_allclose(r.arrays["XYZ"], 2.0 * r.arrays["cube"][..., :3], rtol=1e-5)
    # the first N results are the plain means of the sequences so far
    for k in range(4):
        np.testing.assert_allclose(out[k], np.mean(raw[:k + 1], axis=0), atol=1e-5)
    # the noise falls about as 1 / sqrt(N) on the still part
    err = np.std(out[7][10:] - truth[10:])
    assert 0.35 * sigma < err < 0.65 * sigma
    # the changed block restarts from the new value (no trail of the old scene), the rest keeps its estimate
    np.testing.assert_allclose(out[8][:10, :10], raw[8][:10, :10], atol=1e-6)
    assert sink.counts[:10, :10].max() == 4 and sink.resets[7] == pytest.approx(100 / 1200, abs=0.01)
    assert np.abs(out[11][:10, :10] - (truth[:10, :10] + 0.5)).std() < 0.7 * sigma
    assert max(sink.resets[:7]) < 0.005  # no false restarts of a still scene


@pytest.mark.parametrize("constant", [0.0, 0.01])
def test_the_recorded_sigma_is_the_estimates_own(constant):
    """Noise of a per-pixel sigma and a fixed per-pixel bias of variance ``constant`` (the prior's mismatch, the
    same in every sequence): the accumulated estimate's error over its recorded sigma has z-scores of spread 1,
    while the mean stays a plain mean (N sequences) and then a recursive one; the RMS channel agrees."""
    rng = np.random.default_rng(3)
    shape, N = (40, 50, 6), 4
    truth = rng.uniform(0.2, 0.8, shape).astype(np.float32)
    noise = rng.uniform(0.01, 0.04, shape[:2]).astype(np.float32)[..., None] * np.ones(shape[-1], np.float32)
    bias = rng.normal(0.0, np.sqrt(constant), shape).astype(np.float32) if constant else 0.0
    total = np.sqrt(noise ** 2 + constant)  # one sequence's sigma: the noise and the mismatch
    rms = np.sqrt(np.mean(total ** 2, axis=-1))
    sink = AccumulateSink(N, ("cube", "sigma"), threshold=50.0,
                          constant_variance=np.full(shape[-1], constant) if constant else None)
    for k in range(12):
        y = (truth + bias + rng.normal(0.0, 1.0, shape) * noise).astype(np.float32)
        r = SimpleNamespace(arrays={"cube": y, "sigma": np.concatenate([total, rms[..., None]], -1).copy()})
        sink.write(r)
        c = min(k + 1, N)
        z = (r.arrays["cube"] - truth) / r.arrays["sigma"][..., :-1]
        assert np.std(z) == pytest.approx(1.0, abs=0.05), (k, np.std(z))
        if k > 0:
            assert np.std((r.arrays["cube"] - truth - bias) / noise) < (0.75 if k >= 2 else 0.8)  # it did fall
        if k < N:  # a plain mean of k + 1 sequences: the noise variance over k + 1
            np.testing.assert_allclose(sink.factor, 1.0 / c, rtol=1e-5)
        want_rms = np.sqrt(sink.factor * np.mean(noise ** 2, axis=-1) + constant)
        np.testing.assert_allclose(r.arrays["sigma"][..., -1], want_rms, rtol=1e-4)
    # beyond N the recursive mean of weight 1 / N: its variance tends to 1 / (2 N - 1) of one sequence's
    assert sink.factor.mean() == pytest.approx(1.0 / (2 * N - 1), rel=0.05)


def test_refusals_are_one_line():
    for outputs, why in ((("cube", "sigma_rms", "dE"), "not linear"), (("cube", "XYZ"), "needs the cube and sigma"),
                         (("XYZ", "sigma"), "needs the cube")):
        with pytest.raises(ValueError, match=why) as info:
            AccumulateSink(4, outputs)
        assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="--accumulate"):
        AccumulateSink(1, ("cube", "sigma"))


# ------------------------------------------------------------------------------------------- along the motion


def _texture(shape, bands, seed=1):
    """A smooth random texture as a function of continuous (x, y): sums of sinusoids up to 0.12 cycles per px, so
    any translation of it is known exactly."""
    rng = np.random.default_rng(seed)
    n = 12
    freq = rng.uniform(-0.12, 0.12, (n, 2))
    phase = rng.uniform(0, 2 * np.pi, n)
    amp = rng.uniform(0.02, 0.06, (bands, n))

    def at(dx=0.0, dy=0.0):
        y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
        waves = np.cos(2 * np.pi * (freq[:, 0, None, None] * (x - dx) + freq[:, 1, None, None] * (y - dy))
                       + phase[:, None, None])
        return (0.5 + np.einsum("bn,nhw->hwb", amp, waves)).astype(np.float32)
    return at


def test_shift_image_whole_pixels_is_a_slice_and_a_quadratic_is_exact():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(20, 30, 2)).astype(np.float32)
    out = shift_image(a, (3, -2))  # out(x) = a(x - shift)
    np.testing.assert_array_equal(out[:18, 3:], a[2:, :27])
    assert np.isnan(out[:, :3]).all() and np.isnan(out[18:]).all()
    counts = np.arange(600).reshape(20, 30)
    moved = shift_image(counts, (-4, 1), fill=0)
    assert moved.dtype == counts.dtype and moved[0].max() == 0 and moved[1, 0] == counts[0, 4]
    with pytest.raises(ValueError, match="whole pixels"):
        shift_image(counts, (0.5, 0), fill=0)
    # cubic convolution reproduces a quadratic exactly at a fractional shift where its four taps are inside; NaN
    # only where the sample point is beyond the pixels' footprint (x - 1.3 < -1/2: the first column; y + 0.6 >
    # 19.5: the last row), the taps clamped to the field nearer the edge
    y, x = np.mgrid[:20, :30].astype(np.float64)
    q = lambda x, y: 0.3 + 0.01 * x - 0.02 * y + 0.001 * x * x + 0.002 * x * y - 0.0015 * y * y  # noqa: E731
    out = shift_image(q(x, y)[..., None], (1.3, -0.6))[..., 0]
    assert np.isnan(out[:, 0]).all() and np.isnan(out[-1]).all() and np.isfinite(out[:-1, 1:]).all()
    np.testing.assert_allclose(out[1:18, 3:], q(x - 1.3, y + 0.6)[1:18, 3:], atol=1e-5)
    assert abs(out[0, 1] - q(0.0, 0.6)) < 0.01  # the clamped taps near the edge: close, not exact
    # a NaN of the estimate stays where its nearest sample is, instead of spreading over the taps' reach
    holed = q(x, y)[..., None].copy()
    holed[8, 12] = np.nan
    moved = shift_image(holed, (1.3, -0.6))[..., 0]
    assert np.argwhere(np.isnan(moved[:-1, 1:])).tolist() == [[7, 12]]  # y + 0.6 -> 8, x - 1.3 -> 12 (+1 column)
    with pytest.raises(ValueError, match="finite fill"):
        shift_image(counts, (1, 0))


def test_the_estimate_moves_with_the_scene_and_its_noise_falls():
    """A texture translating (3.4, -1.7) px per sequence: each step is registered on the decoded cubes, the running
    estimate follows the scene (its error against the moved truth falls as the noise averages), the strips that
    come into view restart, and without the motion the textured pixels restart at every sequence."""
    shape, sigma, step = (64, 96), 0.01, np.array([3.4, -1.7])
    truth = _texture(shape, 6)
    rng = np.random.default_rng(7)
    sinks = {m: AccumulateSink(4, ("cube", "sigma_rms"), motion=m) for m in (True, False)}
    for s in range(8):
        clean = truth(*(s * step))
        y = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
        for sink in sinks.values():
            r = _result(y, sigma)
            sink.write(r)
            if sink.motion:
                est = r.arrays["cube"]
    moving = sinks[True]
    np.testing.assert_allclose(np.array(moving.shifts), np.tile(step, (7, 1)), atol=0.05)
    full = moving.counts == 4
    assert full.mean() > 0.7
    err = est[full] - clean[full]
    assert 0.3 * sigma < err.std() < 0.65 * sigma and abs(err.mean()) < 0.1 * sigma
    # the columns on the left came into view with the last step (the scene moves 3.4 px to the right), and the
    # bottom rows (it moves 1.7 px up): restarted
    assert (moving.counts[:, :3] == 1).all() and (moving.counts[-2:] == 1).all()
    assert max(moving.resets) < 0.2
    assert min(sinks[False].resets) > 0.5  # held still, the moving texture is a change nearly everywhere


def test_sequence_displacement_and_an_object_of_its_own_restarts():
    shape, sigma, step = (128, 192), 0.01, np.array([-2.25, 1.5])
    truth = _texture(shape, 6, seed=4)
    a, b = truth(), truth(*step)
    np.testing.assert_allclose(sequence_displacement(a, b), step, atol=0.05)
    rng = np.random.default_rng(2)
    other = _texture(shape, 6, seed=9)
    sink = AccumulateSink(3, ("cube", "sigma_rms"), motion=True)
    for s in range(5):
        y = truth(*(s * step)) + rng.normal(0, sigma, shape + (6,)).astype(np.float32)
        x0 = 80 + 4 * s  # a textured patch moving 4 px per sequence its own way (right), over the background
        patch = other(4.0 * s, 0.0)[40:72, x0:x0 + 40]
        y[40:72, x0:x0 + 40] = patch
        r = _result(y.astype(np.float32), sigma)
        sink.write(r)
    # registered on the background (the whole-image peak alone is pulled 0.3 px towards the patch)
    np.testing.assert_allclose(sink.shifts, np.tile(step, (4, 1)), atol=0.1)
    # the patch's pixels restart (but where its texture happens to match the background's within the noise), so
    # the estimate there is the patch, with no trail of the background
    assert (sink.counts[40:72, 96:136] == 1).mean() > 0.75
    assert np.sqrt(np.mean((r.arrays["cube"][40:72, 96:136] - patch) ** 2)) < 3 * sigma
    assert np.median(sink.counts[88:, 8:80]) == 3  # the background's are averaged
