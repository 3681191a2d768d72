"""kernels/gradient.cl through gradient_images against the host's gradient_image, on every device."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

from specgpu.engine.gradients import gradient_images
from specgpu.motion.images import gradient_image


def frames_of(rng, dtype, K, h, w):
    """K frames with structure and noise, in the range of ``dtype``."""
    yy, xx = np.mgrid[0:h, 0:w]
    base = 400 + 300 * np.sin(xx / 3.0) * np.cos(yy / 5.0)
    frames = np.stack([base * rng.uniform(0.5, 1.5) + rng.normal(0, 20, (h, w)) for _ in range(K)])
    if dtype == np.uint8:
        frames = frames / 4.0
    return np.clip(frames, 0, None).astype(dtype)


def host_images(frames, dark, gain):
    return np.stack([gradient_image(f, None if dark is None else (dark[k] if dark.ndim == 3 else dark), gain)
                     for k, f in enumerate(frames)])


def assert_images(got, want):
    """Equal to float32 rounding: the magnitudes' own (a multiply-add where the host rounds twice) and the mean's
    (compensated float32 sums where the host sums in float64)."""
    assert got.dtype == np.float32 and got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=2e-6 * float(np.abs(want).max()))


@pytest.mark.parametrize("dtype", [np.uint16, np.float32, np.uint8])
@pytest.mark.parametrize("calibration", ["none", "dark and gain", "a dark per frame", "a dead pixel"])
def test_device_gradient_images_are_the_hosts(queue, dtype, calibration):
    rng = np.random.default_rng(int(np.dtype(dtype).itemsize) * 10 + len(calibration))
    K, h, w = 3, 37, 53  # neither side a multiple of 8
    frames = frames_of(rng, dtype, K, h, w)
    dark = gain = None
    if calibration != "none":
        dark = rng.uniform(0, 8, (K, h, w) if calibration == "a dark per frame" else (h, w)).astype(np.float32)
        gain = rng.uniform(0.8, 1.2, (h, w)).astype(np.float32)
    if calibration == "a dead pixel":
        gain[5, 7] = gain[0, 0] = gain[h - 1, w - 1] = np.nan  # read 0 (the corners: the mirrored border too)
    got = gradient_images(frames, dark, gain, device=queue)
    assert isinstance(got, cla.Array)
    want = host_images(frames, dark, gain)
    assert_images(got.get(), want)
    if calibration == "a dead pixel":  # the pixel with no response reads 0: its neighbours see the step
        assert np.isfinite(got.get()).all() and got.get()[0, 5, 6] > 0


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (7, 1), (2, 3), (9, 8), (16, 17)])
def test_tiny_and_odd_images(queue, shape):
    rng = np.random.default_rng(sum(shape))
    frames = frames_of(rng, np.float32, 2, *shape)
    dark = rng.uniform(0, 5, shape).astype(np.float32)
    assert_images(gradient_images(frames, dark, device=queue).get(), host_images(frames, dark, None))


def test_a_frame_without_signal_keeps_its_magnitudes(queue):
    """gradient_image divides by the mean only where it is positive."""
    rng = np.random.default_rng(3)
    frames = frames_of(rng, np.float32, 2, 20, 24)
    frames[1] -= frames[1].mean() + 1.0  # a negative mean
    assert_images(gradient_images(frames, device=queue).get(), host_images(frames, None, None))


def test_frames_already_on_the_device(queue):
    rng = np.random.default_rng(4)
    frames = frames_of(rng, np.uint16, 4, 30, 41)
    dark = rng.uniform(0, 8, (30, 41)).astype(np.float32)
    want = host_images(frames, dark, None)
    on_device = cla.to_device(queue, frames)
    assert_images(gradient_images(on_device, cla.to_device(queue, dark)).get(), want)
    buffer = cl.Buffer(queue.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=frames)
    assert_images(gradient_images(buffer, dark, shape=frames.shape, dtype=np.uint16, device=queue).get(), want)


def test_bad_inputs_are_refused(queue):
    frames = np.zeros((3, 10, 12), np.uint16)
    with pytest.raises(ValueError, match="frames must be"):
        gradient_images(frames[0], device=queue)
    with pytest.raises(ValueError, match="dark has shape"):
        gradient_images(frames, np.zeros((2, 10, 12), np.float32), device=queue)
    with pytest.raises(ValueError, match="gain has shape"):
        gradient_images(frames, None, np.ones((10, 11), np.float32), device=queue)
    with pytest.raises(ValueError, match="dark contains NaN"):
        gradient_images(frames, np.full((10, 12), np.nan, np.float32), device=queue)
    with pytest.raises(TypeError, match="dtype"):
        gradient_images(frames.astype(np.int32), device=queue)
    buffer = cl.Buffer(queue.context, cl.mem_flags.READ_ONLY, 100)
    with pytest.raises(ValueError, match="need shape"):
        gradient_images(buffer, device=queue)
    with pytest.raises(ValueError, match="fewer than"):
        gradient_images(buffer, shape=(3, 10, 12), dtype=np.uint16, device=queue)
