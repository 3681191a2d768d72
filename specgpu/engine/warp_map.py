"""Motion-compensated decoding: the linear map with frame k sampled at x + d_k.

A scene that moves during a sequence lands on different pixels in different frames; decoding each pixel's K
samples as they are mixes the spectra of different surfaces. Given each frame's displacement d_k from the
sequence's reference time (a global translation, a few numbers per frame), the kernels of ``kernels/warp.cl`` read
frame k bilinearly at x + d_k and apply A to those samples. Pixels whose sample point of some frame falls outside
the field are NaN and flagged (:attr:`specgpu.core.mask.Mask.OUTSIDE`), never a made-up value.

Translations run through :class:`PreparedWarp` (``linear_warp_translate``): every pixel of a frame has the same
bilinear weights, so 8 output pixels of a row take their samples from 9 consecutive source pixels of two rows,
read as vectors and corrected as they are read, each source row once for the two output rows it serves; about
what the static decoder costs (``tools/benchmarks/warp_cost.py``). Where a later step reads the corrected frames
too, they are written first (``warp_correct``) and the warp samples them, with the same result. Affine maps and
flows run a
work-item per pixel (``linear_warp``).
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from numpy.typing import ArrayLike

from specgpu.core.validate import check_frames, check_level, check_matrix, validate_method
from specgpu.engine import kernels
from specgpu.engine.linear_map import LinearResult
from specgpu.engine.runtime import DTYPE_TO_CTYPE, get_allocator, get_kernel, get_queue, kernel_variant, new_kernel

__all__ = ["apply_linear_warped", "check_shifts", "PreparedWarp", "prepare_linear_warped"]

#: Frames the translation path holds (kernels/warp.cl keeps each frame's samples in named registers, up to 128)
MAX_TRANSLATE_FRAMES = 128
#: Output groups one translation pass writes at most (kernels/warp.cl, GROUPS)
MAX_GROUPS = 4
_LAYOUTS = {"interleaved": 1, "planar": 0}
#: The work shape of the translation kernel (kernels/warp.cl, linear_warp_translate) by kernel variant
#: (specgpu.engine.runtime.kernel_variant): each work-item takes STRIP rows (a source row read once serves the output
#: rows on either side of it) of XSTEPS steps of 8 pixels, in work-groups of (x, y) work-items. "cpu": a work-item
#: goes 128 pixels along 4 rows, each load of its unrolled rows a stream of its own 32 bytes a step (measured on PoCL:
#: a work-item per 8 pixels going down 8 rows took about twice as long; 256 or 640 pixels about as long, 2 or 8 rows
#: longer); "gpu": a work-item per 8 pixels of 2 rows, neighbours along x in a group, for coalesced loads and as
#: many work-items as the image gives.
_SHAPES = {"cpu": dict(STRIP=4, XSTEPS=16, group=(1, 8)), "gpu": dict(STRIP=2, XSTEPS=1, group=(16, 4))}


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


def apply_linear_warped(frames: ArrayLike, A: ArrayLike, shifts: ArrayLike, dark: ArrayLike | None = None,
                        gain: ArrayLike | None = None, *, saturation: float | None = None,
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
    n = h * w
    translate = (n and not flow and K <= MAX_TRANSLATE_FRAMES
                 and bool(np.all(d[:, [0, 1, 3, 4]] == np.array([1, 0, 0, 1], np.float32))))
    if translate:
        # translations: one pass of PreparedWarp, the raw frames corrected as they are read
        launch = PreparedWarp(queue, frames.dtype, A, (h, w), dark, gain, saturation=saturation,
                              outputs=[("y", B, "planar" if planar else "interleaved")])
        out = launch.enqueue(kernels.to_device(queue, frames.reshape(-1)), d[:, [2, 5]])
        y = np.empty((B, h, w) if planar else (h, w, B), np.float32)
        cl.enqueue_copy(queue, y, out["y"])
        if not return_mask:
            return y
        mask = np.empty((h, w), np.uint8)
        cl.enqueue_copy(queue, mask, out["mask"])
        return LinearResult(y, mask)
    dark_dev, dark_per_frame = kernels.pixel_map(queue, dark, "dark", spatial, K)
    gain_dev = kernels.gain_map(queue, gain, spatial)
    macros = dict(K=K, B=B, IN_T=DTYPE_TO_CTYPE[frames.dtype],
                  HAS_DARK=0 if dark is None else (2 if dark_per_frame else 1), HAS_GAIN=gain is not None,
                  IS_FLOAT_IN=frames.dtype == np.float32, FLOW=True if flow else None,
                  SAT_LEVEL=None if saturation is None else repr(float(saturation)) + "f", OUT_INTERLEAVED=False)
    kernel = get_kernel(queue, "warp.cl", "linear_warp", **macros)
    f_dev = kernels.to_device(queue, frames.reshape(-1))
    out = kernels._empty(queue, max(n * B, 1), np.float32)
    mask = kernels._empty(queue, max(n, 1), np.uint8)
    A_dev = kernels.matrix_on_device(queue, A)
    d_dev = kernels.matrix_on_device(queue, np.zeros((K, 6), np.float32) if flow else d)
    flow_dev = kernels.to_device(queue, d.reshape(-1)) if flow else None
    args = (f_dev.data, A_dev.data, d_dev.data, kernels._data(flow_dev), kernels._data(dark_dev),
            kernels._data(gain_dev), out.data, mask.data, np.uint32(w), np.uint32(h))
    if n:
        kernels._launch(queue, kernel, n, *args, pixels_per_item=1)
    y = out.get()[:n * B].reshape(B, h, w)  # the kernel writes planes (coalesced stores)
    if not planar:
        y = np.ascontiguousarray(np.moveaxis(y, 0, -1))
    if not return_mask:
        return y
    return LinearResult(y, mask.get()[:n].reshape(h, w))


class PreparedWarp:
    """The decoding of a sequence of frames each displaced by a translation, set up once for a stream of sequences:
    y(x) = A s(x), s_k the corrected frame k, ``(o_k - dark) * gain``, sampled bilinearly at x + d_k, with the
    mask and NaNs of :func:`apply_linear_warped` (whose translations run through this).

    One kernel of ``kernels/warp.cl`` per call, ``linear_warp_translate``: 8 pixels of a row at a time, each source
    row read once as vectors and corrected as it is read, the taps off the field clamped to it as the per-pixel
    kernel clamps them (a sample point within the edge pixel's half reads that pixel through two equal taps: its
    value to float32 rounding). With ``corrected_planes``, ``warp_correct`` first writes the corrected frames
    (``corrected``) and their flags (``flags``), which the warp then reads, with the same outputs and mask
    bit for bit. The shifts' device buffer (and the corrected planes) are allocated once; the planes are overwritten
    by each call, so a kernel that reads them (a consistency check) is enqueued before the next call on the same
    (in-order) queue.

    Parameters
    ----------
    queue : pyopencl.CommandQueue
        In-order queue of every launch.
    frames_dtype : uint8, uint16 or float32
        dtype of the frames buffers the calls get.
    A : array_like, (B, K_in)
        Decoder, one column per frame of the buffer.
    shape : (int, int)
        (H, W) of the frames.
    dark : array_like or device array, (H, W) or (K_in, H, W), optional
        Dark level of the sensor pixels, one map or one per frame of the buffer.
    gain : array_like or device array, (H, W), optional
        Flat field; NaN marks a pixel with no response (an output that samples it is NaN).
    saturation : float, optional
        Level at or above which a used sample flags the pixel saturated (default: the integer dtype's maximum).
    read : sequence of int, optional
        Only these frames of the buffer are corrected and sampled (A's columns, the shifts and a per-frame dark
        follow them): a frame no output reads flags no pixel.
    outputs : sequence of (name, rows, layout), optional
        The B rows of A split, in order, into up to four groups, each written to a buffer of its own as
        ``"interleaved"`` (N, rows) or ``"planar"`` (rows, N) float32: the stream's coefficients (N, 5) and XYZ
        (N, 3) from one pass. Default: one group ``"out"``, every row, interleaved.
    corrected_planes : bool
        Also write the corrected frames, ``(o - dark) * gain`` float32 planes of the frames read, and their flags,
        and warp those (two passes, for a later step that reads them).

    Examples
    --------
    >>> import numpy as np, pyopencl as cl
    >>> from specgpu.engine import get_queue, to_device
    >>> queue = get_queue()
    >>> frames = np.stack([np.tile(np.arange(16, dtype=np.float32), (4, 1))] * 2)
    >>> warp = PreparedWarp(queue, np.float32, np.eye(2), (4, 16), outputs=[("y", 2, "planar")])
    >>> out = warp.enqueue(to_device(queue, frames.reshape(-1)), [[0.0, 0.0], [1.5, 0.0]])
    >>> y = np.empty((2, 4, 16), np.float32)
    >>> _ = cl.enqueue_copy(queue, y, out["y"])
    >>> y[:, 1, 2].tolist(), bool(np.isnan(y[:, 1, 15]).all())
    ([2.0, 3.5], True)
    """

    def __init__(self, queue, frames_dtype, A, shape, dark=None, gain=None, *, saturation: float | None = None,
                 read=None, outputs=None, corrected_planes: bool = False):
        dtype = np.dtype(frames_dtype)
        if dtype not in (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32)):
            raise TypeError(f"frames_dtype must be uint8, uint16 or float32, got {dtype}")
        try:
            h, w = (int(v) for v in shape)
        except (TypeError, ValueError):
            raise TypeError(f"shape must be (H, W), got {shape!r}") from None
        if h < 1 or w < 1:
            raise ValueError(f"shape must be two positive sizes (H, W), got {(h, w)}")
        A = check_matrix(A, "A")
        K_in = A.shape[1]
        if read is None:
            read = list(range(K_in))
        else:
            read = [int(k) for k in read]
            if not read or min(read) < 0 or max(read) >= K_in:
                raise ValueError(f"read must name frames 0 .. {K_in - 1} of the buffer (A's columns), got {read}")
        K, B = len(read), A.shape[0]
        if K > MAX_TRANSLATE_FRAMES:
            raise ValueError(f"the translation path reads at most {MAX_TRANSLATE_FRAMES} frames, got {K}; "
                             "apply_linear_warped with affine maps takes any number")
        self.groups = _output_groups(outputs, B)
        saturation = check_level(saturation, "saturation")
        if saturation is None and dtype.kind == "u":
            saturation = float(np.iinfo(dtype).max)
        spatial = (h, w)
        dark_dev, dark_per_frame = kernels.pixel_map(queue, dark, "dark", spatial, K_in)
        gain_dev = kernels.gain_map(queue, gain, spatial)
        self.queue, self.shape, self.n = queue, spatial, h * w
        self.K, self.K_in, self.B, self.read = K, K_in, B, np.array(read)
        self.frames_dtype = dtype
        n = self.n
        shape = _SHAPES[kernel_variant(queue.device)]
        macros = dict(K=K, B=B, IN_T=DTYPE_TO_CTYPE[dtype], HAS_GAIN=gain is not None, IS_FLOAT_IN=dtype == np.float32,
                      HAS_DARK=0 if dark is None else (2 if dark_per_frame else 1),
                      SAT_LEVEL=None if saturation is None else repr(float(saturation)) + "f",
                      STRIP=shape["STRIP"], XSTEPS=shape["XSTEPS"], GROUPS=len(self.groups),
                      FROM_CORRECTED=bool(corrected_planes))
        for g, (_, rows, interleaved) in enumerate(self.groups):
            macros[f"G{g}_ROWS"], macros[f"G{g}_IL"] = rows, interleaved
        self.alloc = get_allocator(queue)
        self._frame_of = cla.to_device(queue, np.asarray(read, np.uint32))
        self._motion = self.alloc(4 * 6 * K)
        self._pending: list = []  # the shifts' non-blocking writes not yet known complete (their host copies)
        self._A = kernels.matrix_on_device(queue, A[:, read])
        self._dark, self._gain = dark_dev, gain_dev  # kept alive with the kernels that read them
        frame_of, dark_buf, gain_buf = self._frame_of.data, kernels._data(dark_dev), kernels._data(gain_dev)
        #: with ``corrected_planes``: the corrected planes, K x H x W float32 in ``read``'s order, as the last call's
        #: first pass wrote them; else None
        self.corrected = None
        #: with ``corrected_planes``: their flags, K x H x W uint8, 1 saturated (at or above ``saturation``), 2 not
        #: finite; else None
        self.flags = None
        self.correct = None
        if corrected_planes:
            self.corrected, self.flags = self.alloc(4 * K * n), self.alloc(K * n)
            self.correct = new_kernel(queue, "warp.cl", "warp_correct", **macros)
            self.correct.set_args(None, frame_of, dark_buf, gain_buf, self.corrected, self.flags, np.uint64(n))
            items = -(-n // 8)
            self._correct_size = ((-(-items // kernels._GROUP) * kernels._GROUP,), (kernels._GROUP,))
            frame_of = dark_buf = gain_buf = None  # the warp reads the planes
        self.warp = new_kernel(queue, "warp.cl", "linear_warp_translate", **macros)
        self.warp.set_args(self.corrected, frame_of, dark_buf, gain_buf, self.flags, self._A.data, self._motion,
                           None, None, None, None, None, np.uint32(w), np.uint32(h))
        columns, strips = -(-w // (8 * shape["XSTEPS"])), -(-h // shape["STRIP"])
        gx, gy = shape["group"]
        self._warp_size = ((-(-columns // gx) * gx, -(-strips // gy) * gy), (gx, gy))
        self._frames_bytes = K_in * n * dtype.itemsize

    #: Argument index of the matrix in linear_warp_translate
    matrix_index = 5

    def enqueue(self, frames, shifts, matrix=None) -> dict:
        """Enqueue the warp (after the correction pass, with ``corrected_planes``) on ``frames`` (the K_in frames, a
        flat :class:`pyopencl.array.Array` of the prepared dtype or a :class:`pyopencl.Buffer`) displaced by
        ``shifts`` ((K_in, 2) (dx, dy) px, finite; only the rows of the frames read are used), written to the
        device without waiting. Returns name -> a fresh pooled buffer of each output group, and ``"mask"`` (N uint8:
        1 saturated, 2 non-finite input, 4 outside the field). ``matrix``: a device buffer of the prepared A's size
        (B x K float32, the columns read) used for this launch and the next ones (a per-sequence decoder)."""
        if isinstance(frames, cla.Array):
            if frames.dtype != self.frames_dtype or frames.offset:
                raise ValueError(f"frames must be a {self.frames_dtype} device array of its own buffer (no offset), "
                                 f"got {frames.dtype}" + (" at an offset" if frames.offset else ""))
            frames = frames.data
        if frames.size < self._frames_bytes:
            raise ValueError(f"the frames buffer holds {frames.size} bytes, fewer than the {self.K_in} frames of "
                             f"{self.shape[0]} x {self.shape[1]} {self.frames_dtype} ({self._frames_bytes} bytes)")
        rows = check_shifts(shifts, self.K_in)  # (K_in, 6): the 2 x 3 maps the kernel reads
        if not np.all(rows[:, [0, 1, 3, 4]] == np.array([1, 0, 0, 1], np.float32)):
            raise ValueError(f"shifts must be translations, ({self.K_in}, 2) (dx, dy per frame): the prepared warp "
                             "samples no affine map (apply_linear_warped does)")
        host = np.ascontiguousarray(rows[self.read])
        self._pending = [e for e in self._pending
                         if e.command_execution_status != cl.command_execution_status.COMPLETE]
        self._pending.append(cl.enqueue_copy(self.queue, self._motion, host, is_blocking=False))
        out = {name: self.alloc(4 * rows * self.n) for name, rows, _ in self.groups}
        out["mask"] = self.alloc(self.n)
        if self.correct is not None:
            self.correct.set_arg(0, frames)
            cl.enqueue_nd_range_kernel(self.queue, self.correct, *self._correct_size)
        else:
            self.warp.set_arg(0, frames)
        if matrix is not None:
            self.warp.set_arg(self.matrix_index, matrix)
            self._matrix = matrix  # it stays set for the next launches: held, as OpenCL holds no reference to it
        for g, (name, _, _) in enumerate(self.groups):
            self.warp.set_arg(7 + g, out[name])
        self.warp.set_arg(11, out["mask"])
        cl.enqueue_nd_range_kernel(self.queue, self.warp, *self._warp_size)
        return out


def prepare_linear_warped(queue, frames_dtype, A, shape, dark=None, gain=None, *, saturation=None, read=None,
                          outputs=None, corrected_planes: bool = False) -> PreparedWarp:
    """:class:`PreparedWarp` (the translation decoding of a stream, set up once), named as the engine's other
    ``prepare_*`` launchers."""
    return PreparedWarp(queue, frames_dtype, A, shape, dark, gain, saturation=saturation, read=read,
                        outputs=outputs, corrected_planes=corrected_planes)


def _output_groups(outputs, B: int) -> list[tuple[str, int, int]]:
    """The output groups as (name, rows, interleaved 0/1), checked: up to MAX_GROUPS, rows adding up to B."""
    if outputs is None:
        return [("out", B, 1)]
    groups = []
    try:
        for name, rows, layout in outputs:
            groups.append((str(name), int(rows), validate_method(layout, _LAYOUTS, "output layout")))
    except (TypeError, ValueError) as error:
        if "layout" in str(error):
            raise
        raise ValueError(f"outputs must be (name, rows, layout) triples, got {outputs!r}") from None
    names = [g[0] for g in groups]
    if not 1 <= len(groups) <= MAX_GROUPS or len(set(names)) != len(names) or "mask" in names:
        raise ValueError(f"outputs must be 1 to {MAX_GROUPS} groups with distinct names other than 'mask', "
                         f"got {names}")
    if min(g[1] for g in groups) < 1 or sum(g[1] for g in groups) != B:
        raise ValueError(f"the output groups' rows {[g[1] for g in groups]} must be positive and add up to A's {B} "
                         "rows")
    return groups
