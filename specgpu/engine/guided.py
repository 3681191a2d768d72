"""The guided filter on the device (:func:`guided_filter`): edge-aware smoothing of a multi-channel image (a
recovery's outputs) by a one-channel guide of higher SNR (the sum of a sequence's frames), and the variance
such smoothing leaves of independent per-pixel noise (:func:`box_box_variance`).

The filter (He, Sun and Tang, "Guided image filtering", ECCV 2010) fits in every (2r + 1)^2 window a linear model
``p = a g + b`` of each channel p on the guide g, ``a = cov(g, p) / (var g + eps)``, and outputs the mean of the
models over the windows covering a pixel, ``q = mean(a) g + mean(b)``. Where the guide is flat within its noise
(``var g << eps``) the output is the window mean of p (noise averaged down); across an edge of the guide
(``var g >> eps``) the output follows the guide, so the edge stays sharp. An edge the guide does not show (two
spectra of equal frame sum) is smoothed like a flat region. Windows are clipped to the image. NaN (a saturated
pixel, or a dead one) spreads to the outputs whose windows hold it: (4 radius + 1)^2 pixels about it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from numpy.typing import ArrayLike

from specgpu.core.validate import check_number
from specgpu.engine.kernels import _launch_lock, to_device
from specgpu.engine.runtime import get_allocator, get_kernel, get_queue, kernel_variant

__all__ = ["guided_filter", "guided_filter_device", "box_box_variance", "flat_variance_reduction"]

_GROUP = 64  # work-items per group along the first axis (columns or rows); the range is padded to a multiple
_MIN_STRIP = 64  # rows (columns) one work-item walks at least: its first window costs 2 radius reads
#: pixels of a row each work-item of the column passes sums, by kernel variant: on a CPU one vector loop over
#: their channels (contiguous), on a GPU one pixel per work-item (neighbours read neighbouring floats)
_BX = {"cpu": 16, "gpu": 1}
#: rows each work-item of the row pass filters at once, one vector lane each (its arithmetic in float4 on a CPU)
_RY = {"cpu": 4, "gpu": 1}
_CACHE_SIZE = 8  # shapes whose intermediates are kept


class _Intermediates:
    """The device buffers of one (queue, shape, channels, radius, strip) and the event of the last pass that used
    them; ``lock`` makes a call's three passes one unit, so two threads on one queue never interleave theirs."""

    def __init__(self, queue, H: int, W: int, C: int, sy: int, sx: int, L: int, ry: int):
        self.sy, self.sx, self.L = sy, sx, L
        self.strips_y, self.strips_x = -(-H // sy), -(-W // sx)
        f = np.dtype(np.float32).itemsize
        mf = cl.mem_flags.READ_WRITE
        self.V = cl.Buffer(queue.context, mf, H * W * (2 * C + 2) * f)
        self.S = cl.Buffer(queue.context, mf, H * W * 2 * C * f)
        self.row_groups = -(-H // ry)
        self.ring = cl.Buffer(queue.context, mf, self.row_groups * ry * self.strips_x * L * 2 * C * f)
        self.last: cl.Event | None = None
        self.lock = threading.Lock()


_cache: OrderedDict[tuple, _Intermediates] = OrderedDict()
_cache_lock = threading.Lock()


def _intermediates(queue, H: int, W: int, C: int, r: int, strip: int | None, ry: int) -> _Intermediates:
    """The intermediates for this call's shape, made once and kept (the least recently used dropped beyond
    :data:`_CACHE_SIZE`; a dropped buffer is freed by OpenCL once the passes queued on it have run)."""
    sy = sx = int(strip) if strip is not None else max(_MIN_STRIP, 4 * r)
    key = (queue, H, W, C, r, sy, ry)
    with _cache_lock:
        entry = _cache.get(key)
        if entry is not None:
            _cache.move_to_end(key)
            return entry
    entry = _Intermediates(queue, H, W, C, min(sy, H), min(sx, W), min(2 * r + 1, W), ry)
    with _cache_lock:
        entry = _cache.setdefault(key, entry)
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return entry


def _enqueue(queue, kernel, shape: tuple, args: tuple, wait_for) -> cl.Event:
    """``kernel`` over ``shape`` (work-groups of :data:`_GROUP` along the first axis, the range padded), after
    ``wait_for``; arguments set and enqueued under the engine's launch lock."""
    glob = (-(-shape[0] // _GROUP) * _GROUP, shape[1])
    with _launch_lock:
        kernel.set_args(*args)
        return cl.enqueue_nd_range_kernel(queue, kernel, glob, (_GROUP, 1), wait_for=wait_for)


def _check_device_array(a, name: str, shape: tuple, queue) -> None:
    if not isinstance(a, cla.Array):
        raise TypeError(f"{name} must be a pyopencl array, got {type(a).__name__}")
    if tuple(a.shape) != shape or a.dtype != np.float32:
        raise ValueError(f"{name} must be float32 of shape {shape}, got {a.dtype} of shape {tuple(a.shape)}")
    if a.context != queue.context:
        raise ValueError(f"{name} lives in another OpenCL context than the queue's")
    if a.offset or not a.flags.c_contiguous:
        raise ValueError(f"{name} must be a whole contiguous buffer (no offset view)")


def guided_filter_device(queue, image: cla.Array, guide: cla.Array, radius: int, eps: float,
                         out: cla.Array | None = None, *, strip: int | None = None) -> cla.Array:
    """The guided filter of device arrays, enqueued on ``queue`` and returned without waiting (no host transfer).

    Three passes of running sums (O(1) per pixel for any radius) over intermediates kept on the device and
    reused by the next call of the same shape; the guide's mean and variance are made once per window and
    shared by every channel. The filter is that of :func:`guided_filter` (see the module notes).

    Parameters
    ----------
    queue : pyopencl.CommandQueue
        Where the passes run; the arrays must live in its context.
    image : pyopencl.array.Array
        (H, W, C) float32, a whole contiguous buffer.
    guide : pyopencl.array.Array
        (H, W) float32, on the scale that ``eps`` is given in.
    radius : int
        Window radius r (windows of (2r + 1)^2 pixels, clipped to the image), >= 1.
    eps : float
        Regularisation in the guide's units squared, > 0.
    out : pyopencl.array.Array, optional
        (H, W, C) float32 to write into; it may be ``image`` itself (read only by the first pass), never the
        guide. Default: a new array from the context's memory pool.
    strip : int, optional
        Rows (columns) each work-item walks; default ``max(64, 4 r)``. Fewer make more work-items for more
        first windows (each 2r reads).

    Returns
    -------
    pyopencl.array.Array
        ``out``: (H, W, C) float32, ready once the queue has run the passes (an in-order queue orders later
        work after them). ``image`` and ``guide`` must stay unchanged until then.
    """
    r = int(check_number("radius", radius, integer=True, low=1, high=1024))
    e = float(check_number("eps", eps, low=0, low_open=True))
    if strip is not None:
        strip = int(check_number("strip", strip, integer=True, low=1))
    shape = tuple(image.shape)
    if len(shape) != 3 or 0 in shape:
        raise ValueError(f"image must be (H, W, C) with no empty axis, got shape {shape}")
    H, W, C = shape
    _check_device_array(image, "image", shape, queue)
    _check_device_array(guide, "guide", (H, W), queue)
    if out is None:
        out = cla.empty(queue, shape, np.float32, allocator=get_allocator(queue))
    else:
        _check_device_array(out, "out", shape, queue)
        if out.base_data == guide.base_data:
            raise ValueError("out must not be the guide (the last pass reads it while writing out)")
    variant = kernel_variant(queue.device)
    bx, ry = _BX[variant], _RY[variant]
    it = _intermediates(queue, H, W, C, r, strip, ry)
    kernels = [get_kernel(queue, "guided.cl", name, C=C, BX=bx, RY=ry) for name in ("gf_columns_in", "gf_rows",
                                                                                   "gf_columns_out")]
    columns = (-(-W // bx), it.strips_y)
    dims = (np.int32(H), np.int32(W), np.int32(r))
    with it.lock:
        # the previous call's last pass reads S: this call's passes may overwrite V and S only after it
        ev = _enqueue(queue, kernels[0], columns, (image.data, guide.data, it.V, *dims, np.int32(it.sy)),
                      [it.last] if it.last is not None else None)
        ev = _enqueue(queue, kernels[1], (it.row_groups, it.strips_x),
                      (it.V, it.ring, it.S, *dims, np.int32(it.sx), np.int32(it.strips_x), np.int32(it.L),
                       np.float32(e)), [ev])
        it.last = _enqueue(queue, kernels[2], columns, (it.S, guide.data, out.data, *dims, np.int32(it.sy)),
                           [ev])
        out.add_event(it.last)
    return out


def guided_filter(image: ArrayLike, guide: ArrayLike, *, radius: int, eps: float, device=None):
    """Edge-aware smoothing of ``image`` (H, W, B) guided by ``guide`` (H, W), on the OpenCL device.

    Parameters
    ----------
    image : array_like or pyopencl.array.Array
        (H, W, B) float32 (a device array is filtered where it lives and a device array returned).
    guide : array_like or pyopencl.array.Array
        (H, W), on the scale that ``eps`` is given in.
    radius : int
        Window radius r (windows of (2r + 1)^2 pixels), >= 1.
    eps : float
        Regularisation, in the guide's units squared (> 0): guide variations within a window well below
        ``sqrt(eps)`` are smoothed over, those well above it kept.
    device : optional
        OpenCL device selector.

    Returns
    -------
    numpy.ndarray or pyopencl.array.Array
        (H, W, B) float32.

    See Also
    --------
    guided_filter_device : the same on device arrays, without waiting.
    """
    r = int(check_number("radius", radius, integer=True, low=1, high=1024))
    e = float(check_number("eps", eps, low=0, low_open=True))
    on_device = isinstance(image, cla.Array)
    shape = tuple(image.shape)
    if len(shape) != 3 or 0 in shape:
        raise ValueError(f"image must be (H, W, B) with no empty axis, got shape {shape}")
    H, W, B = shape
    if tuple(guide.shape) != (H, W):
        raise ValueError(f"guide must be (H, W) = ({H}, {W}), got shape {tuple(guide.shape)}")
    queue = get_queue(device, like=(image, guide))
    p = to_device(queue, image if on_device else np.asarray(image, np.float32), np.float32)
    g = to_device(queue, guide if isinstance(guide, cla.Array) else np.asarray(guide, np.float32), np.float32)
    out = guided_filter_device(queue, p, g, r, e)
    if not on_device:
        return out.get()
    # the inputs converted here go back to the memory pool, shared by every queue on the context, when this
    # returns: they must not be handed to other work while a pass still reads them
    out.finish()
    return out


def _box_box_squares(radius: int) -> np.ndarray:
    """The squared weights ``t(d)^2`` along one axis of a box mean of radius ``radius`` convolved with another,
    ``t(d) = (2r + 1 - |d|) / (2r + 1)^2`` for ``|d| <= 2r``."""
    r = int(check_number("radius", radius, integer=True, low=1, high=1024))
    d = np.arange(-2 * r, 2 * r + 1)
    return ((2 * r + 1 - np.abs(d)) / (2 * r + 1) ** 2) ** 2


def box_box_variance(variance, radius: int) -> np.ndarray:
    """(H, W, B) variance of the mean of box means of radius ``radius`` (the guided filter where its guide is
    flat) of independent per-pixel noise of ``variance`` (H, W, B): the variance convolved with the squared
    weights of a box convolved with a box, ``t(d)^2`` with ``t(d) = (2r + 1 - |d|) / (2r + 1)^2`` along each axis
    (borders: the edge pixels repeated)."""
    from scipy.ndimage import correlate1d  # scipy: heavy, needed only here

    t2 = _box_box_squares(radius)
    v = np.asarray(variance, np.float64)
    v = correlate1d(correlate1d(v, t2, axis=0, mode="nearest"), t2, axis=1, mode="nearest")
    return v.astype(np.float32)


def flat_variance_reduction(radius: int) -> float:
    """How many times the guided filter of radius ``radius`` lowers the variance of independent per-pixel noise
    where its guide is flat (the mean of box means, :func:`box_box_variance` far from a border):
    ``1 / (sum_d t(d)^2)^2``, about 54 at radius 2. At an edge the filter follows the guide and lowers it less."""
    return float(1.0 / _box_box_squares(radius).sum() ** 2)
