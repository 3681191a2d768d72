"""The warped samples' variances for the denoised sigma in one pass over the frames: the total, the pixels' own part
and that part as the filter takes it, each equal to the sample variance written out tap by tap, and each frame's
sample points made once per sequence (not once per variance)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from moving_helpers import moving_setup

import specgpu.pipeline.moving_decode as moving_decode
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel


@pytest.fixture(scope="module")
def noisy_plan():
    desc, bundle, plan, _ = moving_setup()
    return with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s)), bundle


def tap_by_tap(frames, plan, dark, gain, shifts, k, *, light, filtered):
    """One frame's sample variance, pixel by pixel: its four bilinear taps' own variances (weights squared, or the
    weights times the interpolation's correlation for the filter), the light's fluctuation at the sample."""
    noise = NoiseModel.from_params(plan.params["noise"])
    h, w = frames.shape[1:]
    x = frames[k].astype(np.float64) - dark
    g2 = gain.astype(np.float64) ** 2
    own = g2 * (x / noise.gain_e_per_dn + noise.read_var_dn2)
    signal = np.sqrt(g2) * x
    corr = None if filtered is None else 1.0 - np.dot(*(lambda t: (t[1:], t[:-1]))(
        np.sqrt(moving_decode.box_box_squares(filtered)))) / np.sum(moving_decode.box_box_squares(filtered))
    out = np.full((h, w), np.nan)
    for py in range(h):
        for px in range(w):
            sx, sy = px + shifts[k][0], py + shifts[k][1]
            if not (-0.5 - 1e-3 <= sx <= w - 0.5 + 1e-3 and -0.5 - 1e-3 <= sy <= h - 0.5 + 1e-3):
                continue
            sx, sy = min(max(sx, 0), w - 1), min(max(sy, 0), h - 1)
            x0, y0 = int(np.floor(sx)), int(np.floor(sy))
            fx, fy = sx - x0, sy - y0
            taps = [(y0, x0, (1 - fx) * (1 - fy)), (y0, min(x0 + 1, w - 1), fx * (1 - fy)),
                    (min(y0 + 1, h - 1), x0, (1 - fx) * fy), (min(y0 + 1, h - 1), min(x0 + 1, w - 1), fx * fy)]
            if corr is not None:
                v = sum(wt * own[r, c] for r, c, wt in taps) * (1 - 2 * fx * (1 - fx) * corr) * (
                    1 - 2 * fy * (1 - fy) * corr)
            else:
                v = sum(wt * wt * own[r, c] for r, c, wt in taps)
                if light:
                    v += (noise.light_rms * sum(wt * signal[r, c] for r, c, wt in taps)) ** 2
            out[py, px] = v
    return out


def test_the_three_variances_equal_the_samples_written_out(noisy_plan):
    plan, bundle = noisy_plan
    rng = np.random.default_rng(2)
    h, w = 9, 11
    frames = rng.uniform(300.0, 3000.0, (plan.K, h, w))
    dark = np.full((h, w), 64.0)
    gain = rng.uniform(0.9, 1.1, (h, w))
    shifts = rng.uniform(-1.6, 1.6, (plan.K, 2))
    read = [0, 2, 3]
    total, own, smoothed = moving_decode.warped_sample_variances(frames, plan, dark, gain, shifts, read=read,
                                                                 light=True, filtered=2)
    for n, k in enumerate(read):
        for got, kw in ((total, {"light": True, "filtered": None}), (own, {"light": False, "filtered": None}),
                        (smoothed, {"light": False, "filtered": 2})):
            want = tap_by_tap(frames, plan, dark, gain, shifts, k, **kw)
            np.testing.assert_array_equal(np.isnan(got[n]), np.isnan(want))
            np.testing.assert_allclose(np.nan_to_num(got[n]), np.nan_to_num(want), rtol=1e-6)  # float32 gain
    assert NoiseModel.from_params(plan.params["noise"]).light_rms > 0
    assert np.nanmin(total - own) > 0  # the light's part is there: the comparison can fail
    # the public single-variance form is the same numbers
    np.testing.assert_array_equal(moving_decode.warped_sample_variance(frames, plan, dark, gain, shifts, read=read,
                                                                       filtered=2), smoothed)


def test_the_denoised_sigma_reads_each_frames_samples_once(noisy_plan, monkeypatch):
    plan, bundle = noisy_plan
    rng = np.random.default_rng(3)
    h, w = 24, 32
    frames = rng.uniform(500.0, 2000.0, (plan.K, h, w))
    shifts = np.column_stack([np.linspace(0, 2.5, plan.K), np.linspace(0, -1.5, plan.K)])
    rec = SimpleNamespace(estimates=[SimpleNamespace(shifts=shifts)], mask=np.zeros((h, w), np.uint8), layers=[])
    B = plan.A.shape[0]
    pixels = np.zeros((h, w), bool)
    pixels[4:-4, 4:-4] = True
    smoothed = {"pixels": pixels, "guide": rng.uniform(0.5, 1.0, (h, w)).astype(np.float32), "level": 3000.0,
                "slopes": rng.uniform(0.1, 0.9, (h, w, B)).astype(np.float32), "radius": 2, "eps": 1e-4}
    calls = []
    inner = moving_decode._sample_points

    def counted(*args):
        calls.append(args[1])
        return inner(*args)

    monkeypatch.setattr(moving_decode, "_sample_points", counted)
    dark = bundle.dark_at(plan.exposure_s)[:h, :w]
    sigma, _ = moving_decode.warped_uncertainty(frames, plan, dark, bundle.flat_field[:h, :w], rec,
                                                smoothed=smoothed, rms=True)
    read = np.flatnonzero(np.any(np.asarray(plan.A) != 0, axis=0))
    assert sorted(calls) == sorted(read.tolist())  # once per frame read, for all three variances
    plain, _ = moving_decode.warped_uncertainty(frames, plan, dark, bundle.flat_field[:h, :w], rec, rms=True)
    assert np.all(np.isfinite(sigma[pixels])) and np.all(sigma[pixels] < plain[pixels])  # the filter averaged
    np.testing.assert_array_equal(sigma[~pixels], plain[~pixels])
