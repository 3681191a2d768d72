"""Motion of a scene during a sequence, estimated on the host, and the motion-compensated recovery it drives.

A sequence takes K frame periods; anything that moves in that time lands on different pixels in different frames.
**Global** motion (the scene or the camera translates, shakes on its tripod) is one displacement per frame. It is
estimated here by phase correlation (``skimage.registration.phase_cross_correlation``, sub-pixel by its upsampled
DFT) between each frame and a reference frame of the same sequence, on images that do not depend on the light's
spectrum: the gradient magnitude of each dark-subtracted, flat-fielded frame normalised by its mean. Edges stay
where they are whatever the illuminant, while the relative brightness of two surfaces does not; the gradient
magnitude keeps the first and discards the sign of the second, and phase correlation whitens what is left. So no
extra frame is needed and the latency is the sequence itself. (Registering a frame with the same pattern's frame of
the previous sequence also avoids the spectrum, but the sensor's fixed pattern, still on the sensor while the
scene moves, then pulls the estimate to zero, and a vibration near the sequence rate is invisible at lag K.)

The displacements are taken relative to the sequence's reference time, the mean of its frames' times (the middle
frame's time for odd K), which is where the twin's truth puts the scene
(``TwinRig.motion_truth``). The decoder then samples frame k at x + d_k in the same device pass
(:func:`specgpu.engine.warp_map.apply_linear_warped`); pixels some frame saw outside the field are NaN and flagged.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import fft, ndimage
from skimage.registration import phase_cross_correlation

from specgpu.core.validate import validate_method
from specgpu.engine.warp_map import apply_linear_warped
from specgpu.io.npz import write_cube_npz
from specgpu.rig.twin import TwinRig

__all__ = ["MOTION_MODES", "MotionEstimate", "MovingRecovery", "check_motion_mode", "estimate_global_motion",
           "recover_moving", "registration_image", "truth_recorder", "TRUTH_FOLDER"]

#: How frames are decoded with respect to motion: as they are, or compensated for a global translation per frame.
MOTION_MODES = {
    "none": "decode every pixel's samples where they are (a still scene)",
    "global": "estimate a translation per frame (phase correlation of gradient images) and sample frame k at x + d_k",
}

#: A frame whose mean signal is below this share of the brightest frame's is not registered (a dark or ambient
#: frame): its displacement is interpolated in time from the others.
MIN_SIGNAL_SHARE = 0.05

#: A pair's registration that disagrees by more than this (px) with the least-squares solution of all the others
#: is dropped (a failed correlation peak); with ``pairs="all"`` each frame is registered to up to 16 others.
OUTLIER_PX = 0.5


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
    """

    shifts: np.ndarray
    registered: np.ndarray
    error: np.ndarray
    reference_frame: int


