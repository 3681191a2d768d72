"""The ``global``, ``affine`` and ``flow`` estimates registered on the OpenCL device, where the frames' gradient
images are made (:func:`specgpu.engine.registration.register_gradients`), with the host estimate's safety
(:mod:`specgpu.motion.global_motion`, which stays the reference and the path without a device).

One sequence:

1. its frames' gradient images on the device (:func:`specgpu.engine.gradients.gradient_images`; each frame's mean,
   from the same pass, says which frames have signal enough to register and picks the reference frame as the host
   does: :func:`~specgpu.motion.global_motion.usable_frames`, :func:`~specgpu.motion.global_motion.pick_reference`);
2. a coarse search of each frame's shift to the reference frame, then Gauss-Newton steps coarse to fine, all on the
   device. Where the coarse correlation has several peaks of nearly the same height (:data:`NEAR_TIE`: a scene that
   repeats itself, a chart's grid of patches) no peak is guessed: :func:`start_candidates` takes the one nearest
   the steady motion the frames nearer the reference (or the ``prior``) predict, and leaves the frame unregistered
   where none is clearly nearest;
3. a frame whose best peak lies on the edge of the search (a motion faster than ``MAX_SPEED_PX_PER_FRAME``) is
   searched again over the whole overlap; one still on its edge is not registered;
4. where the correlation of the first or the last frame with the reference has a rival peak (:func:`rival_peaks`,
   above the host's ``AMBIGUOUS_PEAK``: two motions, furthest apart there, or a repeating scene), each translation
   is replaced by its tiles' consensus, as the host checks it (:func:`field_translation`, the host's tiles on the
   device's gradient images read back): an object moving on its own over the scene cannot take the estimate over;
5. the frames not registered filled in time, and the displacements taken from the sequence's reference time.

The gradient images read back are kept with the estimate (``MotionEstimate.gradients``), as the host's, for the
consistency check and the object layers.
"""

from __future__ import annotations

import numpy as np
from scipy import fft

from specgpu.engine.gradients import frames_on_device, launch_gradients
from specgpu.engine.registration import register_gradients
from specgpu.engine.runtime import get_queue
from specgpu.motion.estimate import MotionEstimate, at_reference_time, fill_in_time, one_blas_thread
from specgpu.motion.global_motion import (
    AMBIGUOUS_PEAK,
    MAX_SPEED_PX_PER_FRAME,
    GlobalOptions,
    pick_reference,
    usable_frames,
)
from specgpu.motion.images import device_takes
from specgpu.motion.registration import second_peak_ratio, tile_displacements
from specgpu.motion.tiles import OUTLIER_PX
from specgpu.motion.whitening import whitened_stack

__all__ = ["NEAR_TIE", "start_candidates", "rival_peaks", "field_translation", "estimate_on_device"]

#: Peaks of a frame's coarse correlation at least this share of its highest compete: the one nearest the predicted
#: shift is taken, not the highest. A grid of patches gives peaks a pitch apart within a few percent of each other
#: (the truth sometimes the lower); a natural scene's second local maximum is at most about half its first.
NEAR_TIE = 0.8

#: The pyramid level (a quarter of the resolution) whose images are read back for the rival-peak check: their
#: phase correlation separates two motions a few px apart, which the coarse search's level merges
CHECK_LEVEL = 2

#: The Gauss-Newton steps at full resolution sum every n-th band of rows, n the frames' height over this (at least 1;
#: bands of whole rows, :func:`~specgpu.engine.registration.register_gradients`' ``full_rows``): each step is a pass
#: over the frames, and 240 rows of a 640 x 480 frame register as closely as its 480 (0.04-0.07 px from the twin's
#: truth either way) in two thirds of the time, while at 320 x 240 every row counts (half of them: 0.08-0.14 px, all
#: 0.03-0.11)
FULL_ROWS_SUMMED = 240

#: The predicted shift singles a candidate out where the next nearest is at least this many times as far from it.
CLEARLY_NEAREST = 2.0


