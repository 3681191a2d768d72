"""The variance of the guided filter's output (:mod:`specgpu.engine.guided`) on the device
(:func:`filtered_variance_device`; NumPy in and out: :func:`filtered_variance`).

With its guide g fixed the filter is a linear map, ``q_i = sum_j W_ij p_j`` with

    W_ij = 1/m_i sum_{windows k holding i and j} 1/n_k (1 + alpha_k (g_i - mu_k) (g_j - mu_k)),

``mu_k`` and ``alpha_k = 1 / (var_k g + eps)`` of each (2r + 1)^2 window (clipped to the image: ``n_k`` pixels,
``m_i`` windows holding pixel i). Where the guide is flat W is the mean of box means (a box convolved with a box:
noise about 54 times lower at radius 2); where the guide has an edge or texture W follows it and averages less.
Independent per-pixel noise of variance ``v`` leaves ``sum_j W_ij^2 v_j``.

The guide has noise of its own, and where the output follows the guide (``q_i = abar_i g_i + bbar_i``) that noise
passes: ``abar_i^2 var g_i (1 - 2 b_ii + sum_j b_ij^2)``, abar the filter's mean slope of the output on the guide at
i, b the mean of box means (``bbar`` holds ``-abar`` times the guide's box means: their noise is subtracted). The
guide of ``--denoise`` is the frames' sum, far higher in signal-to-noise ratio than any band, but in a textured
scene its noise, passed by the slope, is most of what the filter leaves. So, per channel c (a variance, or a covariance
entry: the same map applies to every channel),

    out = sum_j W_ij^2 own'_j + sum_t w_t abar_d(t) abar_e(t) gvar_i (1 - 2 b_ii + sum_j b_ij^2)
          + (total_i - own'_i) + offset_c

with ``own`` the pixels' own (independent) part of the variance, ``total`` the whole of it (the light's
fluctuation, common to a frame's pixels, is not averaged and is kept), ``abar_d`` the mean slope of slope image d
(a linear map of the frames whose noise the channel carries: a band, X, Y or Z), the terms ``(d, e, w)`` of each
channel saying which products of slopes it takes (``(b, b, 1)`` for band b's variance, ``(X, Y, 1)`` for
``cov(X, Y)``, the mean over the bands for an RMS), ``gvar`` the variance of the guide's own noise, and
``own' = own`` where own and total are finite and the pixel is not flagged in ``mask``, else 0 (such a pixel adds
nothing to its neighbours and keeps its own total, NaN or not). Two passes: the windows' statistics, then the
weights. With a one-channel guide each weight is a polynomial in ``g_i`` and ``g_j`` whose coefficients are sums,
over the windows holding both pixels (a rectangle of the pixel's windows), of per-window quantities; every such
rectangle is a prefix or a suffix of the pixel's windows along each axis, so all (4r + 1)^2 weights of a pixel come
from its windows' running sums in O(r^2), exactly (the sums taken about ``g_i``, as direct sums would be), eight
pixels of a row at once inside the image. Radius at most :data:`MAX_RADIUS`.
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
from specgpu.engine.runtime import get_allocator, get_kernel, get_queue

__all__ = ["MAX_RADIUS", "box_box_squares", "filtered_variance", "filtered_variance_device", "pass_terms"]

#: The largest radius whose variance is carried (each work-item holds its windows' 3 (2r + 1) (4r + 1) running sums
#: of eight pixels in private memory).
MAX_RADIUS = 4
_GROUP = 64  # work-items per group of the statistics pass; the range is padded to a multiple
_APPLY_GROUP = 16  # of the second pass, whose work-items each hold 3 (2r + 1) (4r + 1) vectors (PoCL: on the stack)
_VX = 8  # pixels of a row per work-item of the second pass (kernels/guided_variance.cl's VX: one float8)
_CACHE_SIZE = 16  # the windows' statistics buffers and the small constant tables kept


def box_box_squares(radius: int) -> np.ndarray:
    """(4 radius + 1,) float64: the squared weights ``t(d)^2`` along one axis of a box mean of radius ``radius``
    convolved with another, ``t(d) = (2r + 1 - |d|) / (2r + 1)^2`` for ``|d| <= 2r``: the filter's weights where its
    guide is flat."""
    r = int(check_number("radius", radius, integer=True, low=1, high=1024))
    d = np.arange(-2 * r, 2 * r + 1)
    return ((2 * r + 1 - np.abs(d)) / (2 * r + 1) ** 2) ** 2


def pass_terms(channels: list) -> tuple[np.ndarray, np.ndarray]:
    """The (T, 3) float32 terms (d, e, w) and the (C + 1,) int32 starts of ``channels``, a list (one entry per
    channel) of lists of (d, e, w): the products of slopes each channel's variance takes from the guide's noise."""
    terms = [t for ch in channels for t in ch]
    starts = np.cumsum([0] + [len(ch) for ch in channels]).astype(np.int32)
    flat = np.asarray(terms, np.float32).reshape(-1, 3) if terms else np.zeros((1, 3), np.float32)
    return flat, starts


class _Stats:
    """The windows' statistics of one (queue, shape, slopes) and the event of the last pass that read them."""

    def __init__(self, queue, size: int):
        self.buffer = cl.Buffer(queue.context, cl.mem_flags.READ_WRITE, max(size, 1) * 4)
        self.last: cl.Event | None = None
        self.lock = threading.Lock()


