"""Dense motion of one sequence (``--motion flow``): a displacement per pixel and frame, for scenes whose parts move
differently (an object on its own, a rotation or a zoom a translation cannot follow, a non-rigid motion).

The flow is a block-matching one, on the same spectrum-independent gradient images as the global estimate
(:func:`specgpu.motion.images.gradient_image`): between two frames lit by different spectra the brightness of a
surface changes, the place of its edges does not, so a brightness-constancy flow has nothing to hold on to.

1. The global translation of each frame is estimated first
   (:func:`specgpu.motion.global_motion.estimate_global_motion`).
2. The reference frame is cut into tiles of about :data:`TILE_PX` px; each tile is registered in every other frame by
   phase correlation around where the global motion and its own motion so far put it (the frames nearest the
   reference first, so that a tile moving on its own is followed however far it goes in the sequence).
3. Within one sequence (tens of milliseconds) a part of the scene moves steadily relative to the rest: each tile's
   motion is fitted as one velocity relative to the global translation, frames whose peak disagrees with it by
   more than :data:`STEADY_PX` dropped (a repeating texture's peak a period off, a tile an occlusion covers),
   together with a correction of each frame's global translation that the tiles agree on (the whole-image
   correlation of a scene whose parts move differently, a rotation's, is a compromise between them). A tile with
   too little structure, or whose frames agree on no velocity, takes the nearest measured tile's; then each
   tile's velocity is the median of its 3 x 3 neighbourhood's.
4. The velocities are interpolated bilinearly between the tiles' centres: frame k saw pixel x at
   x + d_k + v(x) (t_k - t_ref), d_k the global translation, t_ref the reference time.

A tile that straddles two motions takes one of them, and the interpolation blurs a motion boundary over a tile;
so the flow is a second hypothesis beside the global one (with its object layers,
:func:`specgpu.pipeline.moving_layers.recover_moving`), not a replacement (:func:`choose_flow`): a pixel takes the
flow's decoding where the frames the flow compensates agree and the global decoding is flagged, has no texture or
is not better correlated by more than a margin; an object layer's pixel takes it only where its frames are textured
and agree under the flow (the layer's own agreement is not compared: its check's maps are not kept), and a pixel
consistent under neither stays NaN and flagged. The steady fit needs :data:`MIN_FRAMES` frames besides the
reference: a flow needs sequences of at least ``MIN_FRAMES + 1`` frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft, ndimage

from specgpu.motion.estimate import at_reference_time
from specgpu.motion.registration import fit_peaks
from specgpu.motion.whitening import whitened_stack

__all__ = ["TILE_PX", "STEADY_PX", "MIN_PEAK_SHARE", "MIN_FRAMES", "MIN_TILES", "TileMotion", "tile_motion",
           "flow_field", "choose_flow"]

#: Side of the flow's tiles, px (the field divided into the nearest whole number of tiles each way).
TILE_PX = 48

#: A frame's tile displacement counts towards the tile's velocity where it lies within this (px) of it.
STEADY_PX = 1.0

#: A tile's correlation peak counts where it holds at least this share of a perfect match's (the peak of a tile
#: registered to itself): below it the tile has too little structure, or structure that differs between the two
#: illuminants.
MIN_PEAK_SHARE = 0.3

#: A tile's velocity stands where at least this many frames besides the reference agree on it.
MIN_FRAMES = 3

#: A frame's correction of its global translation is taken where at least this many measured tiles were registered
#: in it (0 elsewhere, interpolated in time between the frames that have one).
MIN_TILES = 3


@dataclass
class TileMotion:
    """Each tile's velocity relative to the global translation.

    Attributes
    ----------
    centres : tuple of numpy.ndarray
        (rows, columns) of the tiles' centres, px.
    velocity : numpy.ndarray
        (ty, tx, 2) velocity (x, y) of each tile relative to the global translation, px per frame (filled from the
        nearest measured tile where not measured).
    measured : numpy.ndarray
        (ty, tx) bool: the tile's own frames gave its velocity.
    correction : numpy.ndarray
        (K, 2) what the measured tiles add to each frame's global translation (the median of their displacements
        less their own steady motion), px, from the reference frame.
    """

    centres: tuple
    velocity: np.ndarray
    measured: np.ndarray
    correction: np.ndarray


def tile_motion(gradients, shifts, reference_frame: int, usable, *, tile_px: int = TILE_PX,
                cutoff: float = 0.12) -> TileMotion:
    """The velocity of each tile of the reference frame relative to the global translation (steps 2 and 3 of the
    module notes).

    Parameters
    ----------
    gradients : sequence of (H, W) arrays
        Each frame's gradient image (None for a frame not registered).
    shifts : array_like, (K, 2)
        The global displacement of each frame from the reference time, px.
    reference_frame : int
        The frame the tiles are cut from.
    usable : array_like, (K,) bool
        The frames that can be registered.
    tile_px : int
        Tile side, px.
    cutoff : float
        Of the whitened cross-power spectrum's Gaussian weight (as the global estimate's).
    """
    shifts = np.asarray(shifts, np.float64)
    K = len(shifts)
    usable = np.asarray(usable, bool)
    if shifts.shape != (K, 2) or len(gradients) != K or usable.shape != (K,):
        raise ValueError(f"tile_motion needs one gradient image, one (dx, dy) shift and one usable flag per frame, "
                         f"got {len(gradients)} images, shifts of shape {shifts.shape}, {usable.size} flags")
    if not 0 <= int(reference_frame) < K or gradients[reference_frame] is None:
        raise ValueError(f"reference_frame {reference_frame} is not a frame with a gradient image of the {K}")
    g_ref = np.asarray(gradients[reference_frame], np.float32)
    h, w = g_ref.shape
    ty, tx = max(1, int(round(h / tile_px))), max(1, int(round(w / tile_px)))
    th, tw = h // ty, w // tx
    ref_tiles = g_ref[:ty * th, :tx * tw].reshape(ty, th, tx, tw).swapaxes(1, 2).reshape(-1, th, tw)
    F_ref = whitened_stack(ref_tiles, cutoff)
    # the peak of a tile registered to itself (the same for every tile with structure, whose whitened spectrum has
    # the weight's magnitude; 0 for a tile with none, a clipped patch, which is never measured)
    self_peak = fit_peaks(fft.irfft2(F_ref * np.conj(F_ref), s=(th, tw), axes=(-2, -1), workers=1))[1]
    y0 = (np.arange(ty) * th)[:, None].repeat(tx, 1).reshape(-1)
    x0 = (np.arange(tx) * tw)[None, :].repeat(ty, 0).reshape(-1)
    n = ty * tx
    t = np.arange(K, dtype=np.float64) - reference_frame
    relative = np.full((K, n, 2), np.nan)  # each tile's displacement relative to the global one, from the reference
    velocity = np.zeros((n, 2))
    order = sorted((k for k in range(K) if usable[k] and k != reference_frame), key=lambda k: (abs(t[k]), k))
    for k in order:
        g_k = np.asarray(gradients[k], np.float32)
        # where the global motion and the tile's velocity so far put the tile in frame k
        guess = (shifts[k] - shifts[reference_frame])[None, :] + velocity * t[k]
        offset = np.rint(guess).astype(int)
        ys, xs = y0 + offset[:, 1], x0 + offset[:, 0]
        inside = (ys >= 0) & (xs >= 0) & (ys + th <= h) & (xs + tw <= w)
        if not inside.any():
            continue
        idx = np.flatnonzero(inside)
        moving = np.stack([g_k[ys[i]:ys[i] + th, xs[i]:xs[i] + tw] for i in idx])
        surfaces = fft.irfft2(whitened_stack(moving, cutoff) * np.conj(F_ref[idx]), s=(th, tw), axes=(-2, -1),
                              workers=1)
        d, top = fit_peaks(surfaces)
        strong = (self_peak[idx] > 0) & (top >= MIN_PEAK_SHARE * self_peak[idx])
        rel = offset[idx] + d - (shifts[k] - shifts[reference_frame])[None, :]
        relative[k, idx[strong]] = rel[strong]
        velocity = _implied_median(relative, t)  # robust to a peak a texture's period off in an early frame
    fitted, measured, correction = _steady(relative, t)
    grid = np.zeros((ty, tx, 2))
    grid.reshape(n, 2)[measured] = fitted[measured]
    measured = measured.reshape(ty, tx)
    if measured.any() and not measured.all():  # the nearest measured tile's
        _, (iy, ix) = ndimage.distance_transform_edt(~measured, return_indices=True)
        grid = grid[iy, ix]
    # each tile's velocity with its neighbours' (a 3 x 3 median: a tile's own is noisy to a few tenths of a px per
    # frame; the median keeps a linear field, a rotation's or a zoom's, and a step between two motions)
    grid = np.stack([ndimage.median_filter(grid[..., c], size=3, mode="nearest") for c in range(2)], axis=-1)
    # where the tiles' centres (cut from the reference frame) are at the reference time, the field's time: moved
    # back by the reference frame's global displacement (each tile's own motion over that time, under a pixel per
    # frame of it for a reference frame next to the middle, is left out: the grid stays regular)
    dx, dy = shifts[reference_frame]
    centres = (np.arange(ty) * th + (th - 1) / 2.0 - dy, np.arange(tx) * tw + (tw - 1) / 2.0 - dx)
    return TileMotion(centres, grid, measured, correction)


def _implied_median(relative: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 2): each tile's median over its registered frames of its displacement over its time from the reference
    frame (0 where none is registered)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        implied = relative / np.where(t != 0, t, np.nan)[:, None, None]
    out = np.zeros(implied.shape[1:])
    some = np.isfinite(implied[..., 0]).any(axis=0)
    if some.any():
        out[some] = np.nanmedian(implied[:, some], axis=0)
    return out


def _fit_velocities(relative: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 2) velocity of each tile from the frames registered so far (least squares through the reference frame,
    whose relative displacement is 0 by construction; 0 where none is)."""
    have = np.isfinite(relative[..., 0])  # (K, N)
    tt = np.where(have, t[:, None], 0.0)
    num = np.nansum(relative * tt[..., None], axis=0)
    den = np.sum(tt * tt, axis=0)
    return np.where(den[:, None] > 0, num / np.maximum(den, 1e-30)[:, None], 0.0)


