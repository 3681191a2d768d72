"""The consistency check of a motion-compensated sequence on its gradient images: the two maps (texture, worst
correlation) by which pixels whose compensated frames disagree are found.

Each frame's gradient image is sampled where the motion says that frame saw each pixel; their median is the
reference, and per pixel the normalised cross-correlation of each frame with it over a ``window`` x ``window``
box is computed. :func:`consistency_maps` runs this as four device passes (``kernels/consistency.cl``) for a
translation or an affine map per frame, or a displacement per pixel and frame (a dense flow);
:func:`consistency_maps_numpy` is the straightforward NumPy / SciPy computation (``map_coordinates`` and
``uniform_filter``), the tests' reference: on a 640 x 480 sequence of 9 frames it costs about 200 ms. Only two
statistics over the whole field stay on the host (the mean variance of the reference, each frame's median
variance), from maps read back once.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
from scipy import ndimage

from specgpu.engine import kernels
from specgpu.engine.runtime import get_kernel, get_queue

__all__ = ["consistency_maps", "consistency_maps_numpy", "exact_median"]

#: Work-items per group along a row (each 8 pixels); a group is one row's stretch
_GROUP = 16
#: Rows of the strip each work-item of the column sums runs down
_ROWS = 16


def _maps(motion, K: int, spatial: tuple) -> np.ndarray:
    """(K, 2, 3) affine maps of (K, 2) translations or (K, 2, 3) maps; a (K, 2, H, W) flow as it is."""
    maps = np.asarray(motion, np.float64)
    if maps.shape == (K, 2):
        maps = np.concatenate([np.tile(np.eye(2), (K, 1, 1)), maps[:, :, None]], axis=2)
    if maps.shape not in ((K, 2, 3), (K, 2, *spatial)):
        raise ValueError(f"motion must be ({K}, 2), ({K}, 2, 3) or ({K}, 2, {spatial[0]}, {spatial[1]}), "
                         f"got {maps.shape}")
    return maps


def exact_median(values: np.ndarray) -> float:
    """``numpy.median`` of ``values`` (float32, any shape), the same number, in a fraction of its time on a large
    array: a sample's quantiles bracket the median, the values between them are counted and only those
    partitioned (the whole array where the bracket misses, which a sample of 1/16 of a smooth map makes rare)."""
    v = np.asarray(values, np.float32).reshape(-1)
    n = v.size
    if n < 4096:
        return float(np.median(v))
    sample = v[::16]
    spread = int(4 * np.sqrt(sample.size)) + 1  # 8 standard deviations of the sample's rank of the median
    bracket = [max(sample.size // 2 - spread, 0), min(sample.size // 2 + spread, sample.size - 1)]
    lo, hi = np.partition(sample, bracket)[bracket]
    below = int(np.count_nonzero(v < lo))
    inside = v[(v >= lo) & (v <= hi)]
    ranks = [(n - 1) // 2 - below, n // 2 - below]  # the middle one or two of the whole, within the bracket
    if ranks[0] < 0 or ranks[1] >= inside.size:
        return float(np.median(v))
    part = np.partition(inside, ranks)
    return float(np.mean(part[ranks], dtype=np.float32))


def consistency_maps_numpy(gradients, motion, *, window: int = 9, texture: float = 0.5,
                           own: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """``textured`` (H, W) bool and ``worst`` (H, W) float32 of K gradient images (K, H, W) under ``motion``
    ((K, 2) translations, (K, 2, 3) affine maps or a (K, 2, H, W) flow), on the host; see
    :func:`consistency_maps`."""
    g = np.asarray(gradients, np.float32)
    K, h, w = g.shape
    maps = _maps(motion, K, (h, w))
    flow = maps.ndim == 4
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    aligned = np.empty((K, h, w), np.float32)
    for k in range(K):
        m = maps[k]
        if flow:
            sx, sy = xx + m[0], yy + m[1]
        else:
            sx = m[0, 0] * xx + m[0, 1] * yy + m[0, 2]
            sy = m[1, 0] * xx + m[1, 1] * yy + m[1, 2]
        aligned[k] = ndimage.map_coordinates(g[k], [sy, sx], order=1, mode="nearest")
    ref = np.median(aligned, axis=0)

    def box(a):
        return ndimage.uniform_filter(a, window, mode="nearest")

    mr = box(ref)
    vr = np.maximum(box(ref * ref) - mr * mr, 0.0)
    textured = vr > texture * float(np.mean(vr))
    worst = np.ones((h, w), np.float32)
    for k in range(K):
        a = aligned[k]
        ma = box(a)
        va = np.maximum(box(a * a) - ma * ma, 0.0)
        ncc = (box(a * ref) - ma * mr) / np.sqrt(np.maximum(va * vr, 1e-30))
        # only where this frame has structure of its own above its noise (a dim, noisy frame correlates with
        # nothing, and says nothing about the motion)
        ncc[va <= own * float(np.median(va))] = 1.0
        np.minimum(worst, ncc, out=worst)
    return textured, worst


def consistency_maps(gradients, motion, *, window: int = 9, texture: float = 0.5, own: float = 4.0,
                     device=None) -> tuple[np.ndarray, np.ndarray]:
    """The consistency check's two maps of K gradient images under each frame's motion.

    Parameters
    ----------
    gradients : array_like, (K, H, W), or a sequence of K (H, W) arrays
        Each frame's gradient image (float32).
    motion : array_like, (K, 2), (K, 2, 3) or (K, 2, H, W)
        Where frame k saw each pixel: x + d_k, M_k (x, y, 1), or x + flow_k(x).
    window : int
        Side of the box (px) the correlations are taken over.
    texture, own : float
        ``textured``: the reference's local variance above ``texture`` times its mean over the field; a frame's
        correlation counts where its local variance is above ``own`` times its median over the field.
    device : optional
        OpenCL device selector or queue.

    Returns
    -------
    textured : (H, W) bool
    worst : (H, W) float32
        The lowest correlation of a frame with structure of its own against the reference; 1 where none has.
        On the device with an odd ``window``; on the host (the same computation in SciPy) for an even window.
    """
    planes = [np.ascontiguousarray(p, np.float32) for p in gradients] if isinstance(gradients, (list, tuple)) \
        else np.ascontiguousarray(gradients, np.float32)
    shapes = {np.shape(p) for p in planes}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"gradients must be (K, H, W), got shape {np.shape(gradients)}")
    K, (h, w) = len(planes), next(iter(shapes))
    maps = _maps(motion, K, (h, w))
    window = int(window)
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    if window % 2 == 0 or not np.all(np.isfinite(maps)):
        return consistency_maps_numpy(planes, maps, window=window, texture=texture, own=own)
    flow = maps.ndim == 4
    queue = get_queue(device)
    stride = -(-w // 8) * 8
    half = window // 2
    padded = -(-(stride + 2 * half) // 8) * 8  # as kernels/consistency.cl: a whole number of 8-pixel vectors
    translate = not flow and bool(np.all(maps[:, :, :2] == np.eye(2)))
    macros = dict(K=K, WINDOW=window, STRIDE=stride, TRANSLATE=translate, ROWS=_ROWS, FLOW=True if flow else None)
    dims = (np.uint32(w), np.uint32(h))
    plane = stride * h
    grads = kernels._empty(queue, K * h * w, np.float32)
    if isinstance(planes, np.ndarray):  # one write from the start (a simulator such as Oclgrind tracks those)
        cl.enqueue_copy(queue, grads.data, planes, is_blocking=False)
    else:
        for k, p in enumerate(planes):  # each image straight into its place (no stacked copy on the host)
            cl.enqueue_copy(queue, grads.data, p, dst_offset=k * p.nbytes, is_blocking=False)
    # a new one every sequence: not cached; a flow is read per pixel, the maps then unused
    motion_dev = kernels.to_device(queue, np.zeros(6 * K) if flow else maps.reshape(-1), np.float32)
    flow_dev = kernels.to_device(queue, maps.reshape(-1), np.float32) if flow else None
    aligned = kernels._empty(queue, (K + 1) * padded * h, np.float32)
    rows = kernels._empty(queue, (3 * K + 2) * plane, np.float32)
    stats = kernels._empty(queue, (2 * K + 2) * plane, np.float32)

    def launch(name, columns, *args, strips=False):
        kernel = get_kernel(queue, "consistency.cl", name, **macros)
        kernels.launch_range(queue, kernel, (-(-columns // 8), -(-h // _ROWS) if strips else h), (_GROUP, 1), *args,
                             *dims)

    launch("consistency_align", padded, grads.data, motion_dev.data, kernels._data(flow_dev), aligned.data)
    launch("consistency_rows", stride, aligned.data, rows.data)
    launch("consistency_cols", stride, rows.data, stats.data, strips=True)
    va = stats[:K * plane].get().reshape(K, h, stride)[:, :, :w]
    vr = stats[2 * K * plane:(2 * K + 1) * plane].get().reshape(h, stride)[:, :w]
    own_k = np.array([own * exact_median(v) for v in va], np.float32)
    worst = kernels._empty(queue, plane, np.float32)
    textured = kernels._empty(queue, plane, np.uint8)
    launch("consistency_worst", stride, stats.data, kernels.to_device(queue, own_k).data,
           np.float32(texture * float(np.mean(vr))), worst.data, textured.data)
    return (textured.get().reshape(h, stride)[:, :w].astype(bool),
            np.ascontiguousarray(worst.get().reshape(h, stride)[:, :w]))