_stats: OrderedDict[tuple, _Stats] = OrderedDict()
_tables: OrderedDict[tuple, cla.Array] = OrderedDict()
_cache_lock = threading.Lock()


def _kept(cache: OrderedDict, key, make):
    with _cache_lock:
        entry = cache.get(key)
        if entry is not None:
            cache.move_to_end(key)
            return entry
    entry = make()
    with _cache_lock:
        entry = cache.setdefault(key, entry)
        while len(cache) > _CACHE_SIZE:
            cache.popitem(last=False)
    return entry


def _table(queue, values: np.ndarray) -> cla.Array:
    """A small table on the device, uploaded once per (context, content): a constant argument with no transfer
    (and no wait on the queue) per call."""
    values = np.ascontiguousarray(values)
    return _kept(_tables, (queue.context, values.dtype.str, values.tobytes()), lambda: cla.to_device(queue, values))


def _check(a, name: str, shape: tuple, queue, dtype=np.float32) -> None:
    if not isinstance(a, cla.Array):
        raise TypeError(f"{name} must be a pyopencl array, got {type(a).__name__}")
    if tuple(a.shape) != shape or a.dtype != np.dtype(dtype):
        raise ValueError(f"{name} must be {np.dtype(dtype)} of shape {shape}, got {a.dtype} of shape "
                         f"{tuple(a.shape)}")
    if a.context != queue.context:
        raise ValueError(f"{name} lives in another OpenCL context than the queue's")
    if a.offset or not a.flags.c_contiguous:
        raise ValueError(f"{name} must be a whole contiguous buffer (no offset view)")


