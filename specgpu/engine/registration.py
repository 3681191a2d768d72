"""Registration of a sequence's gradient images on the device: each frame's translation, or affine map, relative to a
reference frame, where the gradient images already are (``kernels/register.cl``).

The images are those :func:`specgpu.engine.gradients.gradient_images` makes (the spectrum-independent images the
motion estimate of :mod:`specgpu.motion.global_motion` registers). Coarse to fine:

1. a pyramid of every frame, halved until the short side is under 48 px ([1 3 3 1] / 8 along each axis);
2. on its coarsest level, the correlation coefficient of the reference and each frame at every integer shift within
   reach (``max_speed`` px per frame times the frames between them), the best refined to a fraction of a pixel by a
   parabola through its neighbours;
3. on each level from the coarsest to ``finest``, Gauss-Newton steps on the reference's gradients (the inverse
   compositional form: frame k is sampled at ``M_k x`` and the step is composed on the host), a gain and an offset
   between the two images solved with it, in closed form, from the same sums; the sums of the normal equations are
   reduced on the device by work-groups, and one read-back per step carries all K frames.

A frame is not usable (NaN, ``usable`` False; never a made-up shift) where it, or the reference, has no structure to
register (no variance, or a gradient along one direction only), or where it overlaps the reference too little.
``error`` is ``sqrt(1 - r^2)`` of the correlation coefficient r of the reference and the registered frame, the
counterpart of the phase correlation's normalised error: near 0 where the images match once moved, near 1 where they
share little.

Buffers are kept per (context, kernel variant, K, H, W), so steady-state calls allocate nothing on the device;
programs are built once (:func:`specgpu.engine.runtime.get_kernel`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.engine import kernels
from specgpu.engine.runtime import get_kernel, get_queue, kernel_variant

__all__ = ["DeviceRegistration", "register_gradients", "REGISTRATION_MODELS"]

#: The motion models :func:`register_gradients` fits per frame.
REGISTRATION_MODELS = ("translation", "affine")

#: Work-items per group of the steps (their local sums: NS x GROUP floats) and at most per frame, by kernel variant:
#: on a GPU groups of 64; on PoCL one work-item a group, as kernels/gradient.cl (PoCL runs a group's work-items as a
#: loop, and one work-item that strides over many pixels is what its compiler vectorises best)
_GROUPS = {"gpu": (64, 2048), "cpu": (1, 64)}
#: A level is halved again while its short side is at least this (the coarsest: 30 to 60 px)
_COARSEST_MIN = 48
#: Output rows of a work-item of the pyramid's halving
_HALVE_ROWS = 16
#: Rows of a band the steps at full resolution take whole where they sum a share of the rows (``full_rows``): every
#: n-th band of this many consecutive rows, not every n-th row, which aliases with a scene's structure of a period of
#: n rows (a scene rendered at half the resolution registered px from the truth)
_BAND = 32
#: Pixels per work-item of the steps at least (fewer work-items where a level has fewer pixels)
_PIXELS_PER_ITEM = 1024
#: A step this small (px of the level at the field's edge) is applied and ends the finest level's iterations: the
#: steps shrink about threefold each (on the moving twin at 640 x 480, 0.07 px, then 0.03, 0.014), and what is left
#: then is below the estimate's own bias (0.03 to 0.07 px against the twin's truth), while each step costs a pass
#: over every frame. A coarser level's end at a step of _COARSE_TOLERANCE (the next level corrects what is left).
_STEP_TOLERANCE = 0.05
_COARSE_TOLERANCE = 0.25
#: The smallest share of the reference's pixels a registered frame must overlap
_MIN_OVERLAP = 0.25
#: The normal equations are singular below this ratio of their smallest to largest eigenvalue (an image with a
#: gradient along one direction only)
_MIN_CONDITION = 1e-6


@dataclass(frozen=True)
class DeviceRegistration:
    """Each frame's motion relative to a sequence's reference time, registered on the device.

    Attributes
    ----------
    shifts : numpy.ndarray
        As :class:`specgpu.motion.estimate.MotionEstimate`'s ``shifts``: ``"translation"``, (K, 2) displacement
        (x, y) of each frame from the reference time (frame k sampled at x + shifts[k]); ``"affine"``, (K, 2, 3),
        frame k saw the point at reference-time position x at ``shifts[k] @ (x, y, 1)``. NaN for a frame not
        usable.
    to_reference : numpy.ndarray
        (K, 3, 3): frame k saw the point at position x of the reference frame at ``to_reference[k] @ (x, y, 1)``
        (the identity for the reference frame; NaN for a frame not usable).
    usable : numpy.ndarray
        (K,) bool: the frame was registered.
    error : numpy.ndarray
        (K,) ``sqrt(1 - r^2)`` of the correlation coefficient of the reference and the registered frame (0 for the
        reference frame, NaN where not usable).
    reference_frame : int
        The frame the others were registered to.
    model : str
        ``"translation"`` or ``"affine"``.
    candidates : tuple
        Per frame, the local maxima of its coarse correlation surface within reach, (N, 3) rows of (x, y, r): the
        shift to the reference frame (full-resolution px, refined by a parabola) and the correlation coefficient
        there, highest first; empty for the reference frame and where the coarse search was skipped (``start``).
    rival : numpy.ndarray
        (K,) the second-highest of those maxima over the highest (0 with one maximum; NaN where none was searched):
        near 1 where two displacements compete (a scene that repeats itself, two motions).
    edge : numpy.ndarray
        (K,) bool: the highest candidate lies on the edge of the frame's search (the tail of a peak beyond reach).
    level : numpy.ndarray or None
        (K, h, w) the pyramid level asked for with ``keep_level``, read back.
    """

    shifts: np.ndarray
    to_reference: np.ndarray
    usable: np.ndarray
    error: np.ndarray
    reference_frame: int
    model: str
    candidates: tuple = ()
    rival: np.ndarray | None = None
    edge: np.ndarray | None = None
    level: np.ndarray | None = None


class _Workspace:
    """The device buffers and host arrays of one (context, K, H, W): the pyramid's levels above the input (and a
    level 0 for NumPy input), the maps, the search scores and the step's sums."""

    def __init__(self, queue, K: int, h: int, w: int):
        self.lock = threading.Lock()
        self.sizes = [(h, w)]
        while min(self.sizes[-1]) >= _COARSEST_MIN:
            hh, ww = self.sizes[-1]
            self.sizes.append((-(-hh // 2), -(-ww // 2)))
        self.upload = cla.empty(queue, (K, h, w), np.float32)
        self.levels = [cla.empty(queue, (K, hh, ww), np.float32) for hh, ww in self.sizes[1:]]
        self.group, most = _GROUPS[kernel_variant(queue.device)]
        # work-groups per frame of each level's steps
        self.groups = [max(1, min(most, (hh - 2) * (ww - 2) // _PIXELS_PER_ITEM) // self.group)
                       for hh, ww in self.sizes]
        others = max(K - 1, 1)
        self.maps = cla.empty(queue, (others * 6,), np.float32)
        self.maps_host = np.zeros((others, 6), np.float32)
        self.sums = cla.empty(queue, (others * max(self.groups) * _sum_count(6),), np.float32)
        self.sums_host = np.empty(others * max(self.groups) * _sum_count(6), np.float32)
        self.coarse_host = np.empty(K * self.sizes[-1][0] * self.sizes[-1][1], np.float32)
        self.scores: dict[int, tuple[cla.Array, np.ndarray]] = {}

    def score_buffers(self, queue, others: int, side: int):
        if side not in self.scores:
            self.scores[side] = (cla.empty(queue, (others * side * side,), np.float32),
                                 np.empty(others * side * side, np.float32))
        return self.scores[side]


_WORKSPACES: dict[tuple, _Workspace] = {}
_WORKSPACE_LOCK = threading.Lock()
_MAX_WORKSPACES = 8


def _workspace(queue, K: int, h: int, w: int) -> _Workspace:
    key = (queue.context, kernel_variant(queue.device), K, h, w)
    with _WORKSPACE_LOCK:
        if key not in _WORKSPACES:
            if len(_WORKSPACES) >= _MAX_WORKSPACES:
                _WORKSPACES.pop(next(iter(_WORKSPACES)))
            _WORKSPACES[key] = _Workspace(queue, K, h, w)
        return _WORKSPACES[key]


def _sum_count(params: int) -> int:
    return 3 * params + params * (params + 1) // 2 + 6


def _check_gradients(queue, gradients, reference_frame):
    """The (K, H, W) float32 images on ``queue``'s device and their shape; one-line errors naming the argument."""
    if isinstance(gradients, cla.Array):
        if gradients.ndim != 3 or gradients.dtype != np.float32 or not gradients.flags.c_contiguous:
            raise ValueError(f"gradients must be a C-contiguous (K, H, W) float32 device array, got "
                             f"{gradients.dtype} of shape {tuple(gradients.shape)}")
        if gradients.context != queue.context:
            raise ValueError("gradients live in another OpenCL context than the one chosen for this call")
        stack = None
    else:
        stack = np.asarray(gradients)
        if stack.ndim != 3 or not np.issubdtype(stack.dtype, np.number):
            raise ValueError(f"gradients must be a (K, H, W) array of gradient images, got shape {stack.shape}")
        if not np.isfinite(stack).all():
            raise ValueError("gradients hold NaN or infinite values")
    K, h, w = (int(n) for n in gradients.shape)
    if K < 1 or h < 8 or w < 8:
        raise ValueError(f"gradients must hold at least one image of at least 8 x 8 px, got shape {(K, h, w)}")
    if isinstance(reference_frame, bool) or not isinstance(reference_frame, (int, np.integer)) \
            or not 0 <= int(reference_frame) < K:
        raise ValueError(f"reference_frame must be the index of one of the {K} images, got {reference_frame!r}")
    return stack, (K, h, w)


def register_gradients(gradients, reference_frame: int, *, model: str = "translation",
                       max_speed: float | None = 16.0, finest: int = 0, iterations: int = 10,
                       choose=None, start=None, start_level: int | None = None, keep_level: int | None = None,
                       full_rows: int = 1, full_iterations: int | None = None, device=None) -> DeviceRegistration:
    """Each frame's translation or affine map relative to the reference frame, by registering gradient images on
    the device, coarse to fine (see the module's docstring).

    Parameters
    ----------
    gradients : pyopencl.array.Array or array_like, (K, H, W)
        The frames' gradient images (:func:`specgpu.engine.gradients.gradient_images`): a float32 device array,
        used where it is, or a NumPy array (uploaded into a buffer kept for the shape). Finite.
    reference_frame : int
        The image the others are registered to.
    model : {"translation", "affine"}
        A translation per frame, or an affine map per frame (rotation, zoom, shear; six parameters).
    max_speed : float or None
        The fastest motion looked for, px per frame: frame k's shift is sought within ``max_speed`` times
        ``|k - reference_frame|`` along each axis (and the width of the coarse search's step); None: anywhere a
        quarter of the field still overlaps.
    finest : int
        The finest pyramid level registered on (0: full resolution; 1: half, about four times faster, a little
        less precise).
    iterations : int
        Gauss-Newton steps per level at most (fewer: a step under 0.05 px of the finest level, 0.25 px of a coarser
        one, is the level's last).
    choose : callable, optional
        ``choose(candidates, gaps)`` -> (K - 1, 2): where the refinement of each frame but the reference starts,
        given each one's coarse candidates (as :attr:`DeviceRegistration.candidates`) and its signed distance in
        frames from the reference (``gaps``, (K - 1,)); a NaN row leaves that frame unregistered (not usable).
        Default: each frame's highest candidate.
    start : array_like, (K, 2), optional
        Each frame's translation from the reference frame (frame px = x + start[k], full resolution) the refinement
        starts from: no coarse search (a motion already known to within a few px, e.g. the previous sequence's). A
        NaN row leaves that frame unregistered.
    start_level : int, optional
        With ``start``: the pyramid level the refinement starts on (default: the coarsest); a finer one is cheaper
        and needs ``start`` within about its pixel size of the motion.
    full_rows : int
        The steps at full resolution sum every ``full_rows``-th band of 32 consecutive rows only (1: every row):
        each step a pass over that share of the frames, the rows of a full-resolution image being many and alike
        (bands, not single rows: rows one in n alias with a scene's structure of a period of n rows).
    full_iterations : int, optional
        Gauss-Newton steps at full resolution at most (default ``iterations``).
    keep_level : int, optional
        A pyramid level (1 or coarser) to read back with the result (:attr:`DeviceRegistration.level`): small images
        a check on the host can afford.
    device : optional
        OpenCL device selector or queue (default: the queue of a device array given).

    Returns
    -------
    DeviceRegistration
        Per frame its shift (or map) in :class:`specgpu.motion.estimate.MotionEstimate`'s convention, the map to the
        reference frame, whether it was usable and its registration error.
    """
    if model not in REGISTRATION_MODELS:
        raise ValueError(f"model must be one of {', '.join(REGISTRATION_MODELS)}, got {model!r}")
    if max_speed is not None and not (np.isfinite(max_speed) and max_speed > 0):
        raise ValueError(f"max_speed must be a positive number of px per frame or None, got {max_speed!r}")
    if int(iterations) < 1:
        raise ValueError(f"iterations must be at least 1, got {iterations!r}")
    queue = get_queue(device, like=[gradients])
    stack, (K, h, w) = _check_gradients(queue, gradients, reference_frame)
    ref = int(reference_frame)
    ws = _workspace(queue, K, h, w)
    if not 0 <= int(finest) < len(ws.sizes):
        raise ValueError(f"finest must be a pyramid level in 0..{len(ws.sizes) - 1} for {h} x {w} images, got "
                         f"{finest!r}")
    if start is not None:
        start = np.asarray(start, np.float64)
        if start.shape != (K, 2):
            raise ValueError(f"start must be (K, 2) = {(K, 2)} translations, got shape {start.shape}")
        if start_level is None:
            start_level = len(ws.sizes) - 1
        if not int(finest) <= int(start_level) < len(ws.sizes):
            raise ValueError(f"start_level must be a pyramid level in {int(finest)}..{len(ws.sizes) - 1}, got "
                             f"{start_level!r}")
    if int(full_rows) < 1 or (full_iterations is not None and int(full_iterations) < 1):
        raise ValueError(f"full_rows and full_iterations must be at least 1, got {full_rows!r}, {full_iterations!r}")
    if keep_level is not None and not 1 <= int(keep_level) < len(ws.sizes):
        raise ValueError(f"keep_level must be a pyramid level in 1..{len(ws.sizes) - 1}, got {keep_level!r}")
    with ws.lock:
        reg = _register(queue, ws, stack if stack is not None else gradients, ref, model, max_speed, int(finest),
                        (int(iterations), int(full_rows), None if full_iterations is None else int(full_iterations)),
                        choose, start, None if start is None else int(start_level),
                        None if keep_level is None else int(keep_level))
    return reg


def _read_level(queue, ws: _Workspace, level: int) -> np.ndarray:
    """Pyramid level ``level`` (1 or coarser) of every image, read back: (K, h, w)."""
    K = ws.upload.shape[0]
    out = np.empty((K, *ws.sizes[level]), np.float32)
    cl.enqueue_copy(queue, out, ws.levels[level - 1].data, is_blocking=True)
    return out


def _register(queue, ws: _Workspace, gradients, ref: int, model: str, max_speed, finest: int,
              steps: tuple, choose=None, start=None, start_level=None, keep_level=None) -> DeviceRegistration:
    K, h, w = ws.upload.shape
    if isinstance(gradients, np.ndarray):
        cl.enqueue_copy(queue, ws.upload.data, np.ascontiguousarray(gradients, np.float32), is_blocking=False)
        gradients = ws.upload
    levels = [gradients, *ws.levels]
    halve = _kernel(queue, ws, "register_halve")
    # the levels above the one the refinement starts on (and the one kept) are not needed
    needed = len(ws.sizes) - 1 if start_level is None else max(start_level, keep_level or 0)
    for (hh, ww), src, dst, (h2, w2) in zip(ws.sizes[:needed], levels, levels[1:], ws.sizes[1:]):
        kernels.launch_range(queue, halve, (-(-w2 // 8), -(-h2 // _HALVE_ROWS), K), (1, 1, 1), src.data, dst.data,
                             np.uint32(ww), np.uint32(hh), np.uint32(w2), np.uint32(h2))
    coarsest = len(ws.sizes) - 1 if start_level is None else start_level
    top = levels[coarsest]
    size = K * ws.sizes[coarsest][0] * ws.sizes[coarsest][1]
    if size > ws.coarse_host.size:
        ws.coarse_host = np.empty(size, np.float32)
    cl.enqueue_copy(queue, ws.coarse_host[:size], top.data, is_blocking=True)
    coarse = ws.coarse_host[:size].reshape(K, *ws.sizes[coarsest])
    finite = np.isfinite(coarse).all(axis=(1, 2))
    if not finite.all():  # every input pixel reaches the coarsest level: a NaN there was one in the input
        raise ValueError(f"gradients hold NaN or infinite values (image {int(np.flatnonzero(~finite)[0])})")
    maps = np.tile(np.eye(3), (K, 1, 1))
    usable = np.zeros(K, bool)
    error = np.full(K, np.nan)
    others = [k for k in range(K) if k != ref]
    candidates, rival, edge = [np.zeros((0, 3))] * K, np.full(K, np.nan), np.zeros(K, bool)
    if float(coarse[ref].std()) > 1e-12 * max(float(np.abs(coarse[ref]).mean()), 1e-30):
        usable[ref], error[ref] = True, 0.0
        if others and start is not None:
            maps[others, :2, 2] = start[others]
        elif others:
            gaps = np.array(others) - ref
            found, edge[others] = _coarse_search(queue, ws, top, ref, np.abs(gaps), max_speed)
            for k, c in zip(others, found):
                candidates[k] = c
                rival[k] = c[1, 2] / c[0, 2] if len(c) > 1 and c[0, 2] > 0 else 0.0 if len(c) else np.nan
            if choose is None:
                maps[others, :2, 2] = [c[0, :2] if len(c) else (np.nan, np.nan) for c in found]
            else:
                chosen = np.asarray(choose(found, gaps), np.float64)
                if chosen.shape != (len(others), 2):
                    raise ValueError(f"choose must return ({len(others)}, 2) starts, got shape {chosen.shape}")
                maps[others, :2, 2] = chosen
        if others:
            _refine(queue, ws, levels, ref, others, maps, usable, error, model, coarsest, finest, *steps)
    kept = None if keep_level is None else _read_level(queue, ws, keep_level)
    return replace(_result(maps, usable, error, ref, model, tuple(candidates), rival, edge), level=kept)


def _kernel(queue, ws: _Workspace, name: str, affine: bool = False):
    """A kernel of ``kernels/register.cl``, every entry built with the same macros (one program per variant and
    model)."""
    return get_kernel(queue, "register.cl", name, AFFINE=int(affine), GROUP=ws.group, HROWS=_HALVE_ROWS, BAND=_BAND)


def _rows_summed(h: int, stride: int) -> int:
    """The rows 1 .. h - 2 of an image h rows high that the steps sum taking every ``stride``-th band of
    :data:`_BAND` rows (kernels/register.cl, ROW_OF_BANDS)."""
    rows = np.arange(h - 2)
    return int(np.count_nonzero((rows // _BAND) % stride == 0))


def _level_to_full(level: int) -> np.ndarray:
    """The 3 x 3 map of a level's pixel coordinates to full resolution's (pixel i centred on 2 i + 0.5 below)."""
    s = float(2 ** level)
    return np.array([[s, 0.0, (s - 1.0) / 2.0], [0.0, s, (s - 1.0) / 2.0], [0.0, 0.0, 1.0]])


def _coarse_search(queue, ws: _Workspace, coarse: cla.Array, ref: int, gaps: np.ndarray, max_speed):
    """Each other frame's candidate shifts on the coarsest level: the local maxima of the correlation within reach,
    (N, 3) rows of (x, y) full-resolution px, refined by a parabola through the neighbours along each axis, and
    the correlation there, highest first (a list of K - 1); and whether each frame's highest lies on the edge of
    its search ((K - 1,) bool)."""
    K, hh, ww = coarse.shape
    level = len(ws.sizes) - 1
    scale = 2.0 ** level
    most = min(hh, ww) // 4
    speed = 1e9 if max_speed is None else float(max_speed) / scale  # px of the coarsest level per frame
    reach = np.minimum(np.ceil(speed * gaps + 1.0), most).astype(int)
    R = int(reach.max())
    side = 2 * R + 1
    scores_dev, scores = ws.score_buffers(queue, K - 1, side)
    kernel = _kernel(queue, ws, "register_search")
    kernels.launch_range(queue, kernel, (side * side, K - 1), (min(ws.group, 16), 1), coarse.data, np.uint32(ww),
                         np.uint32(hh), np.uint32(ref), np.int32(R), np.float32(min(speed, 1e9)), scores_dev.data)
    cl.enqueue_copy(queue, scores, scores_dev.data, is_blocking=True)
    surfaces = scores[:(K - 1) * side * side].reshape(K - 1, side, side).astype(np.float64)
    offsets = np.arange(-R, R + 1)
    out, edge = [], np.zeros(K - 1, bool)
    for j, r in enumerate(reach):
        s = np.where((np.abs(offsets)[:, None] <= r) & (np.abs(offsets)[None, :] <= r) & (surfaces[j] > -1.5),
                     surfaces[j], -np.inf)
        padded = np.pad(s, 1, constant_values=-np.inf)
        peak = np.isfinite(s)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:  # at least every neighbour, strictly above those before it (one of a plateau)
                    near = padded[1 + dy:1 + dy + side, 1 + dx:1 + dx + side]
                    peak &= (s > near) if (dy, dx) < (0, 0) else (s >= near)
        ys, xs = np.nonzero(peak)
        order = np.argsort(-s[ys, xs], kind="stable")
        rows = [(offsets[x] + _vertex(s[y, x - 1:x + 2]), offsets[y] + _vertex(s[y - 1:y + 2, x]), s[y, x])
                for y, x in zip(ys[order], xs[order])]
        found = np.array(rows, np.float64).reshape(-1, 3)
        if len(found):
            edge[j] = max(abs(offsets[xs[order[0]]]), abs(offsets[ys[order[0]]])) >= r
        found[:, :2] *= scale
        out.append(found)
    return out, edge


def _vertex(samples: np.ndarray) -> float:
    """Offset in [-0.5, 0.5] of the top of the parabola through three samples (0 at an edge or a flat top)."""
    if len(samples) != 3 or not np.isfinite(samples).all() or (samples < -1.5).any():
        return 0.0
    curvature = samples[0] - 2.0 * samples[1] + samples[2]
    return float(np.clip(0.5 * (samples[0] - samples[2]) / curvature, -0.5, 0.5)) if curvature < 0 else 0.0


def _refine(queue, ws, levels, ref, others, maps, usable, error, model, coarsest, finest, iterations, fine_rows=1,
            fine_iterations=None):
    """Gauss-Newton steps per level, coarsest to ``finest``: ``maps`` (full resolution, frame px = M x) updated in
    place for the frames of ``others``, ``usable`` and ``error`` set from the last step."""
    K, h, w = ws.upload.shape
    affine = model == "affine"
    params = 6 if affine else 2
    ns = _sum_count(params)
    kernel = _kernel(queue, ws, "register_step" if affine else "register_shift", affine)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    norm = max(w, h) / 2.0
    to_centred = np.array([[1.0, 0.0, -centre[0]], [0.0, 1.0, -centre[1]], [0.0, 0.0, 1.0]])
    from_centred = np.linalg.inv(to_centred)
    active = np.ones(len(others), bool)
    others = np.asarray(others)
    for level in range(coarsest, finest - 1, -1):
        hh, ww = ws.sizes[level]
        groups = ws.groups[level]
        S = _level_to_full(level)
        S_inv = np.linalg.inv(S)
        scale = S[0, 0]
        # normalised centred coordinates of this level's pixel x: u = CS x + CU
        cs, cu, cv = scale / norm, (S[0, 2] - centre[0]) / norm, (S[1, 2] - centre[1]) / norm
        pixels = _rows_summed(hh, fine_rows if level == 0 else 1) * (ww - 2)
        for _ in range(iterations if level or fine_iterations is None else min(iterations, fine_iterations)):
            ws.maps_host[:] = (S_inv @ maps[others] @ S)[:, :2].reshape(len(others), 6)
            cl.enqueue_copy(queue, ws.maps.data, ws.maps_host, is_blocking=False)
            shape = np.uint32(ww), np.uint32(hh), np.uint32(ref), ws.maps.data
            coordinates = (np.float32(cs), np.float32(cu), np.float32(cv)) if affine else ()
            stride = np.uint32(fine_rows if level == 0 else 1)
            kernels.launch_range(queue, kernel, (groups * ws.group, len(others)), (ws.group, 1), levels[level].data,
                                 *shape, *coordinates, np.float32(1.0 / scale), stride, ws.sums.data)
            cl.enqueue_copy(queue, ws.sums_host, ws.sums.data, is_blocking=True)
            sums = ws.sums_host[:len(others) * groups * ns].reshape(len(others), groups, ns).sum(axis=1,
                                                                                                 dtype=np.float64)
            step, error[others], active = _solve(sums, params, pixels)
            if affine:
                D = np.tile(np.eye(3), (len(others), 1, 1))
                D[:, :2] += step.reshape(-1, 2, 3) * np.array([1.0 / norm, 1.0 / norm, 1.0])
                maps[others] = maps[others] @ from_centred @ np.linalg.inv(D) @ to_centred
                # the step's largest displacement of a pixel of the field (|u|, |v| <= 1)
                edge = np.abs(step.reshape(-1, 2, 3)).sum(axis=2).max(initial=0.0)
            else:
                maps[others, :2, 2] -= step  # the inverse of a translation
                edge = np.abs(step).max(initial=0.0)
            if edge / scale < (_STEP_TOLERANCE if level == finest else _COARSE_TOLERANCE):  # in px of this level
                break
    usable[others] = active
    lost = np.asarray(others)[~active]
    maps[lost], error[lost] = np.nan, np.nan


def _solve(s: np.ndarray, params: int, pixels: int):
    """From each frame's sums (F, NS): the Gauss-Newton steps (F, params), 0 for a frame not usable; the errors
    ``sqrt(1 - r^2)`` (F,), NaN where not usable; and whether each frame is usable (F,)."""
    F = len(s)
    JI, J1, JT = s[:, :params], s[:, params:2 * params], s[:, 2 * params:3 * params]
    H = np.zeros((F, params, params))
    upper = np.triu_indices(params)
    H[:, upper[0], upper[1]] = H[:, upper[1], upper[0]] = s[:, 3 * params:-6]
    n, si, st, sii, sit, stt = s[:, -6:].T
    with np.errstate(divide="ignore", invalid="ignore"):
        vi, vt, c = sii - si * si / n, stt - st * st / n, sit - si * st / n
        # overlap enough, and structure in both images (an image with none has nothing to register)
        ok = (n >= _MIN_OVERLAP * pixels) & (vi > 1e-12 * np.maximum(sii, 1e-30)) \
            & (vt > 1e-12 * np.maximum(stt, 1e-30))
        H = np.where(ok[:, None, None], H, np.eye(params))
        eig = np.linalg.eigvalsh(H)
        ok &= eig[:, 0] > _MIN_CONDITION * eig[:, -1]  # structure along one direction only: the other is unknown
        alpha = np.where(ok, c / vi, 0.0)  # the reference as gain x frame + offset, least squares
        beta = np.where(ok, (st - alpha * si) / n, 0.0)
        rhs = np.where(ok[:, None], alpha[:, None] * JI + beta[:, None] * J1 - JT, 0.0)
        step = np.linalg.solve(np.where(ok[:, None, None], H, np.eye(params)), rhs[..., None])[..., 0]
        r = c / np.sqrt(vi * vt)
        error = np.where(ok, np.sqrt(np.clip(1.0 - r * r, 0.0, None)), np.nan)
    return step, error, ok


def _at_reference_time(values: np.ndarray) -> np.ndarray:
    """The value at a sequence's reference time of per-frame ``values``: the middle frame's for odd K, the mean of
    the middle two frames' for even K (as :func:`specgpu.motion.estimate.at_reference_time`)."""
    mid = (len(values) - 1) / 2.0
    return 0.5 * (values[int(np.floor(mid))] + values[int(np.ceil(mid))])


def _result(maps: np.ndarray, usable: np.ndarray, error: np.ndarray, ref: int, model: str, candidates: tuple = (),
            rival=None, edge=None) -> DeviceRegistration:
    K = len(maps)
    filled = maps.copy()
    if usable.any() and not usable.all():  # a frame not usable: in time from the others, for the reference time only
        t, good = np.arange(K), np.flatnonzero(usable)
        flat = filled.reshape(K, -1)
        for c in range(flat.shape[1]):
            flat[~usable, c] = np.interp(t[~usable], good, flat[good, c])
    if model == "translation":
        d = maps[:, :2, 2]
        shifts = d - _at_reference_time(filled[:, :2, 2])
    else:
        shifts = (maps @ np.linalg.inv(_at_reference_time(filled)))[:, :2, :] if usable.any() \
            else np.full((K, 2, 3), np.nan)
    shifts[~usable] = np.nan
    maps = maps.copy()
    maps[~usable] = np.nan
    return DeviceRegistration(shifts, maps, usable.copy(), error, ref, model, candidates, rival, edge)
