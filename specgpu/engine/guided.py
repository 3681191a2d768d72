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

_GROUP = 64  # work-items per group of the three passes along the first axis (columns or rows); the range is padded
_MIN_STRIP = 64  # rows (columns) one work-item of the passes walks at least: its first window costs 2 radius reads
#: the one-launch form: rows a strip has at least (its first windows cost 4 radius rows more), and strips per
#: compute unit wanted (a few, so that a core slowed by other work does not hold up the launch)
_MIN_STRIP_ROWS, _STRIPS_PER_UNIT = 16, 4
_CACHE_SIZE = 8  # shapes whose intermediates are kept


class _Intermediates:
    """The device buffers of one (queue, shape, channels, radius, strip, form) and the event of the last pass that
    used them; ``lock`` makes a call's passes one unit, so two threads on one queue never interleave theirs.

    The "cpu" form (one launch of ``gf_strips``) has a scratch buffer of each strip's column sums and its last
    ``L = min(2r + 1, H)`` rows of models; the "gpu" form (three passes) has the full-size V and S and the row
    pass's rings."""

    def __init__(self, queue, H: int, W: int, C: int, r: int, sy: int, sx: int, strips: bool):
        self.sy, self.sx = sy, sx
        self.strips_y, self.strips_x = -(-H // sy), -(-W // sx)
        f = np.dtype(np.float32).itemsize
        mf = cl.mem_flags.READ_WRITE
        if strips:
            self.L = min(2 * r + 1, H)
            self.scratch = cl.Buffer(queue.context, mf, self.strips_y * W * (2 * C + 2 + 2 * C * (1 + self.L)) * f)
        else:
            self.L = min(2 * r + 1, W)
            self.V = cl.Buffer(queue.context, mf, H * W * (2 * C + 2) * f)
            self.S = cl.Buffer(queue.context, mf, H * W * 2 * C * f)
            self.ring = cl.Buffer(queue.context, mf, H * self.strips_x * self.L * 2 * C * f)
        self.source: cl.Buffer | None = None
        self.last: cl.Event | None = None
        self.lock = threading.Lock()

    def copy_of(self, queue, image: cla.Array) -> cl.Buffer:
        """The buffer an image filtered in place is copied to (made on first use)."""
        if self.source is None:
            self.source = cl.Buffer(queue.context, cl.mem_flags.READ_WRITE, image.nbytes)
        return self.source


_cache: OrderedDict[tuple, _Intermediates] = OrderedDict()
_cache_lock = threading.Lock()


def _intermediates(queue, H: int, W: int, C: int, r: int, strip: int | None, strips: bool) -> _Intermediates:
    """The intermediates for this call's shape, made once and kept (the least recently used dropped beyond
    :data:`_CACHE_SIZE`; a dropped buffer is freed by OpenCL once the passes queued on it have run)."""
    if strip is not None:
        sy = sx = int(strip)
    elif strips:  # every compute unit busy: about _STRIPS_PER_UNIT strips each
        units = max(1, int(queue.device.max_compute_units))
        sy = sx = max(_MIN_STRIP_ROWS, 4 * r, -(-H // (_STRIPS_PER_UNIT * units)))
    else:
        sy = sx = max(_MIN_STRIP, 4 * r)
    key = (queue, H, W, C, r, sy, strips)
    with _cache_lock:
        entry = _cache.get(key)
        if entry is not None:
            _cache.move_to_end(key)
            return entry
    entry = _Intermediates(queue, H, W, C, r, min(sy, H), min(sx, W), strips)
    with _cache_lock:
        entry = _cache.setdefault(key, entry)
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return entry


def _enqueue(queue, kernel, shape: tuple, local: tuple, args: tuple, wait_for) -> cl.Event:
    """``kernel`` over ``shape`` in groups of ``local`` (the range padded to a multiple), after ``wait_for``;
    arguments set and enqueued under the engine's launch lock."""
    glob = tuple(-(-int(n) // int(g)) * int(g) for n, g in zip(shape, local))
    with _launch_lock:
        kernel.set_args(*args)
        return cl.enqueue_nd_range_kernel(queue, kernel, glob, local, wait_for=wait_for)


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

    Running sums (O(1) per pixel for any radius) over intermediates kept on the device and reused by the next
    call of the same shape; the guide's mean and variance are made once per window and shared by every channel.
    The filter is that of :func:`guided_filter` (see the module notes). Its form follows the kernel variant of
    the queue's device (:func:`specgpu.engine.runtime.kernel_variant`): on a CPU ("cpu") one launch in which each
    work-item walks a strip of rows across the image, its column sums and last rows of models in a small scratch
    buffer (read and written once, the image and the output; no full-size intermediate); on a GPU ("gpu") three
    passes over full-size intermediates with a pixel or a row per work-item, so that neighbouring work-items
    read neighbouring floats.

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
        (H, W, C) float32 to write into; it may be ``image`` itself (on a CPU the image is then copied first,
        on the device), never the guide. Default: a new array from the context's memory pool.
    strip : int, optional
        Rows (columns) each work-item walks. Default: on a CPU, about four strips per compute unit of at least
        ``max(16, 4 r)`` rows; on a GPU ``max(64, 4 r)``. Fewer make more work-items for more first windows
        (each costs 2r to 4r rows more).

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
    strips = kernel_variant(queue.device) == "cpu"
    it = _intermediates(queue, H, W, C, r, strip, strips)
    dims = (np.int32(H), np.int32(W), np.int32(r))
    with it.lock:
        # the previous call's passes read the intermediates: this call's may overwrite them only after them
        wait = [it.last] if it.last is not None else None
        if strips:
            source = image.data
            if out.base_data == image.base_data:
                # a strip reads the image's rows until its last output row is written, and its neighbours read
                # its first and last rows: filtered in place, the image is read from a copy
                source = it.copy_of(queue, image)
                wait = [cl.enqueue_copy(queue, source, image.data, byte_count=image.nbytes, wait_for=wait)]
            kernel = get_kernel(queue, "guided.cl", "gf_strips", C=C, STRIPS=1)
            it.last = _enqueue(queue, kernel, (it.strips_y,), (1,), (source, guide.data, out.data, it.scratch, *dims,
                                                                      np.int32(it.sy), np.int32(it.L), np.float32(e)),
                               wait)
        else:
            kernels = [get_kernel(queue, "guided.cl", name, C=C, STRIPS=0)
                       for name in ("gf_columns_in", "gf_rows", "gf_columns_out")]
            columns, local = (W, it.strips_y), (_GROUP, 1)
            ev = _enqueue(queue, kernels[0], columns, local, (image.data, guide.data, it.V, *dims, np.int32(it.sy)),
                          wait)
            ev = _enqueue(queue, kernels[1], (H, it.strips_x), local,
                          (it.V, it.ring, it.S, *dims, np.int32(it.sx), np.int32(it.strips_x), np.int32(it.L),
                           np.float32(e)), [ev])
            it.last = _enqueue(queue, kernels[2], columns, local,
                               (it.S, guide.data, out.data, *dims, np.int32(it.sy)), [ev])
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
