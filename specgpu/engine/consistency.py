"""The consistency check of a motion-compensated sequence on its gradient images: the two maps (texture, worst
correlation) by which pixels whose compensated frames disagree are found.

Each frame's gradient image is sampled where the motion says that frame saw each pixel; their median is the
reference, and per pixel the normalised cross-correlation of each frame with it over a ``window`` x ``window``
box is computed. :func:`consistency_maps` runs this on the device (``kernels/consistency.cl``) for a translation
or an affine map per frame, or a displacement per pixel and frame (a dense flow), on gradient images from the
host or already on the device; :func:`consistency_from_frames` from the raw frames, the gradient images made on
the device too (:mod:`specgpu.engine.gradients`). :func:`consistency_maps_numpy` is the straightforward NumPy /
SciPy computation (``map_coordinates`` and ``uniform_filter``), the tests' reference: on a 640 x 480 sequence of 9
frames it costs about 200 ms.

Two statistics of the whole field enter the maps (the mean variance of the reference, each frame's median
variance), so every pixel's variances are known before any pixel's result. Rather than write 2 K + 1 maps of them
for a second pass, the device brackets each frame's median from a sample of the field first, decides every
(pixel, frame) whose variance is clear of the bracketed threshold in the one pass that makes them, and keeps the
few that are not, with the variances near the median (whose exact median it then selects); the host reads back
only the two maps (see ``kernels/consistency.cl``).
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from scipy import ndimage

from specgpu.engine import kernels
from specgpu.engine.gradients import apply_scale, frames_on_device, launch_gradients
from specgpu.engine.runtime import get_kernel, get_queue, kernel_variant

__all__ = ["consistency_maps", "consistency_from_frames", "consistency_maps_numpy", "exact_median"]

#: Output vectors (8 pixels each) a work-item of the check covers along a row on a CPU device, and the rows of its
#: strip (the first WINDOW - 1 rows of a strip only fill its column sums)
_V = 8
_ROWS = 64
#: The most private memory a work-item's ring of row sums takes on a CPU device (it and the column sums stay in the
#: core's caches; PoCL keeps them on a thread's stack)
_RING_BYTES = 72 * 1024
#: The sample that brackets each frame's median: this many strips of this many rows, spread over the field
_SAMPLE_STRIPS = 8
_SAMPLE_ROWS = 8
#: The bracket: the sample's values this share of its count either side of its middle. Strips are no random sample
#: (a scene's texture varies over the field): on the moving twin's natural scene the median of 8 strips of 8 rows
#: lay up to 1.7 % of the field's count from the field's. A median outside the bracket costs a second pass.
_BRACKET = 0.04


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
                           own: float = 4.0, floor=None) -> tuple[np.ndarray, np.ndarray]:
    """``textured`` (H, W) bool and ``worst`` (H, W) float32 of K gradient images (K, H, W) under ``motion``
    ((K, 2) translations, (K, 2, 3) affine maps or a (K, 2, H, W) flow), on the host; see
    :func:`consistency_maps` (``floor`` too)."""
    g = np.asarray(gradients, np.float32)
    K, h, w = g.shape
    maps = _maps(motion, K, (h, w))
    floors = None if floor is None else _floor_images(floor, (K, h, w))
    flow = maps.ndim == 4
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    aligned = np.empty((K, h, w), np.float32)
    floor_at = None if floors is None else np.empty((K, h, w), np.float32)
    for k in range(K):
        m = maps[k]
        if flow:
            sx, sy = xx + m[0], yy + m[1]
        else:
            sx = m[0, 0] * xx + m[0, 1] * yy + m[0, 2]
            sy = m[1, 0] * xx + m[1, 1] * yy + m[1, 2]
        aligned[k] = ndimage.map_coordinates(g[k], [sy, sx], order=1, mode="nearest")
        if floors is not None:  # the noise floor where frame k saw the pixel, sampled as its gradient image
            floor_at[k] = ndimage.map_coordinates(floors[k], [sy, sx], order=1, mode="nearest")
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
        if floor_at is not None:  # nor where it is no more than its noise there gives (a bright flat area's)
            ncc[va <= floor_at[k]] = 1.0
        np.minimum(worst, ncc, out=worst)
    return textured, worst


def _floor_images(floor, shape: tuple) -> np.ndarray:
    """The noise floors as a (K, H, W) float32 array (read back where they are on the device), refused in one line
    unless of the gradient images' shape."""
    f = np.asarray(floor.get() if isinstance(floor, cla.Array) else floor, np.float32)
    if f.shape != shape:
        raise ValueError(f"floor must be (K, H, W) = {shape} like the gradient images, got {f.shape}")
    return f


