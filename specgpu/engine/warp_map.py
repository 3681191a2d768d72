"""Motion-compensated decoding: the linear map with frame k sampled at x + d_k, in the same pass over the frames.

A scene that moves during a sequence lands on different pixels in different frames; decoding each pixel's K
samples as they are mixes the spectra of different surfaces. Given each frame's displacement d_k from the
sequence's reference time (a global translation, a few numbers per frame), the kernel ``kernels/warp.cl`` reads
frame k bilinearly at x + d_k and applies A to those samples, so compensation costs no extra pass. Pixels whose
sample point of some frame falls outside the field are NaN and flagged (``MASK_OUTSIDE``), never a made-up value.
"""

from __future__ import annotations

import numpy as np

from specgpu.core.validate import check_frames, check_level, check_matrix, validate_method
from specgpu.engine import kernels
from specgpu.engine.linear_map import LinearResult
from specgpu.engine.runtime import DTYPE_TO_CTYPE, get_kernel, get_queue

__all__ = ["apply_linear_warped", "MASK_OUTSIDE", "check_shifts"]

#: Mask bit of a pixel whose sample point of some frame lies outside the field.
MASK_OUTSIDE = 4

#: Work-items per group of the translation kernel along a row (each 8 pixels)
_ROW_GROUP = 16
#: Rows each work-item of the translation kernel goes down (kernels/warp.cl's STRIP): a source row read once serves
#: two output rows
_STRIP = 8


