"""The noise floors of a sequence's frames on the device (``kernels/noise_floor.cl``): what the temporal noise alone
gives each frame's local gradient energy, which the consistency check of a motion-compensated sequence reads
(:func:`specgpu.motion.consistency.noise_floors` is the NumPy reference and says what the floor is).

Per frame, ``coef_k (max(box(x f^2), 0) / g + s_read^2 box(f^2))``: box a (2 R + 1)^2 mean with the edges
replicated, x the frame above its dark level, f the flat field, g the camera's electrons per DN, ``coef_k`` the
caller's per-frame factor. Two separable passes on the device; the floors stay there for the check
(:class:`FloorPlanes`).
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from numpy.typing import ArrayLike
from scipy import ndimage

from specgpu.engine import kernels
from specgpu.engine.runtime import DTYPE_TO_CTYPE, get_allocator, get_kernel

__all__ = ["FloorPlanes", "PreparedNoiseFloors"]

#: (rows a work-item of the column pass runs down, pixels one of the row pass runs along) by pixels per work-item:
#: CPU devices (8) few long work-items, measured on PoCL (a work-item per pixel took four times as long); GPUs (1)
#: a work-item per pixel
_SHAPES = {8: (32, 128), 1: (1, 1)}


class FloorPlanes:
    """Noise floors of K frames on the device, (K, H, W) float32 (:class:`PreparedNoiseFloors`), of which the
    consistency check takes the frames it compares (:meth:`take`)."""

    def __init__(self, array: cla.Array):
        if array.ndim != 3 or array.dtype != np.float32:
            raise ValueError(f"floor planes must be a (K, H, W) float32 device array, got {array.shape} "
                             f"{array.dtype}")
        self.array = array

    @property
    def shape(self) -> tuple:
        return self.array.shape

    def take(self, frames=None) -> cla.Array:
        """The planes of ``frames`` (indices, in order; None: every one) as a (len(frames), H, W) device array: the
        planes themselves where they are all of them in order, else copied on the device."""
        K, h, w = self.array.shape
        if frames is None or list(frames) == list(range(K)):
            return self.array
        frames = [int(k) for k in frames]
        if any(not 0 <= k < K for k in frames):
            raise ValueError(f"frames must name planes 0 .. {K - 1}, got {frames}")
        q, n = self.array.queue, h * w
        out = cla.Array(q, (len(frames), h, w), np.float32, allocator=get_allocator(q))
        for i, k in enumerate(frames):
            cl.enqueue_copy(q, out.data, self.array.data, byte_count=4 * n, src_offset=4 * n * k,
                            dst_offset=4 * n * i)
        return out

    def get(self) -> np.ndarray:
        return self.array.get()


class PreparedNoiseFloors:
    """The noise floors of one sensor's frames, set up once on a queue: its dark level, squared flat field and the
    box mean of its read noise on the device.

    Parameters
    ----------
    queue : pyopencl.CommandQueue
    shape : (int, int)
        (H, W) of the frames.
    dark : array_like, (H, W), optional
        The dark level the frames are read above.
    gain : array_like, (H, W), optional
        The flat field (NaN read as 0, as the gradient images read it).
    gain_e_per_dn, read_var_dn2 : float
        The camera's noise (:class:`specgpu.planning.noise.NoiseModel`'s fields).
    window : int
        The box's odd width.
    """

    def __init__(self, queue, shape, dark: ArrayLike | None = None, gain: ArrayLike | None = None, *,
                 gain_e_per_dn: float, read_var_dn2: float, window: int = 9):
        h, w = (int(v) for v in shape)
        window = int(window)
        if h < 1 or w < 1 or window < 1 or window % 2 == 0:
            raise ValueError(f"shape must be two positive sizes and window an odd width, got {(h, w)} and {window}")
        if not (np.isfinite(gain_e_per_dn) and gain_e_per_dn > 0 and np.isfinite(read_var_dn2)
                and read_var_dn2 >= 0):
            raise ValueError(f"gain_e_per_dn must be positive and read_var_dn2 non-negative, got {gain_e_per_dn} "
                             f"and {read_var_dn2}")
        self.queue, self.shape, self.window = queue, (h, w), window
        self.inv_gain, self.read_var = 1.0 / float(gain_e_per_dn), float(read_var_dn2)
        self._dark = self._flat2 = self._read_box = None
        if dark is not None:
            d = np.asarray(dark, np.float32)
            if d.shape != (h, w):
                raise ValueError(f"dark must be one (H, W) = {(h, w)} map, got shape {d.shape}")
            self._dark = kernels.to_device(queue, d.reshape(-1))
        if gain is not None:
            f = np.nan_to_num(np.asarray(gain, np.float32), nan=0.0)
            if f.shape != (h, w):
                raise ValueError(f"gain must be one (H, W) = {(h, w)} map, got shape {f.shape}")
            flat2 = f * f
            read_box = np.float32(self.read_var) * ndimage.uniform_filter(flat2, window, mode="nearest")
            self._flat2 = kernels.to_device(queue, flat2.reshape(-1))
            self._read_box = kernels.to_device(queue, read_box.astype(np.float32).reshape(-1))
        self.alloc = get_allocator(queue)

    def floors(self, frames, coef, read=None) -> FloorPlanes:
        """Enqueue the floors of ``frames`` ((K, H, W) uint8, uint16 or float32, on the host or a flat device array
        of K planes) ``read`` (None: every one), each times its ``coef`` (one per frame made); returns them on the
        device."""
        q = self.queue
        h, w = self.shape
        n = h * w
        fdev = kernels.frame_planes(q, frames, self.shape)
        dtype, K = fdev.dtype, fdev.size // n
        read = list(range(K)) if read is None else [int(k) for k in read]
        if not read or min(read) < 0 or max(read) >= K:
            raise ValueError(f"read must name frames 0 .. {K - 1}, got {read}")
        coef = np.asarray(coef, np.float32).reshape(-1)
        if coef.shape != (len(read),) or not np.isfinite(coef).all():
            raise ValueError(f"coef must be {len(read)} finite numbers (one per frame made), got {coef.shape}")
        vw = kernels._vw(q)
        strip, span = _SHAPES[vw]
        macros = dict(IN_T=DTYPE_TO_CTYPE[np.dtype(dtype)], HAS_DARK=self._dark is not None,
                      HAS_GAIN=self._flat2 is not None, R=self.window // 2, VW=kernels._vw_macro(vw),
                      CSTRIP=strip, RSPAN=span)
        consts = kernels.uploaded(q, np.asarray(read, np.uint32), coef)
        sums = self.alloc(4 * len(read) * n)
        out = cla.Array(q, (len(read), h, w), np.float32, allocator=self.alloc)
        dims = (np.uint32(w), np.uint32(h))
        group = (1, 1, 1) if vw == 8 else (16, 4, 1)
        cols = get_kernel(q, "noise_floor.cl", "floor_cols", **macros)
        rows = get_kernel(q, "noise_floor.cl", "floor_rows", **macros)
        kernels.launch_range(q, cols, (-(-w // vw), -(-h // strip), len(read)), group, fdev.data, consts[0],
                             kernels._data(self._dark), kernels._data(self._flat2), sums, *dims)
        kernels.launch_range(q, rows, (-(-w // span), h, len(read)), group, sums, consts[1],
                             kernels._data(self._read_box), np.float32(self.read_var), np.float32(self.inv_gain),
                             out.data, *dims)
        return FloorPlanes(out)  # the pooled buffers reused only by later commands of this in-order queue