def _steady(relative: np.ndarray, t: np.ndarray, rounds: int = 3) -> tuple:
    """Each tile's steady velocity and each frame's correction of the global translation, fitted together:
    ``relative`` (K, N, 2) = velocity_n t_k + correction_k, robustly. A tile's velocity starts from the median of
    its frames' implied velocities and is fitted to the frames within :data:`STEADY_PX` of that line; a frame's
    correction is the median over the measured tiles (those with at least :data:`MIN_FRAMES` such frames) of
    what their velocities leave. A frame whose global translation is off by more than :data:`STEADY_PX` (a
    rotation's whole-image correlation, which no translation fits) is then corrected rather than dropped by every
    tile. Returns (N, 2) velocities, (N,) bool ``measured``, (K, 2) corrections (0 at the reference frame)."""
    K, n, _ = relative.shape
    finite = np.isfinite(relative[..., 0])
    correction = np.zeros((K, 2))
    velocity, measured = np.zeros((n, 2)), np.zeros(n, bool)
    for _ in range(rounds):
        adjusted = relative - correction[:, None, :]
        start = _implied_median(adjusted, t)
        keep = np.abs(adjusted - start[None] * t[:, None, None]).max(axis=2) <= STEADY_PX  # NaN: False
        velocity = _fit_velocities(np.where(keep[..., None], adjusted, np.nan), t)
        keep = np.abs(adjusted - velocity[None] * t[:, None, None]).max(axis=2) <= STEADY_PX
        measured = keep.sum(axis=0) >= MIN_FRAMES
        left = relative - velocity[None] * t[:, None, None]
        have = np.array([(measured & finite[k]).sum() >= MIN_TILES for k in range(K)])
        for k in np.flatnonzero(have):
            correction[k] = np.median(left[k, measured & finite[k]], axis=0)
        anchor = t == 0  # the reference frame: the tiles were cut from it, its correction is 0 by definition
        correction[anchor] = 0.0
        have |= anchor
        if not have.all():  # a frame no measured tile was registered in: interpolated in time (its global shift was)
            for c in range(2):
                correction[~have, c] = np.interp(np.flatnonzero(~have), np.flatnonzero(have), correction[have, c])
    return velocity, measured, correction


