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

import numpy as np
import pyopencl.array as cla
from numpy.typing import ArrayLike

from specgpu.core.validate import check_number
from specgpu.engine.kernels import _empty, launch_range, to_device
from specgpu.engine.runtime import get_kernel, get_queue

__all__ = ["guided_filter", "box_box_variance", "flat_variance_reduction"]

_GROUP = 128  # work-items per group


def _run(queue, name, shape, *args):
    """Enqueue ``name`` over the range ``shape`` (channels first): work-groups of every channel of up to
    ``_GROUP // channels`` pixels along the second axis (a few hundred thousand groups of one pixel each cost
    more to schedule than their work on PoCL), the range padded to a multiple."""
    kernel = get_kernel(queue, "guided.cl", name)
    c = min(_GROUP, shape[0])
    local = (c, max(1, _GROUP // c)) + (1,) * (len(shape) - 2)
    return launch_range(queue, kernel, shape, local, *args)


def _box(queue, src, H, W, C, r, keep):
    """Box means along x then y; the intermediate image is appended to ``keep`` (see :func:`guided_filter`)."""
    tmp = _empty(queue, H * W * C, np.float32)
    out = _empty(queue, H * W * C, np.float32)
    args = (np.int32(H), np.int32(W), np.int32(C), np.int32(r))
    _run(queue, "box_h", (C, W, H), src.data, tmp.data, *args)
    _run(queue, "box_v", (C, W, H), tmp.data, out.data, *args)
    keep.append(tmp)
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
    n = H * W
    C = 2 * B + 2
    # Every intermediate stays referenced until the last kernel has run: the memory pool is the context's, shared
    # by every queue and thread on it, and a buffer back in it while a queued kernel still uses it could be
    # handed to another queue's work and overwritten.
    keep = [p, g]
    x = _empty(queue, n * C, np.float32)
    _run(queue, "gf_products", (B, n), p.data, g.data, x.data, np.int32(B), np.uint64(n))
    m = _box(queue, x, H, W, C, r, keep)
    ab = _empty(queue, n * 2 * B, np.float32)
    _run(queue, "gf_coeffs", (B, n), m.data, ab.data, np.int32(B), np.float32(e), np.uint64(n))
    mab = _box(queue, ab, H, W, 2 * B, r, keep)
    out = _empty(queue, n * B, np.float32)
    done = _run(queue, "gf_apply", (B, n), mab.data, g.data, out.data, np.int32(B), np.uint64(n))
    keep += [x, m, ab, mab]
    out = out.reshape(H, W, B)
    if not on_device:
        return out.get()
    done.wait()
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
