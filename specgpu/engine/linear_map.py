"""Apply a decoder to frames: y = A (o - dark) * gain for every pixel, on the device.

Every recovery of the paper is this one per-pixel linear map with its own A: narrowband
(A = diag(1/c_i)), biased and symmetric basis (A = Basis . D), tristimulus (A = diag(k)), Wiener and any
future estimator.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from specgpu.core.validate import (
    check_frames,
    check_gain_map,
    check_level,
    check_matrix,
    check_out_dtype,
    check_pixel_map,
    check_result_size,
    is_device_array,
    validate_method,
)
from specgpu.engine import kernels, transfer
from specgpu.engine.runtime import get_queue

__all__ = ["LAYOUTS", "apply_linear", "LinearResult"]

#: Output layouts: channels last (H, W, B) or planes first (B, H, W).
LAYOUTS = {"interleaved": 1, "planar": 0}


class LinearResult(NamedTuple):
    """:func:`apply_linear` outputs with the saturation / non-finite mask."""

    y: object
    mask: object


def apply_linear(frames: ArrayLike, A: ArrayLike, dark: ArrayLike | None = None, gain: ArrayLike | None = None, *,
                 out_dtype: DTypeLike = np.float32, layout: str = "interleaved",
                 saturation: float | None = None, return_mask: bool = False, device=None):
    """y = A (o - dark) * gain for every pixel of a frame stack, on the device.

    Parameters
    ----------
    frames : array_like or pyopencl.array.Array, (K, H, W) or (K, N)
        The K frames of one illumination sequence: uint8, uint16 or float32 (float64 is converted to float32).
    A : array_like, (B, K)
        Decoder matrix (host float64 is rounded to float32 for the device).
    dark : array_like, (H, W) or (K, H, W), optional
        Dark level subtracted from every frame (or one per frame, for frames of different exposure).
    gain : array_like, (H, W), optional
        Per-pixel gain (flat field), applied to the outputs; NaN marks a pixel with no response (a dead pixel,
        :func:`specgpu.core.numerics.live_gain`): its outputs are NaN.
    out_dtype : float32 or float16
        float16 stores round to nearest even; values beyond 65504 become inf.
    layout : {"interleaved", "planar"}
        Output (H, W, B) channels-last, or (B, H, W) planes-first.
    saturation : float, optional
        Sample value at or above which a pixel is flagged saturated (default: the dtype's maximum for integer
        frames, e.g. 65535; pass 1023 for a 10-bit sensor in uint16). Float frames are flagged only when given.
    return_mask : bool
        Also return a uint8 (H, W) mask: 1 = a frame at saturation, 2 = a non-finite sample (OR-ed).
    device : optional
        Explicit device, queue or selector (see :mod:`specgpu.engine.runtime`).

    Returns
    -------
    y : ndarray or pyopencl.array.Array
        (H, W, B) or (B, H, W) of ``out_dtype``; a :class:`LinearResult` (y, mask) when ``return_mask``.
        NaN samples in float frames propagate to the outputs of that pixel only.

    Examples
    --------
    Two frames of 4 x 5 pixels, a dark level of 20 and two outputs (the mean and the difference):

    >>> import numpy as np
    >>> from specgpu.engine import apply_linear
    >>> frames = np.full((2, 4, 5), 100, np.uint16)
    >>> A = np.array([[0.5, 0.5], [1.0, -1.0]])
    >>> y = apply_linear(frames, A, dark=np.full((4, 5), 20.0))
    >>> y.shape, y.dtype
    ((4, 5, 2), dtype('float32'))
    >>> y[0, 0].tolist()
    [80.0, 0.0]
    >>> result = apply_linear(frames, A, layout="planar", return_mask=True)
    >>> result.y.shape, int(result.mask.max())
    ((2, 4, 5), 0)
    """
    frames, K = check_frames(frames)
    A = check_matrix(A, "A", columns=K)
    out_dtype = check_out_dtype(out_dtype)
    out_layout = validate_method(layout, LAYOUTS, "layout")
    spatial = tuple(frames.shape[1:])
    B = A.shape[0]
    queue = get_queue(device, like=(frames, dark, gain))
    saturation = check_level(saturation, "saturation")
    if saturation is None and frames.dtype.kind == "u":
        saturation = float(np.iinfo(frames.dtype).max)
    n = int(np.prod(spatial, dtype=np.int64))
    # the device buffer and, for host frames, the copy it comes back to (on a CPU device both are host memory)
    check_result_size(n * B * out_dtype.itemsize, queue.device,
                      host_copies=0 if is_device_array(frames) else 2, what=f"({n} pixels x {B} outputs) result")
    host_only = not any(is_device_array(a) for a in (frames, dark, gain))
    if host_only and spatial and transfer.transfer_mode(queue.device) == "pinned":
        # a discrete device: pinned staging and row chunks that overlap upload, compute and read-back
        dark_h, dark_per_frame = (None, False) if dark is None else check_pixel_map(dark, "dark", spatial, K)
        gain_h = None if gain is None else check_gain_map(gain, spatial)
        y, mask = transfer.linear_pipelined(
            queue, np.ascontiguousarray(frames), A, dark=dark_h, dark_per_frame=dark_per_frame, gain=gain_h,
            out_dtype=out_dtype, out_layout=out_layout, want_mask=return_mask, saturation=saturation)
        return LinearResult(y, mask) if return_mask else y
    dark_dev, dark_per_frame = kernels.pixel_map(queue, dark, "dark", spatial, K)
    gain_dev = kernels.gain_map(queue, gain, spatial)
    y, mask = kernels.launch_linear(
        queue, kernels.to_device(queue, frames.reshape(-1)), A, n=n, dark=dark_dev, dark_per_frame=dark_per_frame,
        gain=gain_dev, out_dtype=out_dtype, out_layout=out_layout, want_mask=return_mask, saturation=saturation,
    )
    on_device = is_device_array(frames)
    y = y.reshape((*spatial, B) if out_layout else (B, *spatial))
    y = y if on_device else y.get()
    if not return_mask:
        return y
    mask = mask.reshape(spatial)
    return LinearResult(y, mask if on_device else mask.get())

