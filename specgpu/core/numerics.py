"""Small numerics the rooms share: bounded least squares of light levels over column spectra, the flat-field
gain of a pixel with no response, and the process's BLAS on one thread."""

from __future__ import annotations

import hashlib
import math
import os
import threading
from collections import OrderedDict

import numpy as np
from threadpoolctl import threadpool_limits

__all__ = ["DEAD_PIXEL_GAIN", "BLAS_THREAD_VARIABLES", "fit_levels", "lipschitz_bound", "live_gain", "one_blas_thread"]

#: The environment variables that set the BLAS libraries' thread counts (OpenBLAS, MKL, OpenMP builds).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS")


def one_blas_thread() -> bool:
    """Run BLAS on one thread for the rest of the process, unless the environment sets a thread count already
    (:data:`BLAS_THREAD_VARIABLES`: the user's choice stands). Returns whether the limit was applied.

    The host's matrices are small (calibration's least squares over 1024 columns, the designs, the motion
    estimate); the pixels' work runs on the OpenCL device. OpenBLAS splits even a matrix-vector product over every
    core, and where the cores are busy (PoCL's threads, another process) its threads spin waiting on each other:
    on 2 shared cores five SVDs of 200 x 200 took 1.7-2.5 s of CPU with 2 threads and 0.07 s with one. The
    variables are set too, so that a BLAS loaded later (SciPy's) and child processes (Dask's workers) start with
    one thread."""
    if any(os.environ.get(name) for name in BLAS_THREAD_VARIABLES):
        return False
    for name in BLAS_THREAD_VARIABLES:
        os.environ[name] = "1"
    threadpool_limits(limits=1, user_api="blas")
    return True

#: Flat-field gain calibration gives a pixel the white does not reach (under 1 / DEAD_PIXEL_GAIN of the field
#: centre's reading: dead, or outside the light). Such a pixel has no measurement; a gain at or above it marks one.
DEAD_PIXEL_GAIN = 50.0


def live_gain(gain):
    """The flat field as the decoding kernels take it: float32, NaN at the pixels with no response (gain at or above
    :data:`DEAD_PIXEL_GAIN`), so every output of such a pixel, and every warped sample that reads it, is NaN rather
    than its noise times the capped gain. ``None`` stays ``None``; the host's own uses of the flat field (the
    registration images) keep the finite map."""
    if gain is None:
        return None
    g = np.asarray(gain, np.float32)
    dead = g >= DEAD_PIXEL_GAIN
    if not dead.any():
        return g
    g = g.copy()
    g[dead] = np.nan
    return g


def fit_levels(system, target, *, upper: float | None = 1.0, iterations: int = 400) -> np.ndarray:
    """Column levels ``f`` (0 <= f <= upper) minimizing ``|| system @ f - target ||``: bounded least squares
    over the available column spectra (eq. (8)).

    ``system`` is (G, C): a column's spectrum per unit level (an emission, or an emission times V). Start from
    the ratio at each column's centre, refine by projected gradient with Nesterov momentum (the matrix is
    narrow-banded, so this converges in a few hundred cheap steps, each over its nonzero blocks only).

    ``target`` is (G,), or (G, K) for K independent fits on the same system: each column of the answer is the fit
    of that column of ``target``, but the K fits share every product with ``system`` (a matrix product in place of
    K matrix-vector products, which read the whole system from memory each: several times faster for a sequence's
    frames).

    The last fits are kept (keyed by a digest of both arrays, the bound and the step count): the same fit asked
    again, as a plan designed twice on one calibration asks it, returns a copy of the kept answer at once.

    Returns
    -------
    (C,) float64 levels, or (C, K) for a (G, K) target.
    """
    m = np.asarray(system, np.float64)
    t = np.asarray(target, np.float64)
    if m.ndim != 2 or t.ndim not in (1, 2) or t.shape[0] != m.shape[0]:
        raise ValueError(f"target must have shape ({m.shape[0]},), got {t.shape} (or ({m.shape[0]}, K) for K fits)")
    hi = np.inf if upper is None else float(upper)
    key = _fit_key(m, t, hi, iterations)
    with _fits_lock:
        known = _fits.get(key)
        if known is not None:
            _fits.move_to_end(key)
            return known.copy()
    f = _fit(m, t, hi, iterations)
    with _fits_lock:
        _fits[key] = f.copy()
        while len(_fits) > _FITS_KEPT:
            _fits.popitem(last=False)
    return f


