"""Small numerics the rooms share: bounded least squares of light levels over column spectra, the flat-field
gain of a pixel with no response, and the process's BLAS on one thread."""

from __future__ import annotations

import math
import os

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
    narrow-banded, so this converges in a few hundred cheap steps).

    Returns
    -------
    (C,) float64 levels.
    """
    m = np.asarray(system, np.float64)
    t = np.asarray(target, np.float64)
    if m.ndim != 2 or t.shape != (m.shape[0],):
        raise ValueError(f"target must have shape ({m.shape[0]},), got {t.shape}")
    hi = np.inf if upper is None else float(upper)
    col_sum = m.sum(axis=0)
    peak_row = np.argmax(m, axis=0)
    full = m.sum(axis=1)  # every column on
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(full[peak_row] > 0, t[peak_row] / full[peak_row], 0.0)
    f = np.clip(np.nan_to_num(f), 0.0, hi)
    step = 1.0 / lipschitz_bound(m)
    y, tk = f.copy(), 1.0
    for _ in range(iterations):
        f_new = np.clip(y - step * (m.T @ (m @ y - t)), 0.0, hi)
        tk_new = 0.5 * (1 + math.sqrt(1 + 4 * tk * tk))
        y = f_new + ((tk - 1) / tk_new) * (f_new - f)
        f, tk = f_new, tk_new
    f[col_sum <= 0] = 0.0
    return f


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
