"""What a motion estimate of one sequence is, and what every method shares: the displacements from the sequence's
reference time, a frame's value filled in time from the frames around it, and the BLAS library held on one thread
while an estimate runs.

The displacements are taken relative to the sequence's reference time, the mean of its frames' times (the middle
frame's time for odd K), which is where the twin's truth puts the scene (``TwinRig.motion_truth``).
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import ThreadpoolController

__all__ = ["MotionEstimate", "at_reference_time", "fill_in_time", "one_blas_thread"]


@dataclass(frozen=True)
class MotionEstimate:
    """Displacements of one sequence's frames.

    Attributes
    ----------
    shifts : numpy.ndarray
        (K, 2) displacement (x, y) of each frame from the reference time, px.
    registered : numpy.ndarray
        (K,) bool: the frame was registered (False: interpolated from the others).
    error : numpy.ndarray
        (K,) phase correlation's translation-invariant normalised RMS error of each registration (NaN if not
        registered): near 1 when the two images share little.
    reference_frame : int
        The frame the others were registered to.
    model : str
        ``"translation"``: ``shifts`` is (K, 2); ``"affine"``: (K, 2, 3), frame k saw the point at reference
        position x at ``shifts[k] @ (x, y, 1)``.
    """

    shifts: np.ndarray
    registered: np.ndarray
    error: np.ndarray
    reference_frame: int
    model: str = "translation"
    #: The full-resolution gradient images (:func:`gradient_image`) the estimate had, per frame: those it made (a
    #: frame it registered) and those it was given (``gradients=``, which may hold every frame); None for a frame
    #: it neither made nor was given. What :func:`inconsistent_pixels` reads again.
    gradients: tuple | None = field(default=None, repr=False, compare=False)


def at_reference_time(values: np.ndarray) -> np.ndarray:
    """The value at a sequence's reference time of per-frame ``values`` (K, ...): the middle frame's for odd K, the
    mean of the middle two frames' for even K (the mean of the frames' times)."""
    mid = (len(values) - 1) / 2.0
    return 0.5 * (values[int(np.floor(mid))] + values[int(np.ceil(mid))])



def fill_in_time(values: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """``values`` (K, ...) of the frames not ``usable`` linear in time between (or beyond) the nearest two usable
    frames."""
    values = values.copy()
    idx = np.flatnonzero(usable)
    for k in np.flatnonzero(~usable):
        if idx.size == 1:
            values[k] = values[idx[0]]
            continue
        lo, hi = idx[idx < k][-1:], idx[idx > k][:1]
        a, b = (lo[0], hi[0]) if lo.size and hi.size else tuple(idx[:2] if not lo.size else idx[-2:])
        values[k] = values[a] + (values[b] - values[a]) * (k - a) / (b - a)
    return values


@functools.lru_cache(maxsize=1)
def _blas() -> ThreadpoolController:
    return ThreadpoolController()


def one_blas_thread(fn):
    """``fn`` run with the BLAS library on one thread. The sub-pixel peak search multiplies small matrices (about
    15 x H by H x W per registration, over a hundred per sequence); OpenBLAS splits each over all cores, and on a
    machine whose cores are busy (the stream's own threads, another process) its threads wait on each other: on 2
    shared cores a 640 x 480 sequence's estimate took 2.3-4.8 s with 2 threads and 0.3-0.5 s with one. The limit
    is process-wide: held from the first of concurrent calls (the stream estimates sequences on several threads)
    until the last returns, then restored."""
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with _BLAS_LOCK:
            if _BLAS_HELD["count"] == 0:
                _BLAS_HELD["limiter"] = _blas().limit(limits=1, user_api="blas")
            _BLAS_HELD["count"] += 1
        try:
            return fn(*args, **kwargs)
        finally:
            with _BLAS_LOCK:
                _BLAS_HELD["count"] -= 1
                if _BLAS_HELD["count"] == 0:
                    _BLAS_HELD.pop("limiter").restore_original_limits()
    return wrapped


_BLAS_LOCK = threading.Lock()
_BLAS_HELD: dict = {"count": 0}