def flow_field(motion: TileMotion, shifts, shape: tuple) -> np.ndarray:
    """(K, 2, H, W) float32 displacement of each pixel in each frame from the reference time: the global
    ``shifts`` (K, 2) with the tiles' correction, plus the tiles' velocities (interpolated bilinearly between their
    centres) times each frame's time from the reference time (the mean of the frames' indices)."""
    h, w = shape
    shifts = np.asarray(shifts, np.float64)
    K = len(shifts)
    if shifts.shape != (K, 2) or np.shape(motion.correction) != (K, 2):
        raise ValueError(f"flow_field needs (K, 2) shifts and the tiles' (K, 2) correction of the same K, got "
                         f"{shifts.shape} and {np.shape(motion.correction)}")
    (cy, cx), grid = motion.centres, motion.velocity
    yy = (np.arange(h) - cy[0]) / (cy[1] - cy[0]) if len(cy) > 1 else np.zeros(h)
    xx = (np.arange(w) - cx[0]) / (cx[1] - cx[0]) if len(cx) > 1 else np.zeros(w)
    coords = np.meshgrid(yy, xx, indexing="ij")
    v = np.stack([ndimage.map_coordinates(grid[..., c], coords, order=1, mode="nearest") for c in range(2)])
    t = np.arange(K, dtype=np.float64) - (K - 1) / 2.0
    c = np.asarray(motion.correction, np.float64)
    shifts = shifts + c - at_reference_time(c)
    out = np.empty((K, 2, h, w), np.float32)
    for k in range(K):
        out[k] = v * np.float32(t[k])
        out[k] += shifts[k].astype(np.float32)[:, None, None]
    return out


