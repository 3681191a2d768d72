"""Temporal accumulation: on a still scene the running estimate is the mean of the sequences so far (up to N),
its noise falling as 1 / sqrt(N); where a pixel changes beyond its noise it restarts from the new value; outputs
it cannot average are refused in one line; ``stream --accumulate`` runs."""

from types import SimpleNamespace

import numpy as np
import pytest

from specgpu.pipeline.accumulate import AccumulateSink


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


def test_refusals_are_one_line():
    for outputs, why in ((("cube", "sigma_rms", "dE"), "not linear"), (("cube", "XYZ"), "needs the cube and sigma"),
                         (("XYZ", "sigma"), "needs the cube")):
        with pytest.raises(ValueError, match=why) as info:
            AccumulateSink(4, outputs)
        assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="--accumulate"):
        AccumulateSink(1, ("cube", "sigma"))
