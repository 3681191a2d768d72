"""The ``affine`` method: an affine map per frame (a rotation, a zoom, a shear besides the translation), fitted to
the translations of a grid of tiles of each frame registered to the reference frame, tiles off the fit dropped.

The pairwise registration of the frames is the global method's (:func:`specgpu.motion.global_motion.
estimate_global_motion`, ``model="affine"``); from each frame's translation this module fits the map
(:func:`affine_to`) and returns the maps from the sequence's reference time (:func:`affine_estimate`).
"""

from __future__ import annotations

import numpy as np

from specgpu.motion.estimate import MotionEstimate, at_reference_time, fill_in_time
from specgpu.motion.tiles import OUTLIER_PX, tile_displacements_dft

__all__ = ["affine_to", "affine_estimate"]


def affine_to(g_ref: np.ndarray, g_k: np.ndarray, shift, upsample: int, cutoff: float, tiles: int) -> np.ndarray:
    """(3, 3) affine map of reference-frame positions to frame k's: the tiles' displacements
    (:func:`~specgpu.motion.tiles.tile_displacements_dft`) fitted by least squares, tiles more than
    :data:`~specgpu.motion.tiles.OUTLIER_PX` off the fit dropped; the global translation where fewer than 3 tiles
    register."""
    src, dst = tile_displacements_dft(g_ref, g_k, shift, upsample, cutoff, tiles)
    out = np.eye(3)
    out[:2, 2] = shift
    if len(src) < 3:
        return out
    X = np.c_[src, np.ones(len(src))]
    Y = dst
    keep = np.ones(len(src), bool)
    for _ in range(4):
        M, *_ = np.linalg.lstsq(X[keep], Y[keep], rcond=None)
        residual = np.abs(X @ M - Y).max(axis=1)
        bad = residual > max(OUTLIER_PX, 4.0 * float(np.median(residual[keep])))
        if not (bad & keep).any() or (keep & ~bad).sum() < 3:
            break
        keep &= ~bad
    out[:2] = M.T
    return out


def affine_estimate(raw: np.ndarray, usable: np.ndarray, error: np.ndarray, reference_frame: int, gradient,
                    upsample: int, cutoff: float, tiles: int, gradients: tuple | None) -> MotionEstimate:
    """The affine estimate of a sequence from each usable frame's translation ``raw`` (K, 2) to the reference
    frame: each frame's map fitted to its tiles (:func:`affine_to`, ``gradient(k)``: frame k's gradient image),
    the frames not ``usable`` filled in time, and every map taken from the reference time."""
    K = len(raw)
    maps = np.tile(np.eye(3), (K, 1, 1))
    for k in np.flatnonzero(usable):
        if k != reference_frame:
            maps[k] = affine_to(gradient(reference_frame), gradient(int(k)), raw[k], upsample, cutoff, tiles)
    maps = fill_in_time(maps, usable)
    to_mid = np.linalg.inv(at_reference_time(maps))
    return MotionEstimate((maps @ to_mid)[:, :2, :], usable, error, int(reference_frame), "affine", gradients)