#: The fits :func:`fit_levels` keeps (the least recently used dropped first): a plan designed again on one calibration
#: (a budget's capped exposure, the same method asked twice in a study or a demo) reuses its frames' fit, which
#: costs a second or more, instead of redoing it.
_FITS_KEPT = 16
_fits: OrderedDict[bytes, np.ndarray] = OrderedDict()
_fits_lock = threading.Lock()


def _fit_key(m: np.ndarray, t: np.ndarray, hi: float, iterations: int) -> bytes:
    """A digest of everything a fit depends on: both arrays' shapes and bytes, the bound and the step count."""
    digest = hashlib.blake2b(repr((m.shape, t.shape, hi, int(iterations))).encode(), digest_size=32)
    digest.update(np.ascontiguousarray(m).data)
    digest.update(np.ascontiguousarray(t).data)
    return digest.digest()


def _fit(m: np.ndarray, t: np.ndarray, hi: float, iterations: int) -> np.ndarray:
    """The projected-gradient fit of :func:`fit_levels`, uncached."""
    col_sum = m.sum(axis=0)
    peak_row = np.argmax(m, axis=0)
    full = m.sum(axis=1)  # every column on
    lit = (full[peak_row] > 0).reshape((-1,) + (1,) * (t.ndim - 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(lit, t[peak_row] / full[peak_row].reshape(lit.shape), 0.0)
    f = np.clip(np.nan_to_num(f), 0.0, hi)
    step = 1.0 / lipschitz_bound(m)
    product, adjoint = _banded_products(m)
    y, tk = f.copy(), 1.0
    for _ in range(iterations):
        f_new = np.clip(y - step * adjoint(product(y) - t), 0.0, hi)
        tk_new = 0.5 * (1 + math.sqrt(1 + 4 * tk * tk))
        y = f_new + ((tk - 1) / tk_new) * (f_new - f)
        f, tk = f_new, tk_new
    f[col_sum <= 0] = 0.0
    return f


def _banded_products(m: np.ndarray, width: int = 128):
    """``(x -> m @ x, r -> m.T @ r)`` over the rows each block of ``width`` columns reaches: a column's spectrum is
    zero away from its own wavelength, so the blocks of the light's system matrix hold under half its entries, and
    the products skip the rest (the same sums, of the nonzero terms only). A dense matrix makes one block per
    ``width`` columns over every row: the plain products."""
    rows, cols = m.shape
    blocks = []
    for c0 in range(0, cols, width):
        reached = np.flatnonzero(np.any(m[:, c0:c0 + width] != 0, axis=1))
        if reached.size:  # a block of dark columns adds nothing, and its gradient is zero
            r0, r1 = int(reached[0]), int(reached[-1]) + 1
            block = np.ascontiguousarray(m[r0:r1, c0:c0 + width])
            blocks.append((r0, r1, c0, c0 + block.shape[1], block, np.ascontiguousarray(block.T)))

    def product(x):
        out = np.zeros((rows,) + x.shape[1:])
        for r0, r1, c0, c1, block, _ in blocks:
            out[r0:r1] += block @ x[c0:c1]
        return out

    def adjoint(r):
        out = np.zeros((cols,) + r.shape[1:])
        for r0, r1, c0, c1, _, block_t in blocks:
            out[c0:c1] = block_t @ r[r0:r1]
        return out

    return product, adjoint


def lipschitz_bound(m: np.ndarray, iterations: int = 60) -> float:
    """An upper bound of the largest eigenvalue of ``m.T @ m`` by power iteration (a full SVD of the 401 x 1024
    system matrix costs seconds; this costs milliseconds), with a 5 % margin for the unconverged remainder."""
    v = np.ones(m.shape[1]) / math.sqrt(m.shape[1])
    lam = 0.0
    for _ in range(iterations):
        w = m.T @ (m @ v)
        lam = float(np.linalg.norm(w))
        if lam == 0:
            return 1.0
        v = w / lam
    return 1.05 * lam
