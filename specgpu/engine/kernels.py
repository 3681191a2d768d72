"""Launchers of the two kernel families on device arrays (no validation here: the public API validates).

Each ``launch_*`` function takes a queue and :class:`pyopencl.array.Array` inputs already of the right dtype and
layout, specialises the kernel by -D macros (cached by :mod:`specgpu.engine.runtime`) and returns device arrays;
each ``prepare_*`` function sets such a launch up once for repeated calls (:class:`Prepared`). The NumPy-facing
functions of the same quantities (``apply_linear``, ``XYZ_to_Lab``, ``delta_E``, ``frames_to_delta_E``) are in
:mod:`specgpu.engine.linear_map` and :mod:`specgpu.engine.colorimetry`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from numpy.typing import ArrayLike, DTypeLike

from specgpu.core.validate import check_frames, check_gain_map, check_pixel_map
from specgpu.engine.runtime import DTYPE_TO_CTYPE, VARIANTS, get_allocator, get_kernel, kernel_variant, new_kernel

VW = 8  # pixels per work-item of the "cpu" variant, as kernels/common.h
_GROUP = 64  # work-group size; the global size is padded to a multiple of it
# the "gpu" variant's channels-last tile (GROUP x B float32 in local memory) is used up to this size and the
# device's local memory, else a work-item per output element (kernels/linear.cl, TILE)
_TILE_LOCAL_MAX = 32 * 1024
_launch_lock = threading.Lock()  # a Kernel's arguments are shared state: set and enqueue atomically

DE_CODES = {"CIE 1976": 76, "CIE 1994": 94, "CIE 2000": 2000}


_matrices: dict[tuple, cla.Array] = {}  # decoder matrices already on a device, by (context, shape, bytes)
_matrix_lock = threading.Lock()
_MATRIX_CACHE_SIZE = 64


def matrix_on_device(queue, M: np.ndarray) -> cla.Array:
    """A small float32 matrix on the device, uploaded once per distinct content (a plan's A is reused for every
    sequence of a recording; re-uploading it would be a blocking transfer per call)."""
    M = np.ascontiguousarray(M, dtype=np.float32)
    limit = queue.device.max_constant_buffer_size
    if M.nbytes > limit:
        raise ValueError(f"a {M.shape[0]} x {M.shape[1]} matrix ({M.nbytes} bytes) exceeds the constant memory of "
                         f"{queue.device.name.strip()} ({limit} bytes); use fewer outputs or frames per pass")
    key = (queue.context, M.shape, M.tobytes())
    with _matrix_lock:
        dev = _matrices.get(key)
    if dev is not None:
        return dev
    dev = cla.to_device(queue, M)  # outside the lock: a blocking upload must not stall other launches
    with _matrix_lock:
        if len(_matrices) >= _MATRIX_CACHE_SIZE:
            _matrices.pop(next(iter(_matrices)))
        return _matrices.setdefault(key, dev)


def _c_float(x: float) -> str:
    return repr(float(x)) + "f"


def to_device(queue: cl.CommandQueue, a, dtype: DTypeLike | None = None) -> cla.Array:
    """``a`` as a device array on ``queue``'s context (no copy when it already is one of the right dtype)."""
    if isinstance(a, cla.Array):
        if a.context != queue.context:
            raise ValueError("a device array lives in another OpenCL context than the one chosen for this call")
        if dtype is not None and a.dtype != np.dtype(dtype):
            a = a.astype(dtype)
        if a.offset:  # a view into a larger buffer (a slice): kernels take whole buffers
            a = a.copy()
        return a
    host = np.ascontiguousarray(a if dtype is None else np.asarray(a, dtype=dtype))
    return cla.to_device(queue, host, allocator=get_allocator(queue))


def uploaded(queue, *arrays) -> list:
    """Each of ``arrays`` (small: a launch's frame indices, maps, weights) in a buffer of the queue's memory pool,
    written without waiting (pyopencl's event holds the host array until it is copied); the buffers, in order."""
    alloc, out = get_allocator(queue), []
    for a in arrays:
        host = np.ascontiguousarray(a)
        out.append(alloc(host.nbytes))
        cl.enqueue_copy(queue, out[-1], host, is_blocking=False)
    return out


