"""The consistency check's noise floors made on the device (:func:`specgpu.motion.consistency.noise_floors_on_device`,
:mod:`specgpu.engine.noise_floor`) against the NumPy reference (:func:`specgpu.motion.consistency.noise_floors`),
and read in place by the check."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.engine.noise_floor import FloorPlanes, PreparedNoiseFloors
from specgpu.motion.consistency import CHECK_THRESHOLD, consistency, noise_floors, noise_floors_on_device
from specgpu.planning.noise import NoiseModel

NOISE = NoiseModel(gain_e_per_dn=3.0, read_var_dn2=5.0, light_rms=0.01)


def _sensor(K=4, h=37, w=75, seed=0, dtype=np.uint16):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    scene = 800 + 600 * np.sin(xx / 5.0) * np.cos(yy / 7.0)
    frames = np.stack([scene * (0.5 + 0.3 * k) + rng.normal(0, 20, (h, w)) for k in range(K)])
    frames = np.clip(frames, 0, 4000).astype(dtype)
    dark = rng.uniform(40, 50, (h, w)).astype(np.float32)
    gain = rng.uniform(0.9, 1.1, (h, w)).astype(np.float32)
    return frames, dark, gain


def _close(got, want):
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-9 * float(np.max(want)))


@pytest.mark.parametrize("dtype", [np.uint16, np.uint8, np.float32])
@pytest.mark.parametrize("with_gain", [True, False])
def test_the_device_floors_equal_the_reference(queue, kernel_variant, dtype, with_gain):
    """Both kernel variants: strips of 8 columns and spans of a row, or a pixel per work-item."""
    frames, dark, gain = _sensor(dtype=np.float32)
    if dtype == np.uint8:
        frames, dark = np.clip(frames / 16, 0, 255).astype(np.uint8), dark / 16
    elif dtype == np.uint16:
        frames = frames.astype(np.uint16)
    gain = gain if with_gain else None
    if with_gain:
        gain[3, 4] = np.nan  # no response: read as 0, as the gradient images read it
    want = noise_floors(frames, NOISE, dark, gain)
    got = noise_floors_on_device(frames, NOISE, dark, gain, device=queue)
    assert isinstance(got, FloorPlanes) and got.shape == frames.shape
    _close(got.get(), want)


@settings(max_examples=15, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 90), window=st.sampled_from([1, 3, 9, 11]))
def test_any_size_and_window_against_the_reference(queue, h, w, window):
    """Windows wider than the image, single rows and columns, partial vectors, strips and spans."""
    frames, dark, gain = _sensor(K=2, h=h, w=w, seed=h * 100 + w)
    want = noise_floors(frames, NOISE, dark, gain, window=window)
    got = noise_floors_on_device(frames, NOISE, dark, gain, window=window, device=queue).get()
    _close(got, want)


def test_a_long_row_keeps_its_precision(queue):
    """2048 px rows of a bright frame: a running sum starts afresh every span of a row."""
    rng = np.random.default_rng(3)
    frames = rng.integers(3000, 4000, (1, 6, 2048)).astype(np.uint16)
    want = noise_floors(frames, NOISE, None, None)
    _close(noise_floors_on_device(frames, NOISE, None, None, device=queue).get(), want)


def test_the_check_reads_device_floors_as_host_ones(queue):
    """A bright flat patch on a dim field, still: its shot noise is structure to the median's test alone, and the
    floor (made on the host, or on the device and read there) takes it away alike."""
    rng = np.random.default_rng(0)
    noise = NoiseModel(gain_e_per_dn=2.0, read_var_dn2=4.0)
    signal = np.full((5, 64, 96), 30.0)
    signal[:, 16:48, 24:72] = 3000.0
    frames = (16.0 + signal + rng.normal(size=signal.shape) * np.sqrt(signal / 2.0 + 4.0)).astype(np.float32)
    dark = np.full((64, 96), 16.0, np.float32)
    still = np.zeros((5, 2))
    none = consistency(frames, still, dark)[1]
    host = consistency(frames, still, dark, floor=noise_floors(frames, noise, dark))[1]
    planes = noise_floors_on_device(frames, noise, dark, device=queue)
    device = consistency(frames, still, dark, floor=planes.take())[1]
    assert (none < CHECK_THRESHOLD).sum() > 100 * max(1, (host < CHECK_THRESHOLD).sum())  # the floor matters
    np.testing.assert_allclose(device, host, atol=1e-5)
    # a subset of the planes, in another order, as an object layer's check takes them
    np.testing.assert_array_equal(planes.take([3, 1, 4]).get(), planes.get()[[3, 1, 4]])


def test_floors_of_another_context_are_read_back_not_bound(queue):
    """The check runs on its own queue: floors made in another context (another device) are read back and uploaded
    there, not passed as a buffer the check's context does not own."""
    import pyopencl as cl

    frames, dark, gain = _sensor(K=3, h=24, w=40, seed=6)
    other = cl.CommandQueue(cl.Context([queue.device]))
    planes = noise_floors_on_device(frames, NOISE, dark, gain, device=other)
    assert planes.array.context != queue.context
    still = np.zeros((3, 2))
    host = consistency(frames, still, dark, gain, floor=noise_floors(frames, NOISE, dark, gain))
    got = consistency(frames, still, dark, gain, floor=planes.take())
    np.testing.assert_array_equal(got[0], host[0])
    np.testing.assert_allclose(got[1], host[1], atol=1e-5)


def test_bad_input_is_refused_in_one_line(queue):
    frames, dark, gain = _sensor(K=3, h=8, w=9)
    prep = PreparedNoiseFloors(queue, (8, 9), dark, gain, gain_e_per_dn=1.0, read_var_dn2=1.0)
    cases = [
        (lambda: prep.floors(frames[:, :4], [1.0] * 3), "frames must be"),
        (lambda: prep.floors(frames, [1.0] * 2), "coef must be 3"),
        (lambda: prep.floors(frames, [1.0, np.nan, 1.0]), "coef must be 3"),
        (lambda: prep.floors(frames, [1.0], read=[5]), "read must name frames 0 .. 2"),
        (lambda: PreparedNoiseFloors(queue, (8, 9), dark, gain, gain_e_per_dn=1.0, read_var_dn2=1.0, window=4),
         "odd width"),
        (lambda: PreparedNoiseFloors(queue, (8, 9), dark[:3], gain, gain_e_per_dn=1.0, read_var_dn2=1.0),
         "dark must be"),
        (lambda: PreparedNoiseFloors(queue, (8, 9), dark, gain, gain_e_per_dn=-1.0, read_var_dn2=1.0),
         "gain_e_per_dn must be"),
        (lambda: FloorPlanes(prep.floors(frames, [1.0] * 3).array.reshape(3, 72)), "floor planes must be"),
        (lambda: prep.floors(frames, [1.0] * 3).take([0, 3]), "frames must name planes 0 .. 2"),
    ]
    for call, text in cases:
        with pytest.raises((ValueError, TypeError)) as info:
            call()
        message = str(info.value)
        assert text in message and "\n" not in message, message