def _layout(queue, K: int, window: int) -> tuple[int, int, int]:
    """(vectors per work-item along a row, rows of its strip, work-items per group of the selections) for the
    queue's device: on a CPU device wide, tall strips (a row's samples and medians are made for the work-item's
    columns and HALF more each side, a strip's first WINDOW - 1 rows only fill the column sums), as wide as keeps
    the ring of row sums (WINDOW rows of 3 K + 2 sums of V vectors) within :data:`_RING_BYTES`, and one work-item a
    selection; on a GPU many small strips (work-items to fill it) and a group counting with local atomics."""
    if kernel_variant(queue.device) == "gpu":
        return 1, 16, 64
    return max(1, min(_V, _RING_BYTES // (window * (3 * K + 2) * 32))), _ROWS, 1


def _motion_rows(maps: np.ndarray, translate: bool, width: int) -> np.ndarray:
    """(K, 6) float32 rows of the motion as kernels/consistency.cl reads them: with ``translate`` each frame's
    whole and fractional pixels (ix, iy, fx, fy, 0, 0) (the fraction made in float64, so every lane shares it;
    translations beyond the field held at its size plus one, which samples the same clamped edge), else the 2 x 3
    maps."""
    K = len(maps)
    if not translate:
        return np.ascontiguousarray(maps.reshape(K, 6), np.float32)
    d = maps[:, :, 2]
    whole = np.floor(d)
    part = (d - whole).astype(np.float32)
    carry = part >= np.float32(1.0)  # a fraction just below 1 rounds to 1 in float32: the next whole pixel
    whole[carry] += 1.0
    part[carry] = 0.0
    far = np.abs(whole) > width + 1
    whole = np.clip(whole, -(width + 1), width + 1)
    part[far] = 0.0
    rows = np.zeros((K, 6), np.float32)
    rows[:, 0:2], rows[:, 2:4] = whole, part
    return rows


def _check(queue, grads: cla.Array, maps: np.ndarray, scale, *, window: int, texture: float,
           own: float, floor=None) -> tuple[np.ndarray, np.ndarray]:
    """The check on the device of K gradient images ``grads`` (a (K, H, W) float32 device array; ``scale``: a (K,)
    device array its samples are multiplied by, or None) under finite ``maps`` (``_maps``), odd ``window``;
    ``floor``: (K, H, W) noise floors (:func:`consistency_maps`) or None."""
    K, h, w = grads.shape
    flow = maps.ndim == 4
    V, rows, group = _layout(queue, K, window)
    stride = -(-w // (8 * V)) * 8 * V
    translate = not flow and bool(np.all(maps[:, :, :2] == np.eye(2)))
    macros = dict(K=K, WINDOW=window, V=V, ROWS=rows, STRIDE=stride, TRANSLATE=translate, FLOW=True if flow else None,
                  SCALED=scale is not None, SAMPLE_ROWS=_SAMPLE_ROWS, SELECT_GROUP=group, FLOOR=floor is not None)
    dims = (np.uint32(w), np.uint32(h))
    # a new one every sequence: not cached; a flow is read per pixel, the maps then unused
    motion = _upload(queue, np.zeros(6 * K) if flow else _motion_rows(maps, translate, w))
    flow_dev = _upload(queue, maps) if flow else None
    if isinstance(floor, cla.Array) and floor.context == queue.context:  # made on this device: read there
        if floor.shape != (K, h, w) or floor.dtype != np.float32:
            raise ValueError(f"floor must be (K, H, W) = {(K, h, w)} float32 like the gradient images, got "
                             f"{floor.shape} {floor.dtype}")
        floor_dev = floor
    else:  # from the host, or from another device's context (read back: a buffer serves its own context only)
        floor_dev = None if floor is None else _upload(queue, _floor_images(floor, (K, h, w)))
    columns, strips = stride // (8 * V), -(-h // rows)
    nw = columns * strips
    cap = rows * 8 * V

    def kernel(name):
        return get_kernel(queue, "consistency.cl", name, **macros)

    # the sample: whole strips of SAMPLE_ROWS rows spread over the field (every row of a small one)
    full = h // _SAMPLE_ROWS
    if full <= _SAMPLE_STRIPS:
        step, offset, taken, sample_rows = 1, 0, -(-h // _SAMPLE_ROWS), h
    else:
        step = full // _SAMPLE_STRIPS
        offset, taken = step // 2, _SAMPLE_STRIPS
        sample_rows = taken * _SAMPLE_ROWS
    sample = kernels._empty(queue, K * stride * sample_rows, np.float32)
    kernels.launch_range(queue, kernel("consistency_sample"), (columns, taken), (1, 1), grads.data,
                         kernels._data(scale), motion.data, kernels._data(flow_dev), sample.data, np.uint32(step),
                         np.uint32(offset), np.uint32(sample_rows), *dims)
    count = sample_rows * -(-w // 4)  # the bracket reads every fourth column of the sample
    # the sample's va_k are made in strips of other heights than the field's (their column sums rounded otherwise):
    # a margin of ranks even where the sample is the whole field
    spread = int(np.ceil(_BRACKET * count)) + 8
    bracket = kernels._empty(queue, 4 * K, np.uint32)
    kernels.launch_range(queue, kernel("consistency_bracket"), (K * group,), (group,), sample.data,
                         np.uint32(sample_rows), np.uint32(spread), np.float32(own), bracket.data, np.uint32(w))

    worst = kernels._empty(queue, stride * h, np.float32)
    vr_map = kernels._empty(queue, stride * h, np.float32)
    textured = kernels._empty(queue, stride * h, np.uint8)
    vr_sums = kernels._empty(queue, 8 * nw, np.float32)
    below, kept_count, open_count = (kernels._empty(queue, K * nw, np.uint32) for _ in range(3))
    kept, open_va, open_ncc = (kernels._empty(queue, K * nw * cap, np.float32) for _ in range(3))
    open_at = kernels._empty(queue, K * nw * cap, np.uint32)
    thresholds = kernels._empty(queue, K + 1, np.float32)
    status = kernels._empty(queue, K, np.uint32)

    def settle(bracket_buffer):
        kernels.launch_range(queue, kernel("consistency_strips"), (columns, strips), (1, 1), grads.data,
                             kernels._data(scale), motion.data, kernels._data(flow_dev), kernels._data(floor_dev),
                             bracket_buffer, worst.data,
                             vr_map.data, vr_sums.data, below.data, kept_count.data, kept.data, open_count.data,
                             open_at.data, open_va.data, open_ncc.data, *dims)
        kernels.launch_range(queue, kernel("consistency_median"), ((K + 1) * group,), (group,), below.data,
                             kept_count.data, kept.data, vr_sums.data, np.uint32(nw), np.float32(own),
                             np.float32(texture), thresholds.data, status.data, *dims)
        kernels.launch_range(queue, kernel("consistency_settle"), (nw,), (1,), open_count.data, open_at.data,
                             open_va.data, open_ncc.data, thresholds.data, vr_map.data, worst.data, textured.data,
                             np.uint32(nw), np.uint32(columns), np.uint32(h))
        out_worst, out_textured = np.empty((h, w), np.float32), np.empty((h, w), np.uint8)
        missed = np.empty(K, np.uint32)
        for host, dev, size in ((out_worst, worst, 4), (out_textured, textured, 1)):
            cl.enqueue_copy(queue, host, dev.data, buffer_origin=(0, 0), host_origin=(0, 0), region=(w * size, h),
                            buffer_pitches=(stride * size,), host_pitches=(w * size,), is_blocking=False)
        cl.enqueue_copy(queue, missed, status.data, is_blocking=True)
        return out_textured.view(bool), out_worst, missed

    textured_out, worst_out, missed = settle(bracket.data)
    if missed.any():  # the sample misled: every value kept and every frame undecided, the medians exact again
        everything = np.tile(np.array([0, 0xFFFFFFFF, np.float32(-np.inf).view(np.uint32),
                                       np.float32(np.inf).view(np.uint32)], np.uint32), K)
        textured_out, worst_out, missed = settle(_upload(queue, everything).data)
    return textured_out, worst_out


def _upload(queue, a) -> cla.Array:
    """``a`` (float32, or as it is if uint32) in a new device array, written without waiting (to_device waits for
    the queue, the check's passes before included)."""
    host = np.ascontiguousarray(a, np.uint32 if np.asarray(a).dtype == np.uint32 else np.float32).reshape(-1)
    dev = kernels._empty(queue, host.size, host.dtype)
    cl.enqueue_copy(queue, dev.data, host, is_blocking=False)  # the event holds the host array until it is copied
    return dev


def _gradients_on_device(queue, gradients) -> cla.Array:
    """The gradient images as a (K, H, W) float32 device array: a device array as it is, NumPy uploaded (an array in
    one write from the start, which a simulator such as Oclgrind tracks; a list each image straight into its
    place, no stacked copy on the host)."""
    if isinstance(gradients, cla.Array):
        if gradients.ndim != 3 or gradients.dtype != np.float32 or not gradients.flags.c_contiguous:
            raise ValueError(f"gradients on the device must be a C-contiguous (K, H, W) float32 array, got "
                             f"{gradients.shape} {gradients.dtype}")
        return kernels.to_device(queue, gradients)
    planes = [np.ascontiguousarray(p, np.float32) for p in gradients] if isinstance(gradients, (list, tuple)) \
        else np.ascontiguousarray(gradients, np.float32)
    K, (h, w) = len(planes), np.shape(planes[0])
    grads = kernels._empty(queue, K * h * w, np.float32)
    if isinstance(planes, np.ndarray):
        cl.enqueue_copy(queue, grads.data, planes, is_blocking=False)
    else:
        for k, p in enumerate(planes):
            cl.enqueue_copy(queue, grads.data, p, dst_offset=k * p.nbytes, is_blocking=False)
    return grads.reshape(K, h, w)


def _shape_of(gradients) -> tuple:
    """(K, H, W) of the gradient images, refused in one line unless K images of one 2-D shape."""
    if isinstance(gradients, cla.Array):
        shape = tuple(gradients.shape)
        if len(shape) != 3:
            raise ValueError(f"gradients must be (K, H, W), got shape {shape}")
        return shape
    shapes = {np.shape(p) for p in gradients} if isinstance(gradients, (list, tuple)) else None
    if shapes is not None:
        if len(shapes) != 1 or len(next(iter(shapes))) != 2:
            raise ValueError(f"gradients must be (K, H, W), got images of shapes {sorted(shapes)}")
        return (len(gradients), *next(iter(shapes)))
    shape = np.shape(gradients)
    if len(shape) != 3:
        raise ValueError(f"gradients must be (K, H, W), got shape {shape}")
    return shape


def _window(window) -> int:
    window = int(window)
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    return window


def consistency_maps(gradients, motion, *, window: int = 9, texture: float = 0.5, own: float = 4.0,
                     floor=None, device=None) -> tuple[np.ndarray, np.ndarray]:
    """The consistency check's two maps of K gradient images under each frame's motion.

    Parameters
    ----------
    gradients : array_like, (K, H, W), a sequence of K (H, W) arrays, or a pyopencl.array.Array
        Each frame's gradient image (float32); on the device already (as
        :func:`specgpu.engine.gradients.gradient_images` gives them), they are read there.
    motion : array_like, (K, 2), (K, 2, 3) or (K, 2, H, W)
        Where frame k saw each pixel: x + d_k, M_k (x, y, 1), or x + flow_k(x).
    window : int
        Side of the box (px) the correlations are taken over.
    texture, own : float
        ``textured``: the reference's local variance above ``texture`` times its mean over the field; a frame's
        correlation counts where its local variance is above ``own`` times its median over the field.
    floor : array_like, (K, H, W), optional
        Each frame's noise floor of that local variance, in the frame's own pixels (as its gradient image; sampled
        where the motion says the frame saw each pixel, bilinearly): a frame's correlation counts only where its
        local variance is above it too, so that the noise of a bright flat area (far above the field's median,
        which the dim areas set) is not taken for structure of its own. None: the median's test alone.
    device : optional
        OpenCL device selector or queue (default: the queue of device gradients).

    Returns
    -------
    textured : (H, W) bool
    worst : (H, W) float32
        The lowest correlation of a frame with structure of its own against the reference; 1 where none has.
        On the device with an odd ``window`` and finite motion (kernels/consistency.cl); on the host (the same
        computation in SciPy, :func:`consistency_maps_numpy`) otherwise.
    """
    K, h, w = _shape_of(gradients)
    maps = _maps(motion, K, (h, w))
    window = _window(window)
    if window % 2 == 0 or not np.all(np.isfinite(maps)):
        host = gradients.get() if isinstance(gradients, cla.Array) else gradients
        return consistency_maps_numpy(host, maps, window=window, texture=texture, own=own, floor=floor)
    queue = get_queue(device, like=[gradients])
    return _check(queue, _gradients_on_device(queue, gradients), maps, None, window=window, texture=texture, own=own,
                  floor=floor)


def consistency_from_frames(frames, motion, dark=None, gain=None, *, window: int = 9, texture: float = 0.5,
                            own: float = 4.0, floor=None, return_gradients: bool = False, shape=None, dtype=None,
                            device=None):
    """The consistency check of a sequence from its raw frames, on the device: each frame's gradient image
    (:func:`specgpu.engine.gradients.gradient_images`, never leaving the device) and :func:`consistency_maps`.

    Parameters
    ----------
    frames : array_like (K, H, W), pyopencl.array.Array or pyopencl.Buffer
        Raw frames (uint8, uint16 or float32); a Buffer with ``shape`` and ``dtype``.
    motion : array_like, (K, 2), (K, 2, 3) or (K, 2, H, W)
        As :func:`consistency_maps`; finite.
    dark : array_like, (H, W) or (K, H, W), optional
    gain : array_like, (H, W), optional
        As :func:`specgpu.motion.images.gradient_image` takes them (a NaN gain reads 0).
    window, texture, own, floor
        As :func:`consistency_maps` (an even window is checked on the host, from the images read back).
    return_gradients : bool
        Also return the gradient images, a (K, H, W) float32 device array (``.get()``: NumPy), for the callers that
        read them again (the object layers, the flow).
    device : optional
        OpenCL device selector or queue.

    Returns
    -------
    (textured, worst) or (textured, worst, gradients)
        As :func:`consistency_maps`; the check's samples of each frame are its unscaled gradient magnitude times
        the frame's 1 / mean (one pass fewer), equal to the check of the gradient images to float32 rounding.
    """
    queue = get_queue(device, like=[frames, dark, gain])
    frames_dev = frames_on_device(queue, frames, shape=shape, dtype=dtype)
    K, h, w = frames_dev.shape
    maps = _maps(motion, K, (h, w))
    if not np.all(np.isfinite(maps)):
        raise ValueError("motion must be finite")
    window = _window(window)
    images, scale = launch_gradients(queue, frames_dev, dark, gain)
    if return_gradients or window % 2 == 0:
        images, scale = apply_scale(queue, images, scale), None
    if window % 2 == 0:
        maps_out = consistency_maps_numpy(images.get(), maps, window=window, texture=texture, own=own, floor=floor)
    else:
        maps_out = _check(queue, images, maps, scale, window=window, texture=texture, own=own, floor=floor)
    return (*maps_out, images) if return_gradients else maps_out