def frame_planes(queue, frames, spatial: tuple) -> cla.Array:
    """``frames`` ((K, H, W) uint8, uint16 or float32 on the host, float64 converted) as one flat device array of K
    planes of ``spatial`` (H, W); a device array already holding whole planes of those dtypes on ``queue``'s context,
    in a buffer of its own, as it is. Refused in one line otherwise."""
    h, w = spatial
    n = h * w
    if isinstance(frames, cla.Array):
        K = frames.size // n
        if frames.size != K * n or K < 1 or frames.offset or frames.context != queue.context:
            raise ValueError(f"frames must hold whole {h} x {w} frames in a buffer of their own on the "
                             f"prepared device, got {frames.size} samples")
        if frames.dtype not in (np.uint8, np.uint16, np.float32):
            raise ValueError(f"frames must be uint8, uint16 or float32 on the device, got {frames.dtype}")
        return frames
    f, _ = check_frames(frames)
    if f.shape[1:] != (h, w):
        raise ValueError(f"frames must be (K, {h}, {w}), got shape {f.shape}")
    return to_device(queue, f.reshape(-1))


def pixel_map(queue, a, name: str, spatial: tuple, planes: int | None):
    """A validated dark frame / flat field on the device (None stays None); returns (array, per-plane flag)."""
    if a is None:
        return None, False
    a, per_plane = check_pixel_map(a, name, spatial, planes)
    return to_device(queue, a.reshape(-1)), per_plane


def gain_map(queue, gain, spatial: tuple):
    """A validated flat field on the device (None stays None), its NaN marking pixels with no response (their
    outputs NaN: :func:`specgpu.core.numerics.live_gain`)."""
    return None if gain is None else to_device(queue, check_gain_map(gain, spatial).reshape(-1))