def start_candidates(candidates, gaps, prior=None) -> np.ndarray:
    """Where each frame's refinement starts: its highest coarse peak, or, where peaks of nearly the same height
    compete (:data:`NEAR_TIE`), the one nearest the predicted shift, or NaN (not registered) where none is clearly
    nearest (:data:`CLEARLY_NEAREST`).

    The prediction is a steady motion: ``prior`` (px per frame; zero without one) times the frame's distance from
    the reference, for the frames nearest the reference; then the velocity the frames taken so far share (least
    squares through the reference), frames taken in order of their distance from the reference.

    Parameters
    ----------
    candidates : sequence of numpy.ndarray
        Per frame (reference excluded), (N, 3) rows of (x, y, height), highest first
        (:attr:`specgpu.engine.registration.DeviceRegistration.candidates`).
    gaps : array_like of int
        Per frame, its signed distance in frames from the reference.
    prior : array_like, (2,), optional
        The velocity expected, px per frame (a stream's previous sequence's).

    Returns
    -------
    numpy.ndarray
        (F, 2) each frame's starting shift, NaN rows where no candidate is clearly the one.
    """
    gaps = np.asarray(gaps, np.float64)
    velocity = np.zeros(2) if prior is None else np.asarray(prior, np.float64).reshape(2)
    out = np.full((len(candidates), 2), np.nan)
    taken_g, taken_d = [], []
    for j in np.argsort(np.abs(gaps), kind="stable"):
        c = np.asarray(candidates[j], np.float64).reshape(-1, 3)
        if not len(c):
            continue
        near = c[c[:, 2] >= NEAR_TIE * c[0, 2]] if c[0, 2] > 0 else c[:1]
        if len(near) == 1:
            out[j] = near[0, :2]
        else:
            distance = np.hypot(*(near[:, :2] - velocity * gaps[j]).T)
            order = np.argsort(distance)
            if distance[order[1]] < CLEARLY_NEAREST * distance[order[0]]:
                continue  # no peak singled out: not registered, filled in time
            out[j] = near[order[0], :2]
        taken_g.append(gaps[j])
        taken_d.append(out[j])
        g = np.asarray(taken_g)
        velocity = (g[:, None] * np.asarray(taken_d)).sum(axis=0) / float((g * g).sum())
    return out


