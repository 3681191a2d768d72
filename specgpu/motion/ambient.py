"""Where a sequence's ambient frame saw the scene: a frame the motion cannot be registered on, placed by the motion
of the others.

A plan made with ``plan --ambient`` has one frame per sequence with every mirror off
(:func:`specgpu.planning.correction.with_ambient_frame`): it holds the room light alone, no projector light, so it
shares no contrasts with the pattern frames and cannot be registered to them. A motion-compensated decoding still
needs where it saw each pixel, since its sample is subtracted from every pattern frame's. Within one sequence (tens
of milliseconds) a scene moves steadily: :func:`place_frame` fits one velocity to the registered frames'
displacements (for an affine map, each of its six parameters linear in time) and evaluates it at the ambient frame's
time; the flow's tiles then carry their own steady motion to that time as to any frame
(:func:`specgpu.motion.flow.flow_field`).

Where the registered frames do not follow a steady motion (a vibration, a jolt), the fitted line's largest departure
from them (``misfit``, px) says how far the ambient frame may lie from where it was put. That matters only where the
ambient frame has structure at that scale: :func:`misplaced` finds those pixels, which the decoder flags rather than
decode with an ambient sample taken from the wrong place.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy import ndimage

from specgpu.motion.estimate import MotionEstimate, at_reference_time

__all__ = ["STEADY_PX", "place_frame", "misplaced", "at_frame"]

#: The ambient frame's placement is trusted where no registered frame departs from the fitted steady motion by more
#: than this (px): registration noise on the twin is a few hundredths of a pixel, and an ambient sample a quarter
#: pixel off differs from the right one by a quarter of the room light's step across an edge.
STEADY_PX = 0.25


def _corners(shape) -> np.ndarray:
    h, w = shape
    return np.array([[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [0.0, h - 1.0, 1.0], [w - 1.0, h - 1.0, 1.0]]).T


def place_frame(estimate: MotionEstimate, frames, K: int, at: int, shape) -> tuple[MotionEstimate, float]:
    """The motion of a sequence of ``K`` frames from the ``estimate`` of its frames ``frames`` (indices, in order:
    every frame but ``at``), with frame ``at``'s displacement the steady motion fitted to the registered frames.

    Parameters
    ----------
    estimate : MotionEstimate
        Of the frames ``frames`` alone (translation (N, 2) or affine (N, 2, 3)).
    frames : sequence of int
        Their indices in the sequence (their times, in frame periods).
    K : int
        The sequence's frames.
    at : int
        The frame placed (the ambient frame), not among ``frames``.
    shape : (int, int)
        (H, W) of the field (an affine map's departure is measured at its corners).

    Returns
    -------
    (MotionEstimate, float)
        The K frames' displacements from the sequence's reference time (the mean of all K frames' times, as the
        twin's truth puts the scene), frame ``at`` not ``registered`` and without a gradient image; and the
        ``misfit``: the largest departure (px) of a registered frame from the fitted steady motion.
    """
    frames = [int(k) for k in frames]
    if len(frames) != len(estimate.shifts) or at in frames or not 0 <= at < K or len(frames) != K - 1:
        raise ValueError(f"place_frame needs the estimate of every frame of the {K} but frame {at}, got "
                         f"{len(estimate.shifts)} displacements for frames {frames}")
    t = np.asarray(frames, np.float64)
    use = np.asarray(estimate.registered, bool)
    if use.sum() < 2:
        use = np.ones(len(t), bool)
    affine = estimate.model == "affine"
    d = np.asarray(estimate.shifts, np.float64)
    values = d.reshape(len(t), -1)
    # least squares of value = a + v t over the registered frames, each parameter on its own
    design = np.stack([np.ones(use.sum()), t[use]], axis=1)
    coef, *_ = np.linalg.lstsq(design, values[use], rcond=None)
    fitted = np.stack([np.ones(len(t)), t], axis=1) @ coef
    placed = (np.array([1.0, float(at)]) @ coef).reshape(d.shape[1:])
    if affine:  # the departure of each registered frame's map from the line, where it moves a corner most
        p = _corners(shape)
        diff = np.einsum("nij,jc->nic", (values - fitted).reshape(d.shape), p)[use]
    else:
        diff = (values - fitted)[use][:, :, None]
    misfit = float(np.sqrt((diff ** 2).sum(axis=1)).max()) if diff.size else 0.0
    full = np.empty((K, *d.shape[1:]))
    full[frames] = d
    full[at] = placed
    if affine:  # the maps from the sequence's reference time: composed with the inverse of the map there
        maps = np.tile(np.eye(3), (K, 1, 1))
        maps[:, :2, :] = full
        full = (maps @ np.linalg.inv(at_reference_time(maps)))[:, :2, :]
    else:
        full = full - at_reference_time(full)
    registered = np.zeros(K, bool)
    registered[frames] = estimate.registered
    error = np.full(K, np.nan)
    error[frames] = estimate.error
    gradients = None
    if estimate.gradients is not None:
        gradients = [None] * K
        for i, k in enumerate(frames):
            gradients[k] = estimate.gradients[i]
        gradients = tuple(gradients)
    return replace(estimate, shifts=full, registered=registered, error=error,
                   reference_frame=frames[int(estimate.reference_frame)], gradients=gradients), misfit


def at_frame(image, shifts, k: int) -> np.ndarray:
    """(H, W): ``image`` (H, W) read, nearest pixel, where frame ``k`` saw each pixel of the reference time
    (``shifts``: (K, 2) translations, (K, 2, 3) affine maps or a (K, 2, H, W) flow); a point outside the field takes
    the nearest pixel's value."""
    image = np.asarray(image)
    h, w = image.shape
    d = np.asarray(shifts, np.float64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    if d.shape[1:] == (2, 3):
        sx = d[k, 0, 0] * xx + d[k, 0, 1] * yy + d[k, 0, 2]
        sy = d[k, 1, 0] * xx + d[k, 1, 1] * yy + d[k, 1, 2]
    else:
        sx, sy = xx + d[k, 0], yy + d[k, 1]
    cols = np.clip(np.rint(sx), 0, w - 1).astype(np.intp)
    rows = np.clip(np.rint(sy), 0, h - 1).astype(np.intp)
    return image[rows, cols]


def misplaced(ambient, shifts, k: int, misfit: float) -> np.ndarray:
    """(H, W) bool: the pixels whose ambient sample may be wrong when the ambient frame ``k`` (``ambient``: its
    signal above the dark level, flat-fielded, (H, W)) may lie up to twice ``misfit`` px from where ``shifts`` put
    it: where, within that reach, its room light changes by more than three times its noise (the image smoothed by a
    one-pixel Gaussian; the noise from the median of its neighbouring pixels' differences, robust to its edges), or
    the field ends. None of them where the misfit is at most :data:`STEADY_PX`."""
    a = np.asarray(ambient, np.float64)
    if misfit <= STEADY_PX:
        return np.zeros(a.shape, bool)
    reach = max(1, math.ceil(2.0 * misfit))
    noise = 1.4826 * float(np.median(np.abs(np.diff(a, axis=1)))) / math.sqrt(2.0)
    smooth = ndimage.gaussian_filter(a, 1.0)
    size = 2 * reach + 1
    spread = ndimage.maximum_filter(smooth, size=size) - ndimage.minimum_filter(smooth, size=size)
    uncertain = spread > 3.0 * max(noise, 1e-6)
    # and within that reach of the field's edge: the frame may have seen the pixel outside it
    uncertain[:reach], uncertain[-reach:], uncertain[:, :reach], uncertain[:, -reach:] = True, True, True, True
    return at_frame(uncertain, shifts, k)