def choose_flow(mask, maps, mask_flow, flow_maps, held, *, threshold: float, inconsistent: int,
                margin: float = 0.2) -> np.ndarray:
    """(H, W) bool: the pixels decoded with the flow rather than the global motion (or an object layer's).

    Under the flow a pixel is consistent where its frames agree (``worst`` >= ``threshold``, ``flow_maps``; 1 where
    no frame has structure of its own) and its pass flagged nothing (``mask_flow``: its residual included). It takes
    the flow there where the global decoding is flagged inconsistent (``mask`` bit ``inconsistent``), has no texture, or
    is not better correlated by more
    than ``margin`` (``maps``: the global check's). A pixel an object layer decoded (``held``) takes it only on
    positive evidence, its frames textured and agreeing under the flow: a layer's translation is right for an object
    that moves as one, and keeps its flat parts, which no check can judge; a part of the scene that turns or
    deforms is taken by the flow where it shows."""
    textured_g, worst_g = maps
    textured_f, worst_f = flow_maps
    agree = worst_f >= threshold
    consistent = agree & (mask_flow == 0)
    flagged = (mask & np.uint8(inconsistent)) != 0
    better = ~textured_g | (textured_f & (worst_f >= worst_g - margin))
    return consistent & (~held | (textured_f & agree)) & (flagged | better)
