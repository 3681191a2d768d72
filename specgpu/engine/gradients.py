"""Gradient images on the device: :func:`specgpu.motion.images.gradient_image` of each frame of a sequence,
made where the frames are (``kernels/gradient.cl``).

A frame's gradient image is the Sobel gradient magnitude of the dark-subtracted, flat-fielded frame (a NaN gain
read as 0) over that frame's mean, the image motion is registered and checked on. On the host it costs about 4 ms a
frame at 640 x 480 (whole-array NumPy slicing); on the device one pass reads each raw frame once, writes the
magnitudes and sums each frame (compensated sums: the mean is NumPy's float64 mean to float32 rounding), and a
second multiplies each image by its frame's 1 / mean. The consistency check needs no second pass: it multiplies
its samples (:func:`specgpu.engine.consistency.consistency_from_frames`).
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.core.validate import check_frames
from specgpu.engine import kernels
from specgpu.engine.runtime import DTYPE_TO_CTYPE, get_kernel, get_queue

__all__ = ["gradient_images", "frames_on_device"]

#: Rows of the strip each work-item of gradient_sobel runs down (a corrected row read once for three output rows)
_ROWS = 64
#: Work-items per group along a row (each 16 pixels)
_GROUP = 1


def frames_on_device(queue, frames, *, shape=None, dtype=None) -> cla.Array:
    """The K frames as a (K, H, W) device array on ``queue``'s context: a NumPy array (uint8, uint16 or float32,
    float64 converted) uploaded in one write, a C-contiguous :class:`pyopencl.array.Array` as it is, or a
    :class:`pyopencl.Buffer` holding ``shape`` (K, H, W) values of ``dtype``."""
    if isinstance(frames, cl.Buffer):
        if shape is None or dtype is None:
            raise ValueError("frames given as a pyopencl Buffer need shape=(K, H, W) and dtype")
        shape, dtype = tuple(int(n) for n in shape), np.dtype(dtype)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"shape must be (K, H, W) of positive sizes, got {shape}")
        if dtype not in (np.uint8, np.uint16, np.float32):
            raise TypeError(f"frames have dtype {dtype}; supported: uint8, uint16, float32")
        if frames.size < int(np.prod(shape)) * dtype.itemsize:
            raise ValueError(f"the frames' buffer holds {frames.size} bytes, fewer than {shape} {dtype} need")
        if frames.context != queue.context:
            raise ValueError("the frames' buffer lives in another OpenCL context than the one chosen for this call")
        return cla.Array(queue, shape, dtype, data=frames)
    frames, _ = check_frames(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (K, H, W), got shape {tuple(frames.shape)}")
    return kernels.to_device(queue, frames)


def launch_gradients(queue, frames: cla.Array, dark=None, gain=None) -> tuple[cla.Array, cla.Array]:
    """Each frame's Sobel magnitude, unscaled, (K, H, W) float32, and each frame's scale (K,) float32 (1 / its mean
    where positive, else 1), as device arrays; ``frames`` a (K, H, W) device array, ``dark`` and ``gain`` NumPy or
    device arrays (validated here)."""
    K, h, w = frames.shape
    dark_dev, per_frame = kernels.pixel_map(queue, dark, "dark", (h, w), K)
    gain_dev = kernels.gain_map(queue, gain, (h, w))
    macros = dict(K=K, IN_T=DTYPE_TO_CTYPE[np.dtype(frames.dtype)],
                  HAS_DARK=0 if dark is None else 2 if per_frame else 1, HAS_GAIN=gain is not None, GROWS=_ROWS)
    columns, strips = -(-w // 16), -(-h // _ROWS)
    group = min(_GROUP, columns)
    padded = -(-columns // group) * group
    out = kernels._empty(queue, K * h * w, np.float32)
    sums = kernels._empty(queue, 2 * K * strips * padded, np.float32)
    scale = kernels._empty(queue, K, np.float32)
    dims = (np.uint32(w), np.uint32(h))
    kernels.launch_range(queue, get_kernel(queue, "gradient.cl", "gradient_sobel", **macros), (padded, strips),
                         (group, 1), frames.data, kernels._data(dark_dev), kernels._data(gain_dev), out.data,
                         sums.data, *dims)
    kernels.launch_range(queue, get_kernel(queue, "gradient.cl", "gradient_scale", **macros), (K,), (1,), sums.data,
                         np.uint32(strips * padded), scale.data, *dims)
    return out.reshape(K, h, w), scale


def apply_scale(queue, images: cla.Array, scale: cla.Array) -> cla.Array:
    """``images`` (K, H, W) multiplied in place by their frame's ``scale``; returns them."""
    K, h, w = images.shape
    n = h * w
    kernel = get_kernel(queue, "gradient.cl", "gradient_apply", GROWS=_ROWS)
    kernels.launch_range(queue, kernel, (-(-n // 8), K), (64, 1), images.data, scale.data, np.uint32(w), np.uint32(h))
    return images


def gradient_images(frames, dark=None, gain=None, *, shape=None, dtype=None, device=None) -> cla.Array:
    """:func:`specgpu.motion.images.gradient_image` of each of K frames, on the device.

    Parameters
    ----------
    frames : array_like (K, H, W), pyopencl.array.Array or pyopencl.Buffer
        Raw frames, uint8, uint16 or float32: a NumPy array (uploaded in one write) or frames already on the device
        (a Buffer with ``shape`` and ``dtype``).
    dark : array_like, (H, W) or (K, H, W), optional
        Dark level subtracted (NumPy or device array; finite).
    gain : array_like, (H, W), optional
        Flat field multiplied after the dark; NaN (a pixel with no response) reads 0, as on the host.
    device : optional
        OpenCL device selector or queue (default: the queue of a device array among the inputs).

    Returns
    -------
    pyopencl.array.Array
        (K, H, W) float32 on the device, each image equal to ``gradient_image(frames[k], dark_k, gain)`` to float32
        rounding; ``.get()`` gives it as NumPy.
    """
    queue = get_queue(device, like=[frames, dark, gain])
    frames_dev = frames_on_device(queue, frames, shape=shape, dtype=dtype)
    images, scale = launch_gradients(queue, frames_dev, dark, gain)
    return apply_scale(queue, images, scale)
