"""The per-pixel residual check of a motion-compensated decoding on the device (``kernels/residual.cl``).

A pixel's N compensated samples s (dark-subtracted and flat-fielded, as the decoder reads them) are explained by
one reflectance when their residual components ``P s`` (R of them: what the plan's model leaves free) are within
their noise: ``chi2 = (P s)^T C^-1 (P s)`` with ``C = P diag(var) P^T + mismatch`` and ``var_k`` the camera's noise
at sample k's own level. The kernel computes it per pixel (a Cholesky factorisation of C) straight from the warped
pass's sample planes, which stay on the device, and sets :attr:`~specgpu.core.mask.Mask.INCONSISTENT` in the pass's
mask where it exceeds the threshold: no sample is read back. The statistics behind ``P``, ``mismatch`` and the
threshold are the motion room's (:mod:`specgpu.motion.residual`, whose NumPy ``residual_chi2`` is the reference).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
from numpy.typing import ArrayLike

from specgpu.engine import kernels
from specgpu.engine.runtime import get_kernel, get_queue

__all__ = ["PreparedResidual", "residual_chi2_device"]

class PreparedResidual:
    """The residual check of one plan set up once on a queue: its projection, mismatch and noise on the device.

    Parameters
    ----------
    queue : pyopencl.CommandQueue
    project : array_like, (R, N)
        The samples' residual components.
    mismatch : array_like, (R, R)
        Their covariance from spectra outside the plan's model, DN^2.
    gain_e_per_dn, read_var_dn2, light_rms : float
        The camera's noise per raw sample (:class:`specgpu.planning.noise.NoiseModel`'s fields).
    threshold : float
        chi2 above which a pixel is flagged.
    chi : bool
        Also write each pixel's chi2 (:meth:`enqueue`'s ``chi_out``).
    """

    def __init__(self, queue, project: ArrayLike, mismatch: ArrayLike, *, gain_e_per_dn: float, read_var_dn2: float,
                 light_rms: float, threshold: float, chi: bool = False, has_gain: bool = True):
        P = np.atleast_2d(np.asarray(project, np.float64))
        M = np.asarray(mismatch, np.float64)
        R, N = P.shape
        if R < 1 or N < 1 or M.shape != (R, R):
            raise ValueError(f"project must be (R, N) and mismatch (R, R), got {P.shape} and {M.shape}")
        self.queue, self.R, self.N = queue, R, N
        self.vw = kernels._vw(queue)  # pixels per work-item: vectors of 8 on CPU devices, one on GPUs
        self.kernel = get_kernel(queue, "residual.cl", "residual_flag", N=N, R=R, HAS_GAIN=bool(has_gain),
                                 WRITE_CHI=bool(chi), VW=kernels._vw_macro(self.vw))
        self._P = kernels.matrix_on_device(queue, P)
        self._M = kernels.matrix_on_device(queue, M)
        self.noise = (np.float32(1.0 / float(gain_e_per_dn)), np.float32(read_var_dn2),
                      np.float32(float(light_rms) ** 2))
        self.threshold = np.float32(threshold)

    def enqueue(self, samples, gain, mask, n: int, chi_out=None):
        """Enqueue the check of ``n`` pixels: ``samples`` (N planes of n float32, a buffer or device array),
        ``gain`` (n float32 flat field, or None when prepared without one), ``mask`` (n uint8, flags OR-ed in);
        returns the event."""
        data = [None if a is None else (a.data if isinstance(a, cla.Array) else a)
                for a in (samples, gain, mask, chi_out)]
        return kernels._launch(self.queue, self.kernel, int(n), data[0], data[1], self._P.data, self._M.data,
                               *self.noise, self.threshold, data[2], data[3], np.uint32(n), pixels_per_item=self.vw)


def residual_chi2_device(samples: ArrayLike, project: ArrayLike, mismatch: ArrayLike, *, gain_e_per_dn: float,
                         read_var_dn2: float, light_rms: float, threshold: float = np.inf, gain=None,
                         device=None) -> tuple[np.ndarray, np.ndarray]:
    """(chi2 (H, W) float32, flagged (H, W) bool) of each pixel's compensated ``samples`` (H, W, N) on the device,
    ``gain`` (H, W) the flat field they were divided by (NaN where a sample is; :class:`PreparedResidual`)."""
    s = np.asarray(samples, np.float32)
    if s.ndim != 3:
        raise ValueError(f"samples must be (H, W, N), got shape {s.shape}")
    h, w, N = s.shape
    n = h * w
    queue = get_queue(device)
    check = PreparedResidual(queue, project, mismatch, gain_e_per_dn=gain_e_per_dn, read_var_dn2=read_var_dn2,
                             light_rms=light_rms, threshold=threshold, chi=True, has_gain=gain is not None)
    if check.N != N:
        raise ValueError(f"samples hold {N} per pixel; project reads {check.N}")
    planes = kernels.to_device(queue, np.ascontiguousarray(np.moveaxis(s, -1, 0)).reshape(-1))
    g = None if gain is None else kernels.to_device(queue, np.asarray(gain, np.float32).reshape(-1))
    mask = kernels.to_device(queue, np.zeros(max(n, 1), np.uint8))
    chi = kernels._empty(queue, max(n, 1), np.float32)
    if n:
        check.enqueue(planes, g, mask, n, chi)
    return chi.get()[:n].reshape(h, w), mask.get()[:n].reshape(h, w).astype(bool)
