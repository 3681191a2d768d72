"""The motion-compensated outputs' variance on the device (:class:`specgpu.engine.warped_variance.
PreparedWarpedVariance`) against the float64 NumPy reference, the per-frame sample variances
(:func:`specgpu.pipeline.moving_decode.warped_sample_variances`) summed through the same weights."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pyopencl.array as cla
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.engine.warped_variance import PreparedWarpedVariance
from specgpu.pipeline.moving_decode import _interpolation_correlation, warped_sample_variances
from specgpu.planning.noise import NoiseModel

NOISE = NoiseModel(gain_e_per_dn=2.5, read_var_dn2=6.0, light_rms=0.004)


def _sensor(K=6, h=19, w=37, seed=0, dtype=np.uint16):
    rng = np.random.default_rng(seed)
    frames = rng.uniform(80.0, 3000.0, size=(K, h, w))
    frames = frames.astype(dtype) if dtype != np.float32 else frames.astype(np.float32)
    dark = rng.uniform(60.0, 70.0, size=(h, w)).astype(np.float32)
    gain = rng.uniform(0.85, 1.15, size=(h, w)).astype(np.float32)
    return frames, dark, gain


def _reference(frames, dark, gain, shifts, read, weights, *, light, radius, ambient):
    plan = SimpleNamespace(params={"noise": NOISE.as_params()})
    total, own, filt = warped_sample_variances(frames, plan, dark, gain, shifts, read=read, light=light,
                                               filtered=radius, ambient=ambient)
    W = np.asarray(weights, np.float64)
    return [None if V is None else np.tensordot(V, W.T, axes=([0], [0])) for V in (total, own, filt)]


def _prepared(queue, frames, dark, gain):
    return PreparedWarpedVariance(queue, frames.shape[1:], dark, gain, gain_e_per_dn=NOISE.gain_e_per_dn,
                                  read_var_dn2=NOISE.read_var_dn2, light_rms=NOISE.light_rms)


def _shifts(kind, K, rng):
    d = rng.uniform(-3.0, 3.0, size=(K, 2))
    d[0] = 0.0
    if kind == "translation":
        return d
    m = np.zeros((K, 2, 3))
    for k in range(K):
        a = rng.uniform(-0.02, 0.02)
        m[k] = [[np.cos(a), -np.sin(a), d[k, 0]], [np.sin(a), np.cos(a), d[k, 1]]]
    return m


def _assert_close(got, want):
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(np.nan_to_num(got), np.nan_to_num(want), rtol=2e-5, atol=1e-4)


@pytest.mark.parametrize("kind", ["translation", "affine"])
@pytest.mark.parametrize(("light", "radius", "ambient"), [(True, None, None), (True, 2, 3), (False, 4, None),
                                                          (True, 2, None)])
def test_the_channels_equal_the_float64_reference(queue, kernel_variant, kind, light, radius, ambient):
    """Both kernel variants: vectors of 8 pixels (translations read as vectors inside the field) and one pixel."""
    rng = np.random.default_rng(7)
    frames, dark, gain = _sensor()
    gain[4, 5] = np.nan  # no response: every sample that reads it NaN
    gain[9, 9] = 100.0  # at the dead-pixel gain: the same
    K = frames.shape[0]
    read = [0, 1, 2, 3, 5]  # frame 4 read by no output
    weights = rng.uniform(0.0, 2.0, size=(3, len(read)))
    shifts = _shifts(kind, K, rng)
    want = _reference(frames, dark, gain, shifts, read, weights, light=light, radius=radius, ambient=ambient)
    corr = None if radius is None else _interpolation_correlation(radius)
    got = _prepared(queue, frames, dark, gain).channels(frames, shifts, read, weights, light=light,
                                                        ambient=ambient, own=True, corr=corr)
    assert got[0].shape == (*frames.shape[1:], 3) and got[0].dtype == np.float32
    _assert_close(got[0], want[0])
    _assert_close(got[1], want[1])
    if radius is None:
        assert got[2] is None
    else:
        _assert_close(got[2], want[2])
    assert np.isnan(got[0]).any() and np.isfinite(got[0]).any()  # the field's edges, the dead pixels


@settings(max_examples=25, deadline=None)
@given(dx=st.floats(-6.0, 6.0), dy=st.floats(-6.0, 6.0), dtype=st.sampled_from([np.uint8, np.uint16, np.float32]))
def test_any_translation_and_frame_type(queue, dx, dy, dtype):
    frames, dark, gain = _sensor(K=3, h=11, w=14, seed=2, dtype=np.float32)
    if dtype == np.uint8:
        frames = np.clip(frames / 12.0, 0, 255).astype(np.uint8)
        dark = (dark / 12.0).astype(np.float32)
    elif dtype == np.uint16:
        frames = frames.astype(np.uint16)
    shifts = np.array([[0.0, 0.0], [dx, dy], [-dy, dx]])
    weights = np.array([[1.0, 0.5, 2.0]])
    want = _reference(frames, dark, gain, shifts, [0, 1, 2], weights, light=True, radius=None, ambient=None)
    got = _prepared(queue, frames, dark, gain).channels(frames, shifts, [0, 1, 2], weights)
    _assert_close(got[0], want[0])
    assert got[1] is None and got[2] is None


def test_without_a_flat_field_or_light(queue):
    frames, dark, _ = _sensor(K=4, seed=5)
    noise = NoiseModel(gain_e_per_dn=3.0, read_var_dn2=2.0, light_rms=0.0)
    prep = PreparedWarpedVariance(queue, frames.shape[1:], dark, None, gain_e_per_dn=3.0, read_var_dn2=2.0,
                                  light_rms=0.0)
    shifts = np.array([[0.0, 0.0], [1.25, -0.5], [2.5, -1.0], [3.75, -1.5]])
    got, own, _ = prep.channels(frames, shifts, [0, 1, 2, 3], np.eye(4)[:2], own=True)
    plan = SimpleNamespace(params={"noise": noise.as_params()})
    total, _, _ = warped_sample_variances(frames, plan, dark, None, shifts, read=[0, 1, 2, 3])
    want = np.moveaxis(total[:2], 0, -1).copy()
    want[np.isnan(total).any(axis=0)] = np.nan  # a frame seen outside: every channel NaN, as the weighted sum is
    _assert_close(got, want)
    _assert_close(own, got)  # no light: the own part is all of it


def test_bad_input_is_refused_in_one_line(queue):
    frames, dark, gain = _sensor(K=3, h=8, w=9)
    prep = _prepared(queue, frames, dark, gain)
    zero = np.zeros((3, 2))
    cases = [
        (lambda: prep.channels(frames[:, :4], zero, [0, 1], [[1.0, 1.0]]), "frames must be"),
        (lambda: prep.channels(frames, zero, [0, 3], [[1.0, 1.0]]), "read must name frames 0 .. 2"),
        (lambda: prep.channels(frames, zero, [0, 1], [[1.0, 1.0, 1.0]]), "weights must be"),
        (lambda: prep.channels(frames, zero, [0, 1], [[np.nan, 1.0]]), "weights must be"),
        (lambda: prep.channels(frames, np.zeros((3, 2, 8, 9)), [0, 1], [[1.0, 1.0]]), "dense flow"),
        (lambda: prep.channels(frames, np.zeros((2, 2)), [0, 1], [[1.0, 1.0]]), "shifts must have shape"),
        (lambda: prep.channels(frames, zero, [0, 1], [[1.0, 1.0]], ambient=5), "ambient must name"),
        (lambda: prep.channels(cla.to_device(queue, frames.astype(np.float64).reshape(-1)), zero, [0, 1],
                               [[1.0, 1.0]]), "must be uint8, uint16 or float32 on the device"),
        (lambda: prep.channels(cla.to_device(queue, frames.reshape(-1)[:-3]), zero, [0, 1], [[1.0, 1.0]]),
         "whole 8 x 9 frames"),
        (lambda: PreparedWarpedVariance(queue, (8, 9), dark[:4], gain, gain_e_per_dn=1.0, read_var_dn2=1.0,
                                        light_rms=0.0), "dark must be"),
        (lambda: PreparedWarpedVariance(queue, (8, 9), dark, gain, gain_e_per_dn=0.0, read_var_dn2=1.0,
                                        light_rms=0.0), "gain_e_per_dn must be"),
    ]
    for call, text in cases:
        with pytest.raises((ValueError, TypeError)) as info:
            call()
        message = str(info.value)
        assert text in message and "\n" not in message, message
