"""An object moving on its own over a scene whose global motion is compensated: where the flagged pixels of a
global decoding gather (:func:`flagged_regions`), the object's own translation per frame
(:func:`estimate_layer_motion`), its footprint (:func:`object_footprint`) and the background it covers
(:func:`occluded_by`). The decoding with that motion, and what it changes in a recovery, is the pipeline's
(:mod:`specgpu.pipeline.moving_layers`).

The object's translation per frame is registered on the frames' gradient images restricted to the region (the
whitened cross-power of the region of the reference frame against each frame: the highest correlation peaks away
from the background's displacement, refined to sub-pixel by a Gaussian fit, are the candidates, and the steady
motion most frames' candidates agree on, up to :data:`MAX_LAYER_SPEED_PX` per frame, is the object's).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.morphology import convex_hull_image

from specgpu.motion.registration import correlation_surface, peak_at
from specgpu.motion.whitening import whitened_half_spectrum

__all__ = ["MIN_LAYER_SHARE", "JOIN_PX", "MIN_SEPARATION_PX", "MIN_PEAK_SHARE", "MAX_LAYER_SPEED_PX", "CANDIDATES",
           "STEADY_TOLERANCE_PX", "flagged_regions", "object_footprint", "occluded_by", "estimate_layer_motion"]

#: A flagged region is tried as an object when it holds at least this share of the field's pixels.
MIN_LAYER_SHARE = 0.002

#: Flagged pixels closer than this (px) belong to one region (an object's textured parts are separated by its
#: flat ones).
JOIN_PX = 12

#: The object's peak must be at least this far (px) from the background's displacement to be a motion of its own,
#: and at least this share of the background's peak height.
MIN_SEPARATION_PX = 1.0
MIN_PEAK_SHARE = 0.2

#: The fastest motion of an object relative to the background (px per frame) a layer is made for. A repeating
#: texture (a chart's patches) moving too slowly for its own peak to leave the background's offers peaks one period
#: off in every frame, which a steady motion of a period per frame also explains and the check cannot refute (the
#: patches' edges line up a period off): on the twin's chart that period is 22 px and more. Faster objects stay as
#: the global check leaves them, flagged where their frames disagree.
MAX_LAYER_SPEED_PX = 12.0

#: Correlation peaks tried per frame as the object's, highest first.
CANDIDATES = 3

#: A frame's peak agrees with a steady motion of the object (relative to the background) within this, px.
STEADY_TOLERANCE_PX = 1.0



def flagged_regions(flagged, *, min_share: float = MIN_LAYER_SHARE, join_px: int = JOIN_PX,
                    max_regions: int = 2) -> list:
    """The regions of the (H, W) bool ``flagged`` map worth a layer: flagged pixels within ``join_px`` of each
    other joined, regions holding at least ``min_share`` of the field's pixels flagged, largest first, at most
    ``max_regions``; each an (H, W) bool mask (the joined region)."""
    flagged = np.asarray(flagged, bool)
    if not flagged.any():
        return []
    # within join_px steps of a flag (4-connected): the dilation iterated join_px times with the cross, made in one
    # two-pass city-block distance transform instead of join_px passes over the field
    joined = ndimage.distance_transform_cdt(~flagged, metric="taxicab") <= int(join_px)
    labels, n = ndimage.label(joined)
    counts = np.bincount(labels[flagged], minlength=n + 1)[1:].astype(np.float64)  # each region's flags
    order = np.argsort(counts)[::-1]
    minimum = float(min_share) * flagged.size
    return [labels == (i + 1) for i in order[:max_regions] if counts[i] >= minimum]


def object_footprint(seed, *, min_pixels: int = 16, reach_px: float = 20.0) -> np.ndarray:
    """(H, W) bool: where the object is at the reference time, from ``seed`` (its pixels whose frames positively
    agree under its motion: textured ones, such as the edges of its patches, which are sparse, since an object's
    flat parts carry no texture to agree on): the convex hull of the seed's pieces of at least ``min_pixels``, within
    ``reach_px`` of them (a concave object's hull spans background). A background pixel the footprint takes in is
    decoded with the object's motion, which samples other background points (never the object), and the check
    still flags it where they differ in texture."""
    labels, n = ndimage.label(seed)
    sizes = ndimage.sum_labels(seed, labels, index=np.arange(1, n + 1))
    kept = np.isin(labels, 1 + np.flatnonzero(sizes >= min_pixels))
    if not kept.any():
        return kept
    near = ndimage.distance_transform_edt(~kept) <= reach_px
    return convex_hull_image(kept) & near


def occluded_by(footprint, relative) -> np.ndarray:
    """(H, W) bool: pixels outside ``footprint`` (the object at the reference time) that the object covered in some
    frame: frame k saw background point x at x + b_k and the object's point at p + o_k, so x is hidden where it lies
    in the footprint moved by ``relative[k]`` = o_k - b_k (a partly covered pixel counts)."""
    F = np.asarray(footprint, np.float32)
    hidden = np.zeros(F.shape, bool)
    for dx, dy in np.asarray(relative, np.float64):
        hidden |= ndimage.shift(F, (dy, dx), order=1, mode="constant", cval=0.0) > 1e-3
    return hidden & ~np.asarray(footprint, bool)


def estimate_layer_motion(gradients, region, background, reference_frame: int, usable, *, cutoff: float = 0.12,
                          margin: int = 16):
    """The object's displacement per frame relative to the reference frame, or None where none stands out; and the
    box registered.

    In each frame the highest correlation peaks away from the background's are the object's candidates; the object
    is taken to move steadily relative to the background over one sequence, so the candidates most frames agree on
    are its (:func:`_steady_motion`), and a frame none of whose peaks agrees (the object too close to the background's
    displacement there, a dim frame) takes the steady motion's displacement.

    Parameters
    ----------
    gradients : sequence of (H, W) arrays
        Each frame's gradient image (:func:`specgpu.motion.images.gradient_image`; None for a frame not used).
    region : (H, W) bool
        The flagged region the object is in (at the reference time).
    background : (K, 2)
        The global displacement of each frame (its relative displacements are excluded from the object's peak).
    reference_frame : int
    usable : (K,) bool
        Frames to register (the others are filled in time).
    """
    K = len(gradients)
    h, w = gradients[reference_frame].shape
    ys, xs = np.nonzero(region)
    y0, y1 = max(int(ys.min()) - margin, 0), min(int(ys.max()) + 1 + margin, h)
    x0, x1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + 1 + margin, w)
    box = (y0, y1, x0, x1)
    weight = ndimage.gaussian_filter(region[y0:y1, x0:x1].astype(np.float32), 2.0)
    ref = whitened_half_spectrum(gradients[reference_frame][y0:y1, x0:x1] * weight, cutoff)
    ch, cw = y1 - y0, x1 - x0
    yy = np.fft.fftfreq(ch, 1.0 / ch)[:, None]
    xx = np.fft.fftfreq(cw, 1.0 / cw)[None, :]
    background = np.asarray(background, np.float64)
    bg_rel = background - background[reference_frame]
    candidates = []  # (frame, displacement relative to the background's, peak height)
    for k in np.flatnonzero(usable):
        if k == reference_frame:
            continue
        c = correlation_surface(ref, whitened_half_spectrum(gradients[k][y0:y1, x0:x1], cutoff), (ch, cw))
        # the surface peaks at the displacement of each content: the background's where its displacement puts it,
        # and the object's among the highest other local maxima
        bx, by = bg_rel[k]
        near_bg = ((yy - by + ch / 2) % ch - ch / 2) ** 2 + ((xx - bx + cw / 2) % cw - cw / 2) ** 2 <= 2.25
        bg_peak = float(c[near_bg].max()) if near_bg.any() else 0.0
        peaks = (c == ndimage.maximum_filter(c, size=3, mode="wrap")) & ~near_bg & (c >= MIN_PEAK_SHARE * bg_peak)
        iy, ix = np.nonzero(peaks)
        for j in np.argsort(c[iy, ix])[::-1][:CANDIDATES]:
            r = peak_at(c, int(iy[j]), int(ix[j])) - bg_rel[k]
            if np.hypot(*r) >= MIN_SEPARATION_PX:
                candidates.append((int(k), r, float(c[iy[j], ix[j]])))
    relative = _steady_motion(candidates, reference_frame, K)
    if relative is None:
        return None, box
    return bg_rel + relative, box


def _steady_motion(candidates, reference_frame: int, K: int):
    """(K, 2) displacement of the object relative to the background in each frame, from the frames' candidate
    peaks: the velocity (px per frame, relative to the background) most frames' candidates agree with within
    :data:`STEADY_TOLERANCE_PX` (each candidate proposes one), refined by least squares over those; each agreeing
    frame keeps its own measurement, the others take the velocity's. None when fewer than two frames agree, or when
    the velocity is above :data:`MAX_LAYER_SPEED_PX`."""
    if not candidates:
        return None
    frames = np.array([k for k, _, _ in candidates])
    disp = np.array([r for _, r, _ in candidates])
    height = np.array([p for _, _, p in candidates])
    dt = (frames - reference_frame).astype(np.float64)
    best, best_score = None, (0, 0.0)
    for i in range(len(candidates)):
        v = disp[i] / dt[i]
        near = np.hypot(*(disp - v * dt[:, None]).T) <= STEADY_TOLERANCE_PX
        score = (len(set(frames[near].tolist())), float(height[near].sum()))
        if score > best_score:
            best, best_score = near, score
    if best is None or best_score[0] < 2:
        return None
    # one measurement per agreeing frame: its highest candidate near the fit
    v = np.linalg.lstsq(dt[best, None], disp[best], rcond=None)[0][0]
    if np.hypot(*v) > MAX_LAYER_SPEED_PX:
        return None  # faster than any layer is trusted with: likely a repeating texture one period off
    out = (np.arange(K) - reference_frame)[:, None] * v[None, :]
    for k in set(frames[best].tolist()):
        pick = np.flatnonzero(best & (frames == k))
        out[k] = disp[pick[np.argmax(height[pick])]]
    out[reference_frame] = 0.0
    return out