def check_shifts(shifts, K: int, name: str = "shifts", spatial: tuple | None = None) -> np.ndarray:
    """Per-frame motion as (K, 6) float32 rows of 2 x 3 affine maps: from a finite (K, 2) array of displacements
    (dx, dy) px, or (K, 2, 3) affine maps (x', y') = M (x, y, 1); or, given the frames' ``spatial`` (H, W), a
    (K, 2, H, W) flow (a displacement per pixel and frame), returned as it is in float32."""
    try:
        d = np.asarray(shifts, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a (K, 2) or (K, 2, 3) array of numbers, got {type(shifts).__name__}") from None
    if d.shape == (K, 2):
        m = np.zeros((K, 2, 3))
        m[:, 0, 0] = m[:, 1, 1] = 1.0
        m[:, :, 2] = d
        d = m
    flow = spatial is not None and d.shape == (K, 2, *spatial)
    if d.shape != (K, 2, 3) and not flow:
        raise ValueError(f"{name} must have shape ({K}, 2) (dx, dy per frame), ({K}, 2, 3) (an affine map per "
                         f"frame)" + (f" or ({K}, 2, {spatial[0]}, {spatial[1]}) (a flow)" if spatial else "")
                         + f", got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name} must be finite")
    return np.ascontiguousarray(d if flow else d.reshape(K, 6), dtype=np.float32)


def apply_linear_warped(frames, A, shifts, dark=None, gain=None, *, saturation: float | None = None,
                        return_mask: bool = False, layout: str = "interleaved", device=None, read=None):
    """y(x) = A s(x), with s_k(x) the corrected frame k, (o_k - dark) * gain, sampled bilinearly at x + d_k.

    Parameters
    ----------
    frames : array_like, (K, H, W)
        uint8, uint16 or float32 frames of one sequence.
    A : array_like, (B, K)
        Decoder.
    shifts : array_like, (K, 2) or (K, 2, 3)
        Displacement (dx, dy) of each frame from the reference time, px: the scene point at pixel x at the
        reference time was seen at x + d_k in frame k. All zero gives :func:`~specgpu.engine.apply_linear`'s
        result. Or an affine map per frame: the point was seen at M_k (x, y, 1) (a rotation, a zoom); or
        (K, 2, H, W), a displacement per pixel and frame (dense motion).
    dark : array_like, (H, W) or (K, H, W), optional
        Dark level of the sensor pixels.
    gain : array_like, (H, W), optional
        Flat field of the sensor pixels (applied to each sample before interpolation); NaN marks a pixel with no
        response: an output that samples it is NaN.
    saturation : float, optional
        Level at or above which a used sample flags the pixel saturated (default: the integer dtype's maximum).
    return_mask : bool
        Also return the uint8 (H, W) mask: 1 saturated, 2 non-finite input, 4 outside the field (OR-ed).
    layout : {"interleaved", "planar"}
        Output (H, W, B) or (B, H, W).
    read : sequence of int, optional
        Only these frames are read (and A's columns, the shifts and a per-frame dark with them): a frame no output
        reads, such as a broadband reference frame, flags no pixel wherever it saw it.

    Returns
    -------
    ndarray (H, W, B) float32, NaN where a sample point is outside the field; a :class:`LinearResult` with
    ``return_mask``.

    Examples
    --------
    >>> import numpy as np
    >>> frames = np.stack([np.tile(np.arange(6.0, dtype=np.float32), (4, 1))] * 2)
    >>> y = apply_linear_warped(frames, [[1.0, 0.0], [0.0, 1.0]], [[0.0, 0.0], [1.5, 0.0]])
    >>> y[1, 2].tolist(), bool(np.isnan(y[1, 5]).all())
    ([2.0, 3.5], True)
    """
    if read is not None:
        read = [int(k) for k in read]
        frames, A, shifts = np.asarray(frames)[read], np.asarray(A)[:, read], np.asarray(shifts)[read]
        dark = dark if dark is None or np.ndim(dark) < 3 else np.asarray(dark)[read]
    frames, K = check_frames(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (K, H, W) to be warped, got shape {tuple(frames.shape)}")
    A = check_matrix(A, "A", columns=K)
    d = check_shifts(shifts, K, spatial=tuple(frames.shape[1:]))
    flow = d.ndim == 4
    planar = validate_method(layout, {"interleaved": 0, "planar": 1}, "layout")
    spatial = tuple(frames.shape[1:])
    h, w = spatial
    B = A.shape[0]
    saturation = check_level(saturation, "saturation")
    if saturation is None and frames.dtype.kind == "u":
        saturation = float(np.iinfo(frames.dtype).max)
    queue = get_queue(device, like=(frames, dark, gain))
    dark_dev, dark_per_frame = kernels.pixel_map(queue, dark, "dark", spatial, K)
    gain_dev = kernels.gain_map(queue, gain, spatial)
    n = h * w
    macros = dict(K=K, B=B, IN_T=DTYPE_TO_CTYPE[frames.dtype],
                  HAS_DARK=0 if dark is None else (2 if dark_per_frame else 1), HAS_GAIN=gain is not None,
                  IS_FLOAT_IN=frames.dtype == np.float32, FLOW=True if flow else None,
                  SAT_LEVEL=None if saturation is None else repr(float(saturation)) + "f")
    translate = n and not flow and K <= 128 and bool(np.all(d[:, [0, 1, 3, 4]] == np.array([1, 0, 0, 1], np.float32)))
    interleaved = bool(translate and not planar)  # the row kernel writes (H, W, B) itself
    macros["OUT_INTERLEAVED"] = interleaved
    kernel = get_kernel(queue, "warp.cl", "linear_warp", **macros)
    f_dev = kernels.to_device(queue, frames.reshape(-1))
    out = kernels._empty(queue, max(n * B, 1), np.float32)
    mask = kernels._empty(queue, max(n, 1), np.uint8)
    A_dev = kernels.matrix_on_device(queue, A)
    d_dev = kernels.matrix_on_device(queue, np.zeros((K, 6), np.float32) if flow else d)
    flow_dev = kernels.to_device(queue, d.reshape(-1)) if flow else None
    args = (f_dev.data, A_dev.data, d_dev.data, kernels._data(flow_dev), kernels._data(dark_dev),
            kernels._data(gain_dev), out.data, mask.data, np.uint32(w), np.uint32(h))
    if translate:
        # translations: 8 pixels of a row per work-item, down a strip of rows, the frames read as vectors
        translate = get_kernel(queue, "warp.cl", "linear_warp_translate", STRIP=_STRIP, **macros)
        kernels.launch_range(queue, translate, (-(-w // 8), -(-h // _STRIP)), (_ROW_GROUP, 1), *args)
    elif n:
        kernels._launch(queue, kernel, n, *args, pixels_per_item=1)
    if interleaved:
        y = out.get()[:n * B].reshape(h, w, B)
    else:
        y = out.get()[:n * B].reshape(B, h, w)  # the kernel writes planes (coalesced stores)
        if not planar:
            y = np.ascontiguousarray(np.moveaxis(y, 0, -1))
    if not return_mask:
        return y
    return LinearResult(y, mask.get()[:n].reshape(h, w))
