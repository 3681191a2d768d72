"""Motion of a sequence from its broadband reference frames (a plan made with ``--reference-every M``).

A plan's reference frames (:func:`specgpu.planning.reference_frames.with_reference_frames`) are all lit by one
broadband pattern and spread over the sequence (before its first frame, after every M frames, after its last).
:func:`estimate_reference_motion` registers them to each other directly: each to the reference frame nearest the
sequence's middle, by phase correlation of their gradient images (whitened, sub-pixel by the Gaussian fit of
:mod:`specgpu.motion.registration`); two frames lit by the same spectrum show the same contrasts, so nothing but
noise and the motion tells them apart. The pattern frames are not registered at all: each takes the displacement
interpolated in time between the reference frames (a cubic spline through them, linear with two; exact for a
steady translation, and following a vibration as far as the reference frames sample it). An affine map per frame
is fitted to tiles of each reference frame and interpolated element by element (small rotations and zooms).

The displacements are returned from the sequence's reference time as :func:`specgpu.motion.global_motion.
estimate_global_motion` returns them, the mean of all its frames' times (reference frames included), where the
twin's truth puts the scene: an interpolated motion is known at any time, so nothing ties the output to a
reference frame's own time. Each reference frame's translation is checked against its tiles (an object moving on
its own over the scene can take the whole-image correlation over), as the global estimate does where it sees a
rival peak.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline, interp1d

from specgpu.motion.affine import affine_to
from specgpu.motion.estimate import MotionEstimate, at_reference_time, one_blas_thread
from specgpu.motion.images import frame_gradients
from specgpu.motion.registration import correlation_surface, fit_peak, half_spectrum_energy, peak_error
from specgpu.motion.tiles import dominant_translation
from specgpu.motion.whitening import whitened_half_spectrum

__all__ = ["check_reference_frames", "estimate_reference_motion", "interpolate_in_time"]


def check_reference_frames(reference_frames, K: int) -> list[int]:
    """``reference_frames`` as sorted distinct frame indices of a sequence of ``K``: at least two (a motion needs
    two times), each in [0, K); a one-line ValueError otherwise."""
    try:
        idx = sorted({int(i) for i in reference_frames})
    except (TypeError, ValueError):
        raise ValueError(f"reference frames must be frame indices, got {reference_frames!r}") from None
    if len(idx) < 2 or idx[0] < 0 or idx[-1] >= K:
        raise ValueError(f"reference frames {idx} must be at least two frames of the sequence's {K}")
    return idx


def interpolate_in_time(times, values, at, kind: str = "cubic") -> np.ndarray:
    """``values`` (N, ...) known at ``times`` (N,) increasing, at the times ``at`` (K,): (K, ...). ``"cubic"``: a
    not-a-knot cubic spline (a parabola through three, linear through two; beyond the ends extrapolated by the end
    pieces); ``"linear"``: straight lines between neighbours (the end pieces beyond the ends)."""
    t = np.asarray(times, np.float64)
    v = np.asarray(values, np.float64)
    at = np.asarray(at, np.float64)
    if kind not in ("cubic", "linear"):
        raise ValueError(f"interpolation must be cubic or linear, got {kind!r}")
    if kind == "cubic" and t.size >= 3:
        return CubicSpline(t, v, axis=0, bc_type="not-a-knot", extrapolate=True)(at)
    return interp1d(t, v, axis=0, assume_sorted=True, fill_value="extrapolate")(at)


@one_blas_thread
def estimate_reference_motion(frames, reference_frames, dark=None, gain=None, *, model: str = "translation",
                              cutoff: float = 0.12, tiles: int = 4, upsample: int = 10, interpolation: str = "cubic",
                              robust: bool = True) -> MotionEstimate:
    """Each frame's displacement from the sequence's reference time, from its broadband reference frames only.

    Parameters
    ----------
    frames : array_like, (K, H, W)
        The raw frames of one sequence.
    reference_frames : sequence of int
        Indices of the frames lit by the one broadband pattern (at least two;
        :func:`specgpu.planning.reference_frames.reference_indices`).
    dark : array_like, (H, W) or (K, H, W), optional
    gain : array_like, (H, W), optional
        As :func:`specgpu.motion.global_motion.estimate_global_motion`.
    model : {"translation", "affine"}
    cutoff, tiles, upsample
        As :func:`~specgpu.motion.global_motion.estimate_global_motion` (``upsample``: the affine tiles' peaks).
    robust : bool
        Translation model: check each reference frame's whole-image translation against its ``tiles`` x ``tiles``
        tiles and take their consensus where they disagree (an object moving on its own). Always, not only where
        the correlation shows a rival peak as in the global estimate: reference frames lie several frames apart,
        so such an object has moved further from the background between them and its peak can take the whole
        image over without a rival (a chart of a fifth of the field, 3 px/frame, two reference frames 8 frames
        apart); with a few reference frames the tiles cost little.
    interpolation : {"cubic", "linear"}
        How the pattern frames' displacements follow from the reference frames' (:func:`interpolate_in_time`;
        the frames are one frame period apart, as a plan runs them).

    Returns
    -------
    MotionEstimate
        ``registered`` True at the reference frames only; ``reference_frame`` the reference frame the others were
        registered to; ``gradients`` the reference frames' gradient images (None for the others).
    """
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (K, H, W), got shape {frames.shape}")
    K = frames.shape[0]
    refs = check_reference_frames(reference_frames, K)
    if model not in ("translation", "affine"):
        raise ValueError(f"model must be translation or affine with reference frames, got {model!r}")
    mid = (K - 1) / 2.0
    centre = min(refs, key=lambda k: (abs(k - mid), k))  # the reference frame nearest the middle of the sequence
    kept = tuple(frame_gradients(frames, dark, gain, which=refs))
    gradients = {k: kept[k] for k in refs}
    shape = gradients[centre].shape
    spectra = {k: whitened_half_spectrum(gradients[k], cutoff) for k in refs}
    energy = {k: half_spectrum_energy(spectra[k], shape[1]) for k in refs}
    raw = np.zeros((len(refs), 2))
    error = np.full(K, np.nan)
    for i, k in enumerate(refs):
        if k == centre:
            continue
        surface = correlation_surface(spectra[centre], spectra[k], shape)
        d, top = fit_peak(surface)
        raw[i] = d
        error[k] = peak_error(top, energy[centre], energy[k], surface.size)
    error[centre] = float(np.nanmean(error[refs]))  # the mean of its registrations, as the global estimate's
    registered = np.zeros(K, bool)
    registered[refs] = True
    times = np.asarray(refs, np.float64)
    every = np.arange(K, dtype=np.float64)
    if model == "translation":
        if robust:  # a second motion over the scene: each reference frame's tiles decide
            cache: dict = {}
            for i, k in enumerate(refs):
                if k != centre:
                    raw[i] = dominant_translation(gradients[centre], gradients[k], raw[i], upsample, cutoff, tiles,
                                                  cache)
        shifts = interpolate_in_time(times, raw, every, interpolation)
        return MotionEstimate(shifts - at_reference_time(shifts), registered, error, int(centre), model, kept)
    maps = np.tile(np.eye(3), (len(refs), 1, 1))
    for i, k in enumerate(refs):
        if k != centre:
            maps[i] = affine_to(gradients[centre], gradients[k], raw[i], upsample, cutoff, tiles)
    maps = interpolate_in_time(times, maps, every, interpolation)
    maps[:, 2] = (0.0, 0.0, 1.0)
    to_mid = np.linalg.inv(at_reference_time(maps))
    return MotionEstimate((maps @ to_mid)[:, :2, :], registered, error, int(centre), model, kept)