def launch_range(queue, kernel, shape: tuple, local: tuple, *args):
    """Enqueue ``kernel`` with ``args`` over the range ``shape`` in work-groups of ``local``, the range padded to a
    multiple of it (the extra work-items return at once); arguments set and enqueued under one lock (a Kernel's
    arguments are shared by every thread)."""
    glob = tuple(-(-int(n) // int(g)) * int(g) for n, g in zip(shape, local))
    with _launch_lock:
        kernel.set_args(*args)
        return cl.enqueue_nd_range_kernel(queue, kernel, glob, tuple(local))


def _launch(queue, kernel, n_pixels: int, *args, pixels_per_item: int = VW):
    items = -(-n_pixels // pixels_per_item)
    # A fixed work-group size on every device: on GPUs for occupancy, on CPU devices because PoCL sizes groups
    # by the launch and keeps a group's private data on a thread stack (large groups overflowed it). The global
    # size is padded; the extra work-items return at once.
    global_size, local_size = (-(-items // _GROUP) * _GROUP,), (_GROUP,)
    with _launch_lock:
        kernel.set_args(*args)
        return cl.enqueue_nd_range_kernel(queue, kernel, global_size, local_size)


def _vw(queue) -> int:
    """Pixels per work-item of the variant chosen for the queue's device (runtime.kernel_variant)."""
    return VARIANTS[kernel_variant(queue.device)]


def _vw_macro(vw: int):
    return None if vw == VW else vw  # the default of kernels/common.h: the same build options as before variants


def _tile_fits(queue, B: int) -> bool:
    return _GROUP * B * 4 <= min(_TILE_LOCAL_MAX, queue.device.local_mem_size)


def _input_macros(frames_dtype, K: int, in_layout: int, dark_mode: int, has_gain: bool, saturation):
    dt = np.dtype(frames_dtype)
    return dict(
        K=K,
        IN_T=DTYPE_TO_CTYPE[dt],
        IN_LAYOUT=in_layout,
        HAS_DARK=dark_mode,
        HAS_GAIN=has_gain,
        IS_FLOAT_IN=dt == np.float32,
        SAT_LEVEL=None if saturation is None else _c_float(saturation),
    )


def _empty(queue, size: int, dtype) -> cla.Array:
    return cla.empty(queue, (size,), dtype, allocator=get_allocator(queue))


def _data(a):
    return None if a is None else a.data


def launch_linear(queue: cl.CommandQueue, frames: cla.Array, A: np.ndarray, *, n: int, in_layout: int = 0,
                  dark: cla.Array | None = None, dark_per_frame: bool = False, gain: cla.Array | None = None,
                  out_dtype: DTypeLike = np.float32, out_layout: int = 0, want_mask: bool = False,
                  saturation: float | None = None):
    """y = A (o - dark) * gain over ``n`` pixels; returns (out (B*n,), mask (n,) or None) as flat device arrays."""
    B = A.shape[0]
    out_dtype = np.dtype(out_dtype)
    name, macros, items, ppi = _linear_kernel(queue, frames.dtype, A, n, in_layout, dark, dark_per_frame, gain,
                                              out_dtype, out_layout, want_mask, saturation)
    kernel = get_kernel(queue, "linear.cl", name, **macros)
    out = _empty(queue, B * n, out_dtype)
    mask = _empty(queue, n, np.uint8) if want_mask else None
    A_dev = matrix_on_device(queue, A)
    if n:
        _launch(queue, kernel, items, frames.data, A_dev.data, _data(dark), _data(gain),
                out.data, _data(mask), np.uint64(n), pixels_per_item=ppi)
    return out, mask


def _linear_kernel(queue, frames_dtype, A, n, in_layout, dark, dark_per_frame, gain, out_dtype, out_layout,
                   want_mask, saturation, out_sqrt=False, square=None):
    """The linear kernel's entry, macros and launch size for the variant of the queue's device."""
    B, K = A.shape
    vw = _vw(queue)
    # "cpu" variant: planar float16 has its own entry with 16 pixels per work-item (one 32-byte store per plane);
    # "gpu" variant, channels last: a local-memory tile (a work-item per pixel) or a work-item per output element
    wide = vw == VW and out_dtype == np.float16 and out_layout == 0 and K <= 128
    gpu_interleaved = vw == 1 and out_layout == 1
    tile = _tile_fits(queue, B) if gpu_interleaved else None
    per_element = gpu_interleaved and not tile
    macros = dict(
        B=B, OUT_HALF=out_dtype == np.float16, OUT_LAYOUT=out_layout, WRITE_MASK=want_mask, VW=_vw_macro(vw),
        GROUP=_GROUP if gpu_interleaved else None, TILE=tile, OUT_SQRT=True if out_sqrt else None,
        SQUARE_GAIN=None if square is None else _c_float(square[0]),
        SQUARE_SHIFT=None if square is None else _c_float(square[1]),
        SQUARE_SKIP=None if square is None or len(square) < 3 else int(square[2]),
        **_input_macros(frames_dtype, K, in_layout, 0 if dark is None else (2 if dark_per_frame else 1),
                        gain is not None, saturation if want_mask else None),
    )
    return "linear_apply_h16" if wide else "linear_apply", macros, n * B if per_element else n, 16 if wide else vw


class Prepared:
    """One launch repeated with new frames and outputs (the stream): a kernel object of its own with every other
    argument set once, so a call sets the few buffers that change and enqueues (no kernel lookup, no option
    strings, no argument conversion). Used from one thread."""

    def __init__(self, queue, kernel, items: int, pixels_per_item: int, args: list, frames_index: int,
                 outputs: dict):
        self.queue, self.kernel = queue, kernel
        work_items = -(-items // pixels_per_item)
        self.global_size, self.local_size = (-(-work_items // _GROUP) * _GROUP,), (_GROUP,)
        self.frames_index = frames_index
        self.outputs = outputs  # name -> (argument index, bytes)
        self.empty = items == 0
        self.alloc = get_allocator(queue)
        kernel.set_args(*args)
        # OpenCL's clSetKernelArg keeps no reference to a buffer, nor does pyopencl: the launch holds every buffer
        # its kernel points at, or one dropped elsewhere (a matrix leaving the upload cache) is released while the
        # kernel still names it, and the next enqueue reads freed memory
        self._held = {i: a for i, a in enumerate(args) if isinstance(a, cl.MemoryObjectHolder)}

    #: Argument index of the matrix (A or M) in both kernel families.
    matrix_index = 1

    def enqueue(self, frames_buffer, matrix=None, inputs=None) -> dict:
        """Enqueue on ``frames_buffer``; returns name -> a fresh pooled device buffer of each output. ``matrix``, a
        device buffer of the same size as the prepared one, replaces the matrix for this launch and the next
        ones (a per-sequence decoder: the stream's white-reference correction). ``inputs``: argument index ->
        buffer, further inputs set for this launch."""
        out = {name: self.alloc(max(nbytes, 1)) for name, (_, nbytes) in self.outputs.items()}
        if self.empty:
            return out
        k = self.kernel
        k.set_arg(self.frames_index, frames_buffer)
        if matrix is not None:
            k.set_arg(self.matrix_index, matrix)
            self._held[self.matrix_index] = matrix  # it stays set for the next launches
        for index, buf in (inputs or {}).items():
            k.set_arg(index, buf)
            self._held[index] = buf
        for name, (index, _) in self.outputs.items():
            k.set_arg(index, out[name])
        cl.enqueue_nd_range_kernel(self.queue, k, self.global_size, self.local_size)
        return out


def prepare_linear(queue: cl.CommandQueue, frames_dtype: DTypeLike, A: np.ndarray, *, n: int,
                   dark: ArrayLike | None = None, dark_per_frame: bool = False, gain: ArrayLike | None = None,
                   out_dtype: DTypeLike = np.float32, out_layout: int = 0, want_mask: bool = False, saturation=None,
                   sqrt_offsets: ArrayLike | None = None, square=None) -> Prepared:
    """:func:`launch_linear` as a :class:`Prepared` launch; outputs ``out`` (B*n) and ``mask`` (n) when asked.

    ``sqrt_offsets`` (B,): write ``sqrt(max(y_b + offset_b, 0))`` (a standard deviation from a variance linear in
    the frames plus a constant; NaN where the variance is NaN, as NumPy's ``maximum`` gives it); the device
    matrix is then A's B x K values followed by the B offsets
    (:func:`linear_matrix`). ``square`` ``(q, c)`` or ``(q, c, k)``: each sample above the dark, ``x``, enters
    the matrix as ``x + q (x - c)^2`` (a frame variance with the light's fluctuation,
    :meth:`specgpu.planning.noise.NoiseModel.light_square`), except frame ``k``'s (an ambient frame's variance
    sample)."""
    B = A.shape[0]
    K = A.shape[1]
    out_dtype = np.dtype(out_dtype)
    if square is not None:
        square = tuple(square)
        if (len(square) not in (2, 3) or not all(np.isfinite(float(v)) for v in square[:2])
                or (len(square) == 3 and not (isinstance(square[2], (int, np.integer)) and 0 <= square[2] < K))):
            raise ValueError(f"square must be two finite numbers (q, c) and optionally a frame index below {K}, "
                             f"got {square!r}")
    name, macros, items, ppi = _linear_kernel(queue, np.dtype(frames_dtype), A, n, 0, dark, dark_per_frame,
                                              gain, out_dtype, out_layout, want_mask, saturation,
                                              out_sqrt=sqrt_offsets is not None, square=square)
    kernel = new_kernel(queue, "linear.cl", name, **macros)
    A_dev = matrix_on_device(queue, linear_matrix(A, sqrt_offsets))
    outputs = {"out": (4, B * n * out_dtype.itemsize)}
    if want_mask:
        outputs["mask"] = (5, n)
    return Prepared(queue, kernel, items, ppi, [None, A_dev.data, _data(dark), _data(gain), None, None,
                                                np.uint64(n)], 0, outputs)


def linear_matrix(A: ArrayLike, sqrt_offsets: ArrayLike | None = None) -> np.ndarray:
    """The float32 values of a linear launch's matrix argument: A (B x K) row-major, then the B offsets of a
    square-root output."""
    A = np.ascontiguousarray(A, np.float32)
    if sqrt_offsets is None:
        return A
    off = np.asarray(sqrt_offsets, np.float32).reshape(-1)
    if off.size != A.shape[0]:
        raise ValueError(f"sqrt_offsets needs {A.shape[0]} values, got {off.size}")
    return np.concatenate([A.reshape(-1), off])


def prepare_frames_to_delta_E(queue: cl.CommandQueue, frames_dtype: DTypeLike, M: np.ndarray, white, reference, *,
                              n: int,
                              method: str = "CIE 2000", reference_single: bool = True, dark: ArrayLike | None = None,
                              dark_per_frame: bool = False, gain: ArrayLike | None = None, write_XYZ: bool = False,
                              write_Lab: bool = False, want_mask: bool = False, saturation=None) -> Prepared:
    """:func:`launch_frames_to_delta_E` as a :class:`Prepared` launch; outputs among XYZ, Lab, delta_E, mask."""
    K = M.shape[1]
    vw = _vw(queue)
    kernel = new_kernel(
        queue, "colorimetry.cl", "frames_to_delta_e",
        DE_METHOD=DE_CODES[method], REF_SINGLE=reference_single, WRITE_XYZ=write_XYZ, WRITE_LAB=write_Lab,
        WRITE_DE=reference is not None, WRITE_MASK=want_mask, VW=_vw_macro(vw),
        **_input_macros(np.dtype(frames_dtype), K, 0, 0 if dark is None else (2 if dark_per_frame else 1),
                        gain is not None, saturation if want_mask else None),
    )
    M_dev = matrix_on_device(queue, M)
    outputs = {}
    if write_XYZ:
        outputs["XYZ"] = (8, 12 * n)
    if write_Lab:
        outputs["Lab"] = (9, 12 * n)
    if reference is not None:
        outputs["delta_E"] = (10, 4 * n)
    if want_mask:
        outputs["mask"] = (11, n)
    Xn, Yn, Zn = (np.float32(v) for v in white)
    return Prepared(queue, kernel, n, vw, [None, M_dev.data, _data(dark), _data(gain), Xn, Yn, Zn,
                                           _data(reference), None, None, None, None, np.uint64(n)], 0, outputs)


def prepare_XYZ_to_delta_E(queue: cl.CommandQueue, white, reference, *, n: int, method: str = "CIE 2000",
                           reference_single: bool = True, write_Lab: bool = False) -> Prepared:
    """CIELAB and the colour difference to ``reference`` of ``n`` XYZ pixels (3n, flat, the launch's "frames") in
    one pass, as a :class:`Prepared` launch: the XYZ read once, outputs ``Lab`` (3n) only with ``write_Lab`` and
    ``delta_E`` (n) only with a ``reference`` (a flat :class:`pyopencl.array.Array`: one colour with
    ``reference_single``, else per pixel), no Lab buffer between the two steps."""
    vw = _vw(queue)
    if reference is None and not write_Lab:
        raise ValueError("the XYZ colour launch needs a reference (delta_E) or write_Lab")
    kernel = new_kernel(queue, "colorimetry.cl", "xyz_to_delta_e", DE_METHOD=DE_CODES[method],
                        REF_SINGLE=reference_single, WRITE_LAB=write_Lab, WRITE_DE=reference is not None,
                        VW=_vw_macro(vw))
    outputs = {}
    if write_Lab:
        outputs["Lab"] = (5, 12 * n)
    if reference is not None:
        outputs["delta_E"] = (6, 4 * n)
    Xn, Yn, Zn = (np.float32(v) for v in white)
    return Prepared(queue, kernel, n, vw, [None, Xn, Yn, Zn, _data(reference), None, None, np.uint64(n)], 0,
                    outputs)


def prepare_delta_E_sigma(queue: cl.CommandQueue, white, constant_cov, *, n: int) -> Prepared:
    """The first-order dE2000 standard deviation of XYZ (3n, the launch's "frames") given the noise part of its
    covariance (6n: XX XY XZ YY YZ ZZ per pixel, input argument 1) and a constant (3, 3) covariance, as a
    :class:`Prepared` launch; output ``dE_sigma`` (n)."""
    vw = _vw(queue)
    kernel = new_kernel(queue, "colorimetry.cl", "delta_e_sigma", VW=_vw_macro(vw))
    C = np.asarray(constant_cov, np.float64).reshape(3, 3)
    c_dev = matrix_on_device(queue, np.array([C[i, j] for i in range(3) for j in range(i, 3)], np.float32))
    Xn, Yn, Zn = (np.float32(v) for v in white)
    return Prepared(queue, kernel, n, vw, [None, None, c_dev.data, Xn, Yn, Zn, None, np.uint64(n)], 0,
                    {"dE_sigma": (6, 4 * n)})


def launch_XYZ_to_Lab(queue: cl.CommandQueue, XYZ: cla.Array, white, *, n: int) -> cla.Array:
    """CIELAB (3n, flat) of ``n`` XYZ pixels (3n, flat) for the ``white`` XYZ, on the device (the launcher of
    :func:`specgpu.engine.colorimetry.XYZ_to_Lab`)."""
    vw = _vw(queue)
    kernel = get_kernel(queue, "colorimetry.cl", "xyz_to_lab", VW=_vw_macro(vw))
    lab = _empty(queue, 3 * n, np.float32)
    if n:
        Xn, Yn, Zn = (np.float32(v) for v in white)
        _launch(queue, kernel, n, XYZ.data, lab.data, Xn, Yn, Zn, np.uint64(n), pixels_per_item=vw)
    return lab


def launch_delta_E(queue: cl.CommandQueue, Lab_1: cla.Array, Lab_2: cla.Array, *, method: str, n: int,
                   single1: bool = False,
                   single2: bool = False) -> cla.Array:
    """Colour differences (n) of two flat CIELAB device arrays by ``method`` (a key of :data:`DE_CODES`); a
    ``single`` flag reads that argument as one colour for every pixel (the launcher of
    :func:`specgpu.engine.colorimetry.delta_E`)."""
    vw = _vw(queue)
    kernel = get_kernel(queue, "colorimetry.cl", "delta_e", DE_METHOD=DE_CODES[method],
                        LAB1_SINGLE=single1, LAB2_SINGLE=single2, VW=_vw_macro(vw))
    de = _empty(queue, n, np.float32)
    if n:
        _launch(queue, kernel, n, Lab_1.data, Lab_2.data, de.data, np.uint64(n), pixels_per_item=vw)
    return de


@dataclass
class FusedOutputs:
    """Device results of the fused pass; fields not asked for are None."""

    delta_E: cla.Array | None
    XYZ: cla.Array | None
    Lab: cla.Array | None
    mask: cla.Array | None


def launch_frames_to_delta_E(queue: cl.CommandQueue, frames: cla.Array, M: np.ndarray, white,
                             reference: cla.Array | None, *,
                             n: int, method: str = "CIE 2000", reference_single: bool = True,
                             dark: cla.Array | None = None, dark_per_frame: bool = False,
                             gain: cla.Array | None = None, write_XYZ: bool = False, write_Lab: bool = False,
                             want_mask: bool = False, saturation: float | None = None) -> FusedOutputs:
    """frames -> XYZ = M (o - dark) * gain -> Lab -> dE(reference, pixel) in one pass (M is 3 x K)."""
    K = M.shape[1]
    write_de = reference is not None
    vw = _vw(queue)
    kernel = get_kernel(
        queue, "colorimetry.cl", "frames_to_delta_e",
        DE_METHOD=DE_CODES[method], REF_SINGLE=reference_single, WRITE_XYZ=write_XYZ, WRITE_LAB=write_Lab,
        WRITE_DE=write_de, WRITE_MASK=want_mask, VW=_vw_macro(vw),
        **_input_macros(frames.dtype, K, 0, 0 if dark is None else (2 if dark_per_frame else 1),
                        gain is not None, saturation if want_mask else None),
    )
    out = FusedOutputs(
        delta_E=_empty(queue, n, np.float32) if write_de else None,
        XYZ=_empty(queue, 3 * n, np.float32) if write_XYZ else None,
        Lab=_empty(queue, 3 * n, np.float32) if write_Lab else None,
        mask=_empty(queue, n, np.uint8) if want_mask else None,
    )
    M_dev = matrix_on_device(queue, M)
    Xn, Yn, Zn = (np.float32(v) for v in white)
    if n:
        _launch(queue, kernel, n, frames.data, M_dev.data, _data(dark), _data(gain), Xn, Yn, Zn,
                _data(reference), _data(out.XYZ), _data(out.Lab), _data(out.delta_E), _data(out.mask),
                np.uint64(n), pixels_per_item=vw)
    return out