def rival_peaks(images: np.ndarray, reference_frame: int, which, scale: float,
                max_speed: float | None = MAX_SPEED_PX_PER_FRAME) -> np.ndarray:
    """(K,) each frame's second correlation peak over its first (0 for the others), by the host's whitened phase
    correlation (:func:`~specgpu.motion.registration.second_peak_ratio`) of small images ``images`` (K, h, w) at
    1 / ``scale`` of the resolution, peaks sought within reach of ``max_speed`` px per frame: what says whether
    two motions compete. (The device's correlation of the gradient images themselves, not whitened, is led by the
    strongest edges: a chart's over the scene's.) The surfaces are made together (one inverse FFT of the stack) and
    each peak taken at its highest sample: the ratio compares samples."""
    options = GlobalOptions()
    radius, (K, h, w) = options.radius, images.shape
    out = np.zeros(K)
    others = [int(k) for k in which if k != reference_frame]
    if not others:
        return out
    spectra = whitened_stack(images[[reference_frame, *others]], options.cutoff)
    surfaces = fft.irfft2(spectra[1:] * np.conj(spectra[:1]), s=(h, w), axes=(-2, -1), workers=1)
    for k, surface in zip(others, surfaces):
        within = None if max_speed is None else int(np.ceil(max_speed * abs(k - reference_frame) / scale)) + radius
        r = np.arange(-min(within, h // 2), min(within, h // 2) + 1) if within is not None else np.arange(h) - h // 2
        c = np.arange(-min(within, w // 2), min(within, w // 2) + 1) if within is not None else np.arange(w) - w // 2
        i, j = np.unravel_index(int(np.argmax(surface[np.ix_(r % h, c % w)])), (len(r), len(c)))
        out[k] = second_peak_ratio(surface, np.array([c[j], r[i]], np.float64), radius, within)
    return out


def field_translation(g_ref: np.ndarray, g_k: np.ndarray, shift, reference_tiles: dict, tiles: int = 4) -> np.ndarray:
    """The translation most of the field shares: the mean of the ``tiles`` x ``tiles`` tiles' displacements within
    :data:`~specgpu.motion.tiles.OUTLIER_PX` of their median (the tiles registered by the host's phase correlation
    where ``shift`` puts them, again where their median puts them if it lies a pixel or more away), ``shift``
    where fewer than three tiles register. The device's registration sums over the whole field, so an object
    moving on its own pulls it by a fraction of a pixel; the tiles' consensus does not follow the object."""
    shift = np.asarray(shift, np.float64)
    src, dst = tile_displacements(g_ref, g_k, shift, GlobalOptions().cutoff, tiles, reference_tiles)
    if len(src) < 3:
        return shift
    d = dst - src
    med = np.median(d, axis=0)
    if np.any(np.rint(med) != np.rint(shift)):  # again where the tiles overlap fully: each peak more accurate
        src, dst = tile_displacements(g_ref, g_k, med, GlobalOptions().cutoff, tiles, reference_tiles)
        if len(src) >= 3:
            d = dst - src
            med = np.median(d, axis=0)
    near = np.abs(d - med).max(axis=1) <= OUTLIER_PX
    return d[near].mean(axis=0) if near.sum() >= 3 else med


@one_blas_thread
def estimate_on_device(frames, dark=None, gain=None, *, model: str = "translation", reference_frame: int | None = None,
                       prior=None, upsample: int = 10, robust: bool = True, device=None) -> MotionEstimate | None:
    """A translation or an affine map per frame of one sequence, registered on the device (see the module's
    docstring); None where the device cannot take the inputs as they are
    (:func:`~specgpu.motion.images.device_takes`: the host estimate then runs).

    Parameters
    ----------
    frames : array_like, (K, H, W)
        The raw frames of one sequence (uint8, uint16 or float).
    dark : array_like, (H, W) or (K, H, W), optional
        Dark level subtracted before registration.
    gain : array_like, (H, W), optional
        Flat field applied before registration.
    model : {"translation", "affine"}
        A translation per frame, or an affine map per frame.
    reference_frame : int, optional
        The frame the others are registered to (default: the brightest of the middle three).
    prior : array_like, (2,), optional
        The velocity expected, px per frame (the previous sequence's in a stream): where peaks compete, the one
        it predicts is taken (:func:`start_candidates`).
    upsample : int
        Not used (the tiles' peaks are fitted): the keyword of the host's estimate.
    robust : bool
        Translations: check each against its tiles where some frame's correlation has a rival peak.
    device : optional
        OpenCL device selector or queue.

    Returns
    -------
    MotionEstimate or None
        As :func:`~specgpu.motion.global_motion.estimate_global_motion`'s, ``gradients`` every frame's gradient
        image; ``error`` ``sqrt(1 - r^2)`` of the correlation coefficient of the reference and the registered frame.
    """
    if model not in ("translation", "affine"):
        raise ValueError(f"model must be one of translation, affine, got {model!r}")
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (K, H, W), got shape {frames.shape}")
    dark = None if dark is None else np.asarray(dark, np.float32)
    if not device_takes(frames, dark, gain) or min(frames.shape[1:]) < 8:
        return None
    queue = get_queue(device)
    # the magnitudes registered unscaled (a gain per frame is solved with each step): each frame's 1 / mean is
    # applied to the images read back, not in another pass on the device
    images, scale = launch_gradients(queue, frames_on_device(queue, frames), dark, gain)
    scale = scale.get(queue=queue)
    levels = 1.0 / scale.astype(np.float64)  # each frame's mean signal (1: none)
    usable = usable_frames(np.where(levels == 1.0, 0.0, levels))
    ref = pick_reference(levels, usable, reference_frame)

    def choose(candidates, gaps):
        return start_candidates(candidates, gaps, prior)

    check = CHECK_LEVEL if min(frames.shape[1:]) >= 4 * 48 else 1
    rows = max(1, frames.shape[1] // FULL_ROWS_SUMMED)
    speed = MAX_SPEED_PX_PER_FRAME
    reg = register_gradients(images, ref, model=model, max_speed=speed, choose=choose, keep_level=check,
                             full_rows=rows, device=queue)
    if (reg.edge & usable).any():  # a motion faster than the reach: searched over the whole overlap
        speed = None
        reg = register_gradients(images, ref, model=model, max_speed=None, choose=choose, keep_level=check,
                                 full_rows=rows, device=queue)
    read = images.get(queue=queue)
    read *= scale[:, None, None]  # float32 products, as the device's gradient_images makes them
    gradients = tuple(read)
    if not reg.usable[ref]:  # the reference has no structure: nothing registered, no motion made up
        none = np.zeros(len(frames), bool)
        shifts = np.tile(np.eye(3)[:2], (len(frames), 1, 1)) if model == "affine" else np.zeros((len(frames), 2))
        return MotionEstimate(shifts, none, np.full(len(frames), np.nan), ref, model, gradients)
    usable = usable & reg.usable & ~reg.edge
    maps = np.where(usable[:, None, None], reg.to_reference, np.nan)
    if model == "affine":
        filled = fill_in_time(maps, usable)
        shifts = (filled @ np.linalg.inv(at_reference_time(filled)))[:, :2, :]
        return MotionEstimate(shifts, usable, np.where(usable, reg.error, np.nan), ref, "affine", gradients)
    raw = maps[:, :2, 2].copy()
    # the frames at either end of the sequence, where two motions lie furthest apart, say whether they compete
    ends = np.flatnonzero(usable)[[0, -1]]
    if robust and rival_peaks(reg.level, ref, ends, 2.0 ** check, speed).max() > AMBIGUOUS_PEAK:
        reference_tiles: dict = {}
        for k in np.flatnonzero(usable):
            if k != ref:
                raw[k] = field_translation(gradients[ref], gradients[k], raw[k], reference_tiles)
    raw = fill_in_time(raw, usable)
    return MotionEstimate(raw - at_reference_time(raw), usable, np.where(usable, reg.error, np.nan), ref,
                          "translation", gradients)