def registration_image(frame, dark=None, gain=None, *, binning: int = 1) -> np.ndarray:
    """The spectrum-independent image a frame is registered on: gradient magnitude (Sobel) of the
    dark-subtracted, flat-fielded frame over its mean, under a Hann window (phase correlation assumes periodic
    images), float32; ``binning`` averages b x b pixels first (faster, coarser)."""
    f = np.asarray(frame, np.float32)
    if dark is not None:
        f = f - np.asarray(dark, np.float32)
    if gain is not None:
        f = f * np.asarray(gain, np.float32)
    if binning > 1:
        h, w = (f.shape[0] // binning) * binning, (f.shape[1] // binning) * binning
        f = f[:h, :w].reshape(h // binning, binning, w // binning, binning).mean(axis=(1, 3))
    mean = float(np.mean(f))
    f = f / mean if mean > 0 else f
    g = np.hypot(ndimage.sobel(f, 0), ndimage.sobel(f, 1))
    wy = np.hanning(g.shape[0]).astype(np.float32)
    wx = np.hanning(g.shape[1]).astype(np.float32)
    return g * wy[:, None] * wx[None, :]


def estimate_global_motion(frames, dark=None, gain=None, *, reference_frame: int | None = None,
                           upsample: int = 50, binning: int = 1, pairs: str = "all", cutoff: float = 0.12,
                           max_gap: int = 8) -> MotionEstimate:
    """A translation per frame of one sequence, relative to the sequence's reference time.

    Parameters
    ----------
    frames : array_like, (K, H, W)
        The raw frames of one sequence.
    dark : array_like, (H, W) or (K, H, W), optional
        Dark level subtracted before registration.
    gain : array_like, (H, W), optional
        Flat field applied before registration (the light's spot and the lens's falloff stay on the sensor; left
        in, they pull the estimate towards zero).
    reference_frame : int, optional
        The frame the others are registered to (default: the brightest of the middle three).
    upsample : int
        Sub-pixel resolution 1 / upsample px of the phase correlation peak.
    binning : int
        Average b x b pixels before registering (b times faster FFTs; the shifts are scaled back).
    cutoff : float
        Standard deviation (cycles per pixel) of the Gaussian weight on the spatial frequencies of the whitened
        cross-power spectrum.
    pairs : {"all", "reference"}
        Register every pair of frames at most ``max_gap`` apart and solve for the displacements by least squares
        (for K = 9, all 36 pairs: each frame's error averaged over 8 registrations), or each frame to the
        reference frame only (K - 1 registrations).
    max_gap : int
        The furthest apart (in frames) two frames registered with ``pairs="all"`` are.

    Returns
    -------
    MotionEstimate
        Each frame's displacement from the position at the reference time (the middle frame's for odd K, the mean
        of the middle two's for even K); a frame too dark to register (below :data:`MIN_SIGNAL_SHARE` of the
        brightest) is interpolated linearly in time.
    """
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (K, H, W), got shape {frames.shape}")
    K = frames.shape[0]
    upsample = int(upsample)
    if upsample < 1:
        raise ValueError(f"upsample must be >= 1, got {upsample}")
    dark = None if dark is None else np.asarray(dark, np.float32)
    per_frame_dark = dark is not None and dark.ndim == 3

    def dark_of(k):
        return None if dark is None else (dark[k] if per_frame_dark else dark)

    level = np.array([float(np.mean(frames[k], dtype=np.float64)) - (0.0 if dark is None else float(np.mean(dark_of(k))))
                      for k in range(K)])
    usable = level >= MIN_SIGNAL_SHARE * max(float(level.max()), 1e-30)
    if usable.sum() < 1:
        raise ValueError("no frame of the sequence has signal to register")
    if reference_frame is None:
        middle = [k for k in range(max(0, K // 2 - 1), min(K, K // 2 + 2)) if usable[k]]
        reference_frame = max(middle or list(np.flatnonzero(usable)), key=lambda k: level[k])
    if pairs not in ("all", "reference"):
        raise ValueError(f"pairs must be one of all, reference, got {pairs!r}")
    if not 0 <= reference_frame < K or not usable[reference_frame]:
        raise ValueError(f"reference_frame {reference_frame} is not a usable frame of the {K}")
    spectra = {}
    weight = None

    def spectrum(k):
        # phase only (whitened), weighted towards low spatial frequencies: a sub-pixel shift of a sampled image
        # is a linear phase only well below the Nyquist frequency (interpolation and the pixels' own footprint
        # bend it towards zero near it, which would bias the estimate towards no motion)
        nonlocal weight
        if k not in spectra:
            F = fft.fft2(registration_image(frames[k], dark_of(k), gain, binning=binning))
            if weight is None:
                fy = fft.fftfreq(F.shape[0])[:, None]
                fx = fft.fftfreq(F.shape[1])[None, :]
                weight = np.exp(-0.5 * (fx**2 + fy**2) / cutoff**2)
            spectra[k] = F / np.maximum(np.abs(F), 1e-30) * np.sqrt(weight)
        return spectra[k]

    idx = np.flatnonzero(usable)
    if pairs == "reference":
        links = [(reference_frame, int(k)) for k in idx if k != reference_frame]
    else:  # every pair up to max_gap frames apart: K - 1 unknowns from up to K (K - 1) / 2 measurements
        links = [(int(a), int(b)) for i, a in enumerate(idx) for b in idx[i + 1:] if b - a <= max_gap]
    rows, rhs, errs = [], [], {}
    for a, b in links:
        shift, err, _ = phase_cross_correlation(spectrum(a), spectrum(b), upsample_factor=upsample,
                                                normalization=None, space="fourier")
        row = np.zeros(K)
        row[b], row[a] = 1.0, -1.0
        rows.append(row)
        rhs.append(-np.asarray(shift[::-1], np.float64) * binning)  # (row, col) moving b onto a -> (x, y) of b - a
        errs.setdefault(a, []).append(float(err))
        errs.setdefault(b, []).append(float(err))
    raw = np.full((K, 2), np.nan)
    raw[reference_frame] = 0.0
    others = [int(k) for k in idx if k != reference_frame]
    if others:
        M, rhs = np.asarray(rows)[:, others], np.asarray(rhs)
        keep = np.ones(len(rows), bool)
        for _ in range(4):  # drop registrations that disagree with the others (a failed peak), then solve again
            sol, *_ = np.linalg.lstsq(M[keep], rhs[keep], rcond=None)  # the reference frame is held at 0
            residual = np.abs(M @ sol - rhs).max(axis=1)
            bad = residual > max(OUTLIER_PX, 4.0 * float(np.median(residual[keep])))
            if not (bad & keep).any() or np.linalg.matrix_rank(M[keep & ~bad]) < len(others):
                break
            keep &= ~bad
        raw[others] = sol
    error = np.array([np.mean(errs[k]) if k in errs else np.nan for k in range(K)])
    if not usable.all():  # linear in time between (or beyond) the nearest two registered frames
        for k in np.flatnonzero(~usable):
            if idx.size == 1:
                raw[k] = raw[idx[0]]
                continue
            lo = idx[idx < k][-1:]
            hi = idx[idx > k][:1]
            a, b = (lo[0], hi[0]) if lo.size and hi.size else tuple(idx[:2] if not lo.size else idx[-2:])
            raw[k] = raw[a] + (raw[b] - raw[a]) * (k - a) / (b - a)
    # the reference time is the mean of the frames' times: the middle frame's for odd K, half-way between the
    # middle two for even K
    mid = (K - 1) / 2.0
    lo, hi = int(np.floor(mid)), int(np.ceil(mid))
    shifts = raw - 0.5 * (raw[lo] + raw[hi])
    return MotionEstimate(shifts, usable, error, int(reference_frame))


def check_motion_mode(motion) -> str:
    """``motion`` as a key of :data:`MOTION_MODES` (an unknown one is an error listing them)."""
    validate_method(motion, MOTION_MODES, "motion")
    return motion.lower()


@dataclass(frozen=True)
class MovingRecovery:
    """A motion-compensated recovery: the outputs at the reference time, the mask and each sequence's motion."""

    y: np.ndarray
    mask: np.ndarray
    estimates: list


def recover_moving(frames, A, *, dark=None, gain=None, saturation=None, upsample: int = 50, binning: int = 1,
                   shifts=None, device=None) -> MovingRecovery:
    """Recover one sequence of a moving scene: estimate each frame's displacement (or take ``shifts``), then decode
    with frame k sampled at x + d_k in one device pass.

    Parameters
    ----------
    frames : array_like, (K, H, W)
    A : array_like, (B, K)
    dark, gain, saturation
        As :func:`specgpu.engine.apply_linear`.
    upsample, binning
        Of :func:`estimate_global_motion`.
    shifts : array_like, (K, 2), optional
        Known displacements (e.g. the twin's truth); no estimation then.
    device : optional
        OpenCL device selector.

    Returns
    -------
    MovingRecovery
        ``y`` (H, W, B) float32, NaN where a pixel was seen outside the field or saturated; ``mask`` (H, W) uint8
        (1 saturated, 2 non-finite, 4 outside the field); ``estimates`` [MotionEstimate] (empty with ``shifts``).
    """
    estimates = []
    if shifts is None:
        est = estimate_global_motion(frames, dark, gain, upsample=upsample, binning=binning)
        estimates.append(est)
        shifts = est.shifts
    res = apply_linear_warped(frames, A, shifts, dark, gain, saturation=saturation, return_mask=True, device=device)
    y = res.y
    y[(res.mask & 1) > 0] = np.nan
    return MovingRecovery(y, res.mask, estimates)


#: Sub-folder of a sequence folder captured on a moving twin that holds each sequence's truth.
TRUTH_FOLDER = "motion_truth"


def truth_recorder(directory, description, plan, scene):
    """A callable ``(index, sequence)`` that writes the truth of each sequence captured on a moving twin into
    ``directory/motion_truth/sequence_<index>.npz``: a scene cube (``wavelengths``, ``reflectance``: the scene at
    the sequence's reference time, so ``specgpu evaluate CUBE --truth`` reads it), with ``displacement`` (K, 2),
    each frame's true displacement from the reference time, px, and ``reference_time_s``."""
    rig = TwinRig(plan.rig_description(description), scene=scene)
    rig.load_sequence(plan.patterns)
    folder = Path(directory) / TRUTH_FOLDER
    folder.mkdir(parents=True, exist_ok=True)

    def record(index: int, sequence) -> Path:
        truth = rig.motion_truth(sequence.timestamps_s)
        return write_cube_npz(folder / f"sequence_{index:04d}.npz", truth["reflectance"], rig.scene.wavelengths,
                              extra={"displacement": truth["displacement"],
                                     "reference_time_s": np.array(truth["reference_time_s"])})

    return record
