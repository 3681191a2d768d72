"""What the tiles of a frame say about its motion: each tile of the reference frame registered where the global
translation puts it, and the translation most of the field shares (an object moving on its own over the scene
can take a whole-image correlation over; the tiles outvote it).
"""

from __future__ import annotations

import numpy as np
from skimage.registration import phase_cross_correlation

from specgpu.motion.registration import tile_displacements
from specgpu.motion.whitening import hann, whitened_spectrum

__all__ = ["OUTLIER_PX", "register_dft", "tile_displacements_dft", "dominant_translation"]

#: A pair's registration that disagrees by more than this (px) with the least-squares solution of all the others
#: is dropped (a failed correlation peak); with ``pairs="all"`` each frame is registered to up to 16 others.
OUTLIER_PX = 0.5


def register_dft(a: np.ndarray, b: np.ndarray, upsample: int) -> tuple[np.ndarray, float]:
    """(x, y) displacement of the content of whitened spectrum ``b`` relative to ``a``, and the error."""
    shift, err, _ = phase_cross_correlation(a, b, upsample_factor=upsample, normalization=None, space="fourier")
    return -np.asarray(shift[::-1], np.float64), float(err)



def tile_displacements_dft(g_ref, g_k, shift, upsample: int, cutoff: float, tiles, max_error: float = 1.0):
    """Centres (N, 2) of the tiles of a ``tiles`` x ``tiles`` (or (rows, columns)) grid of the reference image and
    where frame k saw each (N, 2): every tile registered where the global ``shift`` puts it (tiles it moves off
    the field skipped, and those whose correlation error is above ``max_error``)."""
    h, w = g_ref.shape
    ty, tx = (tiles, tiles) if np.isscalar(tiles) else tiles
    th, tw = h // ty, w // tx
    t = np.rint(np.asarray(shift)).astype(int)
    src, dst = [], []
    for i in range(ty):
        for j in range(tx):
            y0, x0 = i * th, j * tw
            ys, xs = y0 + t[1], x0 + t[0]
            if ys < 0 or xs < 0 or ys + th > h or xs + tw > w:
                continue
            d, err = register_dft(whitened_spectrum(hann(g_ref[y0:y0 + th, x0:x0 + tw]), cutoff),
                                  whitened_spectrum(hann(g_k[ys:ys + th, xs:xs + tw]), cutoff), upsample)
            if err > max_error:
                continue
            c = np.array([x0 + (tw - 1) / 2.0, y0 + (th - 1) / 2.0])
            src.append(c)
            dst.append(c + t + d)
    return np.reshape(src, (-1, 2)), np.reshape(dst, (-1, 2))



def _tiles_at(g_ref, g_k, where, upsample: int, cutoff: float, tiles, reference_tiles: dict | None) -> np.ndarray:
    """The tiles' displacements (N, 2) with the frame registered where ``where`` puts it: by the fitted peak
    (:func:`specgpu.motion.registration.tile_displacements`, the reference's tiles' spectra kept in
    ``reference_tiles``) or, ``reference_tiles`` None, by the upsampled DFT (:func:`tile_displacements_dft`)."""
    src, dst = tile_displacements_dft(g_ref, g_k, where, upsample, cutoff, tiles) if reference_tiles is None \
        else tile_displacements(g_ref, g_k, where, cutoff, tiles, reference_tiles)
    return dst - src


def dominant_translation(g_ref, g_k, shift, upsample: int, cutoff: float, tiles: int,
                         reference_tiles: dict | None = None) -> np.ndarray:
    """The translation most of the field shares: ``shift`` (the whole-image registration) unless the tiles'
    median is more than :data:`OUTLIER_PX` from it (a smaller, strongly textured object moving on its own
    dominates the whole-image correlation), then the mean of the tiles within :data:`OUTLIER_PX` of their
    median, the tiles registered again at that median; ``shift`` where fewer than three tiles are that near (the
    tiles agree on nothing). ``reference_tiles``: the tiles registered by
    :func:`specgpu.motion.registration.tile_displacements` (the fitted peak), the reference's tiles' spectra
    kept in it across frames; None: by the upsampled DFT."""
    d = _tiles_at(g_ref, g_k, shift, upsample, cutoff, tiles, reference_tiles)
    if len(d) < 3:
        return np.asarray(shift, np.float64)
    med = np.median(d, axis=0)
    if np.abs(med - shift).max() <= OUTLIER_PX:
        return np.asarray(shift, np.float64)
    if np.any(np.rint(med) != np.rint(shift)):  # again where the tiles overlap fully: each peak more accurate
        again = _tiles_at(g_ref, g_k, med, upsample, cutoff, tiles, reference_tiles)
        if len(again) >= 3:
            d, med = again, np.median(again, axis=0)
    near = np.abs(d - med).max(axis=1) <= OUTLIER_PX
    # no three tiles agree on the median (a dim frame's tiles scattered, some a pattern's period off): no consensus
    return d[near].mean(axis=0) if near.sum() >= 3 else np.asarray(shift, np.float64)