def filtered_variance_device(queue, own: cla.Array, total: cla.Array, guide: cla.Array, radius: int, eps: float, *,
                             slopes: cla.Array, guide_var: cla.Array, terms: list, offsets: ArrayLike | None = None,
                             sqrt: bool = False, mask: cla.Array | None = None, mask_bits: int = 0,
                             out: cla.Array | None = None) -> cla.Array:
    """The variance (or its square root) of the guided filter's output, of device arrays, enqueued on ``queue``
    and returned without waiting (see the module notes).

    Parameters
    ----------
    queue : pyopencl.CommandQueue
    own, total : pyopencl.array.Array
        (H, W, C) float32: the pixels' own part of each channel's variance (or covariance entry) and the whole.
    guide : pyopencl.array.Array
        (H, W) float32, the filter's guide on the scale ``eps`` is given in.
    radius, eps
        The filter's (1 <= radius <= :data:`MAX_RADIUS`, eps > 0).
    slopes : pyopencl.array.Array
        (H, W, D) float32: the unfiltered images whose slopes on the guide the terms read.
    guide_var : pyopencl.array.Array
        (H, W) float32: the variance of the guide's own noise, in the guide's units squared.
    terms : list
        Per channel, a list of (d, e, w): it takes ``w abar_d abar_e guide_var``.
    offsets : array_like, optional
        (C,) added to every pixel (a constant variance); default 0.
    sqrt : bool
        Write ``sqrt(max(v, 0))`` (a standard deviation; NaN where v is) instead of v.
    mask : pyopencl.array.Array, optional
        (H, W) uint8 flags; a pixel with any of ``mask_bits`` adds nothing to its neighbours.
    out : pyopencl.array.Array, optional
        (H, W, C) float32 to write into; it may be ``total`` or ``own``. Default: from the context's memory pool.

    Returns
    -------
    pyopencl.array.Array
        ``out``, ready once the queue has run the passes; the inputs must stay unchanged until then.
    """
    r = int(check_number("radius", radius, integer=True, low=1, high=MAX_RADIUS))
    e = float(check_number("eps", eps, low=0, low_open=True))
    shape = tuple(own.shape)
    if len(shape) != 3 or 0 in shape:
        raise ValueError(f"own must be (H, W, C) with no empty axis, got shape {shape}")
    H, W, C = shape
    for a, name, s in ((own, "own", shape), (total, "total", shape), (guide, "guide", (H, W)),
                       (guide_var, "guide_var", (H, W))):
        _check(a, name, s, queue)
    if len(slopes.shape) != 3 or tuple(slopes.shape[:2]) != (H, W) or slopes.shape[2] < 1:
        raise ValueError(f"slopes must be ({H}, {W}, D), got shape {tuple(slopes.shape)}")
    _check(slopes, "slopes", tuple(slopes.shape), queue)
    D = int(slopes.shape[2])
    if len(terms) != C or any(not (0 <= int(d) < D and 0 <= int(f) < D) for ch in terms for d, f, _ in ch):
        raise ValueError(f"terms must hold a list of (d, e, w) with d, e below {D} for each of the {C} channels")
    if mask is not None:
        _check(mask, "mask", (H, W), queue, np.uint8)
    off = np.zeros(C) if offsets is None else np.asarray(offsets, np.float64).reshape(-1)
    if off.shape != (C,) or not np.all(np.isfinite(off)):
        raise ValueError(f"offsets must be {C} finite numbers, got shape {np.shape(offsets)}")
    if out is None:
        out = cla.empty(queue, shape, np.float32, allocator=get_allocator(queue))
    else:
        _check(out, "out", shape, queue)
    flat, starts = pass_terms(terms)
    tables = [_table(queue, a) for a in (flat, starts, off.astype(np.float32))]
    stats = _kept(_stats, (queue, H, W, D, C), lambda: _Stats(queue, H * W * (3 + D + C)))
    bits = int(mask_bits) if mask is not None else 0
    macros = {"R": r, "C": C, "D": D, "SQRT": bool(sqrt), "SKIPPED_BITS": bits}
    first, second = (get_kernel(queue, "guided_variance.cl", name, **macros) for name in ("gv_stats", "gv_apply"))
    m = mask.data if mask is not None else own.data  # never read without mask bits
    glob = (-(-H * W // _GROUP) * _GROUP,)
    waits = [ev for a in (own, total, guide, slopes, guide_var, mask, out) if a is not None for ev in a.events]
    with stats.lock, _launch_lock:
        # the previous call's second pass reads the statistics: this first pass may overwrite them only after it
        first.set_args(guide.data, slopes.data, own.data, total.data, m, stats.buffer, np.int32(H), np.int32(W),
                       np.float32(e))
        ev = cl.enqueue_nd_range_kernel(queue, first, glob, (_GROUP,),
                                        wait_for=waits + ([stats.last] if stats.last is not None else []))
        second.set_args(guide.data, stats.buffer, own.data, total.data, m, tables[0].data, tables[1].data,
                        guide_var.data, tables[2].data, out.data, np.int32(H), np.int32(W))
        tiles = H * -(-W // _VX)
        stats.last = cl.enqueue_nd_range_kernel(queue, second, (-(-tiles // _APPLY_GROUP) * _APPLY_GROUP,),
                                                (_APPLY_GROUP,), wait_for=[ev])
        out.add_event(stats.last)
    return out


def filtered_variance(own: ArrayLike, total: ArrayLike, guide: ArrayLike, *, radius: int, eps: float,
                      slopes: ArrayLike, guide_var: ArrayLike, terms: list, offsets: ArrayLike | None = None,
                      sqrt: bool = False, mask: ArrayLike | None = None, mask_bits: int = 0,
                      device=None) -> np.ndarray:
    """:func:`filtered_variance_device` of host arrays (``own``, ``total`` (H, W, C); ``guide``, ``guide_var``
    (H, W); ``slopes`` (H, W, D); ``mask`` (H, W) uint8); returns (H, W, C) float32."""
    own = np.ascontiguousarray(own, np.float32)
    if own.ndim != 3:
        raise ValueError(f"own must be (H, W, C), got shape {own.shape}")
    queue = get_queue(device)

    def dev(a, dtype=np.float32):
        return to_device(queue, np.ascontiguousarray(a, dtype))

    out = filtered_variance_device(queue, dev(own), dev(total), dev(guide), radius, eps, slopes=dev(slopes),
                                   guide_var=dev(guide_var), terms=terms, offsets=offsets, sqrt=sqrt,
                                   mask=None if mask is None else dev(mask, np.uint8), mask_bits=mask_bits)
    return out.get()
