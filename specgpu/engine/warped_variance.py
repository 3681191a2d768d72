"""The variance of a motion-compensated decoding's outputs, on the device (``kernels/warped_variance.cl``).

A motion-compensated output reads frame k bilinearly at the point the frame saw each pixel; its variance is each
frame's sample variance through the decoder's squared rows. The kernel makes the samples' variances where the
warped pass samples the frames (the camera's noise per sensor pixel, interpolated with the bilinear weights
squared, plus the light's fluctuation at the sample's own signal; and, for a guided filter, the own part as the
filter takes it) and writes only their C weighted sums per pixel, so the K per-frame variance maps the host
computation makes (:func:`specgpu.pipeline.moving_decode.warped_sample_variances`, the float64 reference) are never
made. Translations and affine maps per frame; a dense flow is not served here.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from numpy.typing import ArrayLike

from specgpu.core.numerics import live_gain
from specgpu.engine import kernels
from specgpu.engine.runtime import DTYPE_TO_CTYPE, get_allocator, get_kernel
from specgpu.engine.warp_map import check_shifts

__all__ = ["PreparedWarpedVariance"]

#: Channels one launch writes at most (the kernel keeps three accumulators per channel in private memory)
MAX_CHANNELS = 128
#: Work-groups by pixels per work-item: vectors of 8 along a row, a work-item per pixel (GPUs: neighbours along x)
_GROUP = {8: (4, 4), 1: (16, 4)}


class PreparedWarpedVariance:
    """The motion-compensated outputs' variance for one sensor, set up once on a queue: its dark level, flat field
    and noise on the device.

    Parameters
    ----------
    queue : pyopencl.CommandQueue
    shape : (int, int)
        (H, W) of the frames.
    dark : array_like, (H, W)
        The dark level the frames are read above, DN.
    gain : array_like, (H, W), optional
        The flat field the samples are multiplied by (NaN or at least the dead-pixel gain: a pixel with no
        response, whose variance is NaN, :func:`specgpu.core.numerics.live_gain`).
    gain_e_per_dn, read_var_dn2, light_rms : float
        The camera's noise (:class:`specgpu.planning.noise.NoiseModel`'s fields).

    Examples
    --------
    >>> import numpy as np
    >>> from specgpu.engine import get_queue
    >>> frames = np.full((2, 4, 6), 100.0, np.float32)
    >>> prep = PreparedWarpedVariance(get_queue(), (4, 6), np.zeros((4, 6)), gain_e_per_dn=1.0, read_var_dn2=4.0,
    ...                               light_rms=0.0)
    >>> total, _, _ = prep.channels(frames, [[0.0, 0.0], [1.5, 0.0]], [0, 1], [[1.0, 1.0]])
    >>> float(total[1, 1, 0]), bool(np.isnan(total[1, 5, 0]))
    (156.0, True)
    """

    def __init__(self, queue, shape, dark: ArrayLike, gain: ArrayLike | None = None, *, gain_e_per_dn: float,
                 read_var_dn2: float, light_rms: float):
        h, w = (int(v) for v in shape)
        if h < 1 or w < 1:
            raise ValueError(f"shape must be two positive sizes (H, W), got {(h, w)}")
        if not (np.isfinite(gain_e_per_dn) and gain_e_per_dn > 0):
            raise ValueError(f"gain_e_per_dn must be a positive number, got {gain_e_per_dn}")
        if not (np.isfinite(read_var_dn2) and read_var_dn2 >= 0 and np.isfinite(light_rms) and light_rms >= 0):
            raise ValueError(f"read_var_dn2 and light_rms must be non-negative numbers, got {read_var_dn2} and "
                             f"{light_rms}")
        dark = np.asarray(dark, np.float32)
        if dark.shape != (h, w):
            raise ValueError(f"dark must be one (H, W) = {(h, w)} map, got shape {dark.shape}")
        self.queue, self.shape, self.n = queue, (h, w), h * w
        self.noise = (float(gain_e_per_dn), float(read_var_dn2), float(light_rms))
        self._dark = kernels.to_device(queue, dark.reshape(-1))
        self._gain2 = None
        if gain is not None:
            g = np.asarray(live_gain(gain), np.float32)
            if g.shape != (h, w):
                raise ValueError(f"gain must be one (H, W) = {(h, w)} map, got shape {g.shape}")
            self._gain2 = kernels.to_device(queue, (g * g).reshape(-1))
        self.alloc = get_allocator(queue)

    def upload(self, frames) -> cla.Array:
        """``frames`` ((K, H, W) uint8, uint16 or float32) as one flat device array of K planes, for several
        :meth:`channels` calls on the same sequence (an object layer's shifts); a device array of whole planes as
        it is (:func:`specgpu.engine.kernels.frame_planes`)."""
        return kernels.frame_planes(self.queue, frames, self.shape)

    def channels(self, frames, shifts, read, weights, *, light: bool = True, ambient: int | None = None,
                 own: bool = False, corr: float | None = None):
        """The weighted sums of the read frames' sample variances per pixel: ``(total, own, filtered)``, each
        (H, W, C) float32 (``own`` and ``filtered`` None unless asked for), NaN where a frame saw the pixel
        outside the field.

        Parameters
        ----------
        frames : array_like, (K, H, W), or a device array of K planes (:meth:`upload`)
            uint8, uint16 or float32 frames of one sequence on the sensor's scale (the dark level not subtracted).
        shifts : array_like, (K, 2) or (K, 2, 3)
            Each frame's translation or affine map (:func:`specgpu.engine.warp_map.apply_linear_warped`).
        read : sequence of int
            The frames the decoder reads (``weights``' columns, in order).
        weights : array_like, (C, len(read))
            Channel c is ``sum_k weights[c, k] V_k``.
        light : bool
            Add the light's fluctuation to ``total`` (off where a reference white's gains divide it out).
        ambient : int, optional
            The plan's ambient frame: no light's fluctuation on its sample; the others' is at their signal above it.
        own : bool
            Also the sums of the samples' own part (no light).
        corr : float, optional
            The own part as a guided filter takes it (``1 - R(1) / R(0)`` of its weights,
            :func:`specgpu.pipeline.moving_decode.warped_sample_variance`'s ``filtered``).
        """
        q = self.queue
        h, w = self.shape
        fdev = self.upload(frames)
        dtype, K = fdev.dtype, fdev.size // self.n
        if np.ndim(shifts) == 4:
            raise ValueError("shifts: a dense flow's variance is not made on the device (translations and affine "
                             "maps are)")
        d = check_shifts(shifts, K)
        read = [int(k) for k in read]
        if not read or min(read) < 0 or max(read) >= K:
            raise ValueError(f"read must name frames 0 .. {K - 1}, got {read}")
        Wt = np.atleast_2d(np.asarray(weights, np.float32))
        C = Wt.shape[0]
        if Wt.shape[1] != len(read) or not 1 <= C <= MAX_CHANNELS or not np.isfinite(Wt).all():
            raise ValueError(f"weights must be (C, {len(read)}) finite numbers with 1 <= C <= {MAX_CHANNELS}, got "
                             f"shape {Wt.shape}")
        if ambient is not None and not 0 <= int(ambient) < K:
            raise ValueError(f"ambient must name one of the {K} frames, got {ambient}")
        gain_e, read_var, light_rms = self.noise
        with_light = bool(light) and light_rms > 0
        vw = kernels._vw(q)
        kernel = get_kernel(q, "warped_variance.cl", "warped_variances", IN_T=DTYPE_TO_CTYPE[np.dtype(dtype)],
                            KR=len(read), NCH=C, VW=kernels._vw_macro(vw), HAS_GAIN=self._gain2 is not None,
                            WITH_LIGHT=with_light,
                            AMBIENT=-1 if ambient is None or not with_light else int(ambient), WANT_OWN=bool(own),
                            WANT_FILTERED=corr is not None)
        outs = [self.alloc(4 * C * self.n) if want else None for want in (True, own, corr is not None)]
        small = [np.asarray(read, np.uint32), np.ascontiguousarray(d[read]), np.ascontiguousarray(Wt)]
        limit = q.device.max_constant_buffer_size
        if max(a.nbytes for a in small) > limit:
            raise ValueError(f"weights of {C} channels x {len(read)} frames ({Wt.nbytes} bytes) exceed the constant "
                             f"memory of {q.device.name.strip()} ({limit} bytes); ask for fewer channels per call")
        consts = kernels.uploaded(q, *small)
        kernels.launch_range(q, kernel, (-(-w // vw), h), _GROUP[vw], fdev.data, *consts,
                             self._dark.data, kernels._data(self._gain2), np.float32(1.0 / gain_e),
                             np.float32(read_var), np.float32(light_rms), np.float32(0.0 if corr is None else corr),
                             outs[0], outs[1], outs[2], np.uint32(w), np.uint32(h))
        host = []
        for buf in outs:
            if buf is None:
                host.append(None)
                continue
            planes = np.empty((C, h, w), np.float32)
            cl.enqueue_copy(q, planes, buf)
            host.append(np.moveaxis(planes, 0, -1))
        return tuple(host)
