"""Motion of a scene during a sequence, estimated on the host, and the motion-compensated recovery it drives.

A sequence takes K frame periods; anything that moves in that time lands on different pixels in different frames.
**Global** motion (the scene or the camera translates, shakes on its tripod) is one displacement per frame. It is
estimated here by phase correlation between each frame and a reference frame of the same sequence (real
single-precision FFTs, the sub-pixel peak by a Gaussian fit: :mod:`specgpu.pipeline.registration`; or
``skimage.registration.phase_cross_correlation``'s upsampled DFT), on images that do not depend on the light's
spectrum: the gradient magnitude of each dark-subtracted, flat-fielded frame normalised by its mean. Edges stay
where they are whatever the illuminant, while the relative brightness of two surfaces does not; the gradient
magnitude keeps the first and discards the sign of the second, and phase correlation whitens what is left. So no
extra frame is needed and the latency is the sequence itself. (Registering a frame with the same pattern's frame of
the previous sequence also avoids the spectrum, but the sensor's fixed pattern, still on the sensor while the
scene moves, then pulls the estimate to zero, and a vibration near the sequence rate is invisible at lag K.)

An **affine** map per frame (a rotation, a zoom) is fitted to the translations of a grid of tiles; each frame's
global translation is checked against its tiles too, so that an object moving on its own over the scene cannot
take the estimate over. After compensation, pixels whose frames still disagree (the object, an occlusion) are
found from their compensated gradient images (:func:`inconsistent_pixels`) and, where those cannot tell (no frame
has structure there), from the decoding's residual (:mod:`specgpu.pipeline.moving_residual`), flagged and left
NaN.

The displacements are taken relative to the sequence's reference time, the mean of its frames' times (the middle
frame's time for odd K), which is where the twin's truth puts the scene
(``TwinRig.motion_truth``). (A displacement per pixel, ``--motion flow``, starts from this estimate:
:mod:`specgpu.pipeline.moving_flow`.) The decoder then samples frame k at x + d_k in the same device pass
(:func:`specgpu.engine.warp_map.apply_linear_warped`); pixels some frame saw outside the field are NaN and flagged.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy import fft
from skimage.registration import phase_cross_correlation
from threadpoolctl import ThreadpoolController

from specgpu.core.validate import validate_method
from specgpu.engine.consistency import consistency_from_frames, consistency_maps
from specgpu.engine.gradients import gradient_images
from specgpu.io.npz import write_cube_npz
from specgpu.pipeline.registration import (
    bin_image,
    correlation_surface,
    fit_peak_within,
    half_spectrum_energy,
    hann_window,
    peak_error,
    second_peak_ratio,
    sobel_magnitude,
    tile_displacements,
    whitened_half_spectrum,
)
from specgpu.rig.twin import TwinRig

__all__ = ["sequence_truth", "truth_name", "inconsistent_pixels", "consistency", "CHECK_THRESHOLD",
           "at_reference_time", "frame_gradients", "MOTION_MODES", "MotionEstimate", "check_motion_mode",
           "estimate_global_motion", "registration_image", "truth_recorder", "TRUTH_FOLDER"]

#: How frames are decoded with respect to motion: as they are, or compensated for a global translation per frame.
MOTION_MODES = {
    "none": "decode every pixel's samples where they are (a still scene)",
    "global": "estimate a translation per frame (phase correlation of gradient images) and sample frame k at x + d_k",
    "affine": "estimate an affine map per frame (translation, rotation, zoom; tiles registered and fitted) and "
              "sample frame k at M_k x",
    "flow": "global, then a dense flow (tiles registered, a steady velocity each, interpolated per pixel) decodes "
            "each pixel whose frames it makes agree where the global motion leaves it inconsistent, untextured or "
            "less consistent: frame k sampled at x + d_k(x)",
}

#: A frame whose mean signal is below this share of the brightest frame's is not registered (a dark or ambient
#: frame): its displacement is interpolated in time from the others.
MIN_SIGNAL_SHARE = 0.05

#: A pair's registration that disagrees by more than this (px) with the least-squares solution of all the others
#: is dropped (a failed correlation peak); with ``pairs="all"`` each frame is registered to up to 16 others.
OUTLIER_PX = 0.5

#: With the fitted peak (``peak="fit"``), a frame's translation is checked against its tiles only where the
#: correlation surface of the frame and the reference frame has a second peak (1.5 standard deviations of the
#: peak or more away) above this share of the first: two motions compete (an object moving on its own), or the
#: scene repeats itself. On the moving twin a chart moving over the still natural scene gives 0.45 or more, the
#: natural scene alone moving 0.2 or less.
AMBIGUOUS_PEAK = 0.3

#: The fastest motion (px per frame) the global estimate looks for: a pair of frames g frames apart is correlated
#: over displacements of at most ``g`` times this (and the width of the peak) along each axis. A scene that repeats
#: itself (a chart's grid of patches, 100 px apart at 640 x 480) correlates almost as well, or better, a period
#: off; a period beyond reach is then neither taken nor counted as a rival, so a still or slow chart needs no
#: more than the reference pairs. 16 px per frame is 64 px between the middle and the last frame of 9, beyond
#: the speeds the object layers separate (:data:`specgpu.pipeline.moving_layers.MAX_LAYER_SPEED_PX`).
MAX_SPEED_PX_PER_FRAME = 16.0

#: Where a reference pair's best peak within reach of :data:`MAX_SPEED_PX_PER_FRAME` is below this share of the
#: surface's highest, which lies beyond reach, or sits on the edge of the reach below it, the scene moves faster
#: than that: the sequence is estimated again over the whole surface. A faster motion leaves within reach only
#: noise (on the moving twin at 18 to 30 px per frame, the pair furthest out of reach: 0.02-0.11 of the true
#: peak) or the tail of the true peak on the edge (17 px per frame), which no later step would catch: the warp
#: would take it, and the consistency check cannot judge flat pixels. Two peaks that are both real stay
#: apart: a repeating scene's peak a period off (the true one is 0.9 of it or more), and an object moving faster
#: than the reach over a still scene (a chart at 25 px per frame over the natural scene: the scene's peak is
#: 0.44-0.73 of the chart's), whose motion is the object layers' to find, not the scene's. A false peak within
#: reach that is not noise (a fixed pattern the flat field left, a still overlay) holds the estimate there all the
#: same.
BEYOND_REACH = 0.2


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


def gradient_image(frame, dark=None, gain=None, *, binning: int = 1) -> np.ndarray:
    """The spectrum-independent image a frame is registered on: gradient magnitude (Sobel) of the
    dark-subtracted, flat-fielded frame over its mean, float32; ``binning`` averages b x b pixels first."""
    f = np.subtract(frame, dark, dtype=np.float32) if dark is not None else np.array(frame, np.float32)
    if gain is not None:  # a NaN gain (a pixel with no response) reads 0 here: one NaN would spoil the FFTs
        f *= np.nan_to_num(np.asarray(gain, np.float32), nan=0.0)
    f = bin_image(f, binning)
    mean = float(np.mean(f, dtype=np.float64))
    g = sobel_magnitude(f)  # linear in f: the division by the mean on the result
    if mean > 0:
        g *= np.float32(1.0 / mean)
    return g


def hann(image: np.ndarray) -> np.ndarray:
    """``image`` under a 2-D Hann window (:func:`specgpu.pipeline.registration.hann_window`; phase correlation
    assumes periodic images)."""
    return image * hann_window(image.shape)


def registration_image(frame, dark=None, gain=None, *, binning: int = 1) -> np.ndarray:
    """:func:`gradient_image` under a Hann window."""
    return hann(gradient_image(frame, dark, gain, binning=binning))


def _whitened(image: np.ndarray, cutoff: float) -> np.ndarray:
    """Phase-only spectrum of ``image`` weighted towards low spatial frequencies: a sub-pixel shift of a sampled
    image is a linear phase only well below the Nyquist frequency (interpolation and the pixels' own footprint
    bend it towards zero near it, which would bias the estimate towards no motion)."""
    F = fft.fft2(image)
    return F / np.maximum(np.abs(F), 1e-30) * _frequency_weight(F.shape, float(cutoff))


@functools.lru_cache(maxsize=16)
def _frequency_weight(shape: tuple, cutoff: float) -> np.ndarray:
    """The Gaussian weight of :func:`_whitened` on an FFT grid of ``shape``: made once per (shape, cutoff), not per
    image (a sequence whitens K whole images and many tiles of the same few shapes)."""
    fy = fft.fftfreq(shape[0])[:, None]
    fx = fft.fftfreq(shape[1])[None, :]
    weight = np.exp(-0.25 * (fx**2 + fy**2) / cutoff**2)
    weight.flags.writeable = False
    return weight


def _register(a: np.ndarray, b: np.ndarray, upsample: int) -> tuple[np.ndarray, float]:
    """(x, y) displacement of the content of whitened spectrum ``b`` relative to ``a``, and the error."""
    shift, err, _ = phase_cross_correlation(a, b, upsample_factor=upsample, normalization=None, space="fourier")
    return -np.asarray(shift[::-1], np.float64), float(err)


@functools.lru_cache(maxsize=1)
def _blas() -> ThreadpoolController:
    return ThreadpoolController()


def _one_blas_thread(fn):
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


@_one_blas_thread
def estimate_global_motion(frames: ArrayLike, dark: ArrayLike | None = None, gain: ArrayLike | None = None, *,
                           reference_frame: int | None = None,
                           upsample: int = 10, binning: int = 1, pairs: str = "auto", cutoff: float = 0.12,
                           max_gap: int = 8, model: str = "translation", tiles: int = 4,
                           robust: bool = True, peak: str = "fit",
                           ambiguous: float = AMBIGUOUS_PEAK,
                           max_speed: float | None = MAX_SPEED_PX_PER_FRAME, gradients=None) -> MotionEstimate:
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
        With ``peak="dft"``: sub-pixel resolution 1 / upsample px of the phase correlation peak (on the moving
        twin 1/10 px peaks give the same errors as 1/50 px ones).
    peak : {"fit", "dft"}
        How the correlation peak is located to a fraction of a pixel: a Gaussian through the samples across it
        (:func:`specgpu.pipeline.registration.fit_peak`; the weighted surface is a Gaussian, so this is exact to
        about 0.01 px of a 1/100 px upsampled DFT) on real single-precision FFTs; or skimage's upsampled DFT
        (``phase_cross_correlation``), five to ten times slower. On the moving twin at 640 x 480 (24 sequences,
        ``tools/studies/motion_registration.py``) the defaults (fit, reference pairs there) err by at most 0.07 px,
        median
        0.04 px, in an eighth of the time of the upsampled DFT of all pairs (0.08, 0.04).
    binning : int
        Average the gradient images over b x b pixels before registering (faster FFTs; the shifts are scaled
        back; the images kept for the consistency check stay at full resolution).
    cutoff : float
        Standard deviation (cycles per pixel) of the Gaussian weight on the spatial frequencies of the whitened
        cross-power spectrum.
    pairs : {"auto", "reference", "all"}
        Which pairs of frames are registered; the displacements are their least-squares solution, pairs that
        disagree with the others by more than :data:`OUTLIER_PX` dropped. ``"reference"``: each frame to the
        reference frame (K - 1 registrations; on the moving twin as accurate as all pairs, whose long gaps pair
        the most different bands); ``"all"``: every pair at most ``max_gap`` apart (for K = 9, 36); ``"auto"`` (the
        default): with ``peak="fit"`` the reference pairs, and every pair as well where one of their correlation
        surfaces has a rival peak (see ``ambiguous``): a scene that repeats itself (a chart's grid of patches) can
        put one pair's peak a whole period off, which only the other pairs outvote; with ``"dft"`` every pair.
    max_gap : int
        The furthest apart (in frames) two frames registered with ``pairs="all"`` are.
    model : {"translation", "affine"}
        A displacement per frame, or an affine map per frame (rotation, zoom, shear): each frame's translation is
        refined by registering ``tiles`` x ``tiles`` tiles of it to the reference frame and fitting the map. (A
        displacement per pixel: :mod:`specgpu.pipeline.moving_flow`, from this estimate.)
    robust : bool
        Translation model: check each frame's whole-image translation against its tiles' median and take the
        tiles' consensus where they disagree (an object moving over the scene can dominate the whole-image
        correlation); costs ``tiles``^2 small registrations per frame. With ``peak="fit"`` only when some frame's
        correlation with the reference frame has a second peak above ``ambiguous`` times the first (see
        :data:`AMBIGUOUS_PEAK`), then for every frame; with ``"dft"`` always.
    max_speed : float or None
        With ``peak="fit"``: the fastest motion looked for, px per frame (:data:`MAX_SPEED_PX_PER_FRAME`): each
        pair's peak, and its rivals, are sought within that speed times the frames between them; None: anywhere
        on the surface. Where a pair of the first round (the reference pairs, or every pair with ``pairs="all"``)
        has its best peak within reach below :data:`BEYOND_REACH` of the surface's highest, or on the edge of the
        reach below it, the scene moves faster: the sequence is estimated again with None.
    gradients : sequence, optional
        The frames' :func:`gradient_image` s already made (K entries, None where one is to be made here; e.g. on
        the device, :func:`frame_gradients`): registered as they are.

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

    dark_level = None if dark is None else np.mean(dark, axis=(-2, -1), dtype=np.float64)  # one per dark frame
    level = np.array([float(np.mean(frames[k], dtype=np.float64))
                      - (0.0 if dark is None else float(dark_level[k] if per_frame_dark else dark_level))
                      for k in range(K)])
    usable = level >= MIN_SIGNAL_SHARE * max(float(level.max()), 1e-30)
    if usable.sum() < 1:
        raise ValueError("no frame of the sequence has signal to register")
    if reference_frame is None:
        middle = [k for k in range(max(0, K // 2 - 1), min(K, K // 2 + 2)) if usable[k]]
        reference_frame = max(middle or list(np.flatnonzero(usable)), key=lambda k: level[k])
    if model not in ("translation", "affine"):
        raise ValueError(f"model must be one of translation, affine, got {model!r}")
    if model != "translation" and binning != 1:
        raise ValueError(f"model={model!r} registers tiles at full resolution: binning must be 1")
    if pairs not in ("auto", "reference", "all"):
        raise ValueError(f"pairs must be one of auto, reference, all, got {pairs!r}")
    if not 0 <= reference_frame < K or not usable[reference_frame]:
        raise ValueError(f"reference_frame {reference_frame} is not a usable frame of the {K}")
    if peak not in ("fit", "dft"):
        raise ValueError(f"peak must be one of fit, dft, got {peak!r}")
    if max_speed is not None and not (np.isfinite(max_speed) and max_speed > 0):
        raise ValueError(f"max_speed must be a positive number of px per frame or None, got {max_speed!r}")
    fit = peak == "fit"
    given = gradients
    spectra, gradients, ambiguity, energies = {}, {}, {}, {}
    if given is not None:
        if len(given) != K:
            raise ValueError(f"gradients must hold one image (or None) per frame, {K}, got {len(given)}")
        for k, g in enumerate(given):
            if g is not None:
                if np.shape(g) != frames.shape[1:]:
                    raise ValueError(f"gradients[{k}] is {np.shape(g)}, the frames are {frames.shape[1:]}")
                gradients[k] = np.asarray(g, np.float32)

    def gradient(k):  # full resolution (the consistency check reads them again); binned to be registered
        if k not in gradients:
            gradients[k] = gradient_image(frames[k], dark_of(k), gain)
        return gradients[k]

    def spectrum(k):
        if k not in spectra:
            image = bin_image(gradient(k), binning)
            spectra[k] = whitened_half_spectrum(image, cutoff) if fit else _whitened(hann(image), cutoff)
        return spectra[k]

    def energy(k):
        if k not in energies:
            energies[k] = half_spectrum_energy(spectrum(k), gradient(k).shape[1] // binning)
        return energies[k]

    def register(a, b):
        if not fit:
            return _register(spectrum(a), spectrum(b), upsample)
        shape = tuple(n // binning for n in gradient(a).shape)
        surface = correlation_surface(spectrum(a), spectrum(b), shape)
        radius = max(1, int(np.ceil(1.5 / (2.0 * np.pi * cutoff))))  # 1.5 sigma of the peak
        # the displacements the motion can have reached between the two frames (binned px)
        within = None if max_speed is None else int(np.ceil(max_speed * abs(b - a) / binning)) + radius
        d, top = fit_peak_within(surface, within)
        if within is not None and (a, b) in first_round:
            highest = float(surface.max())
            on_edge = float(np.abs(d).max()) >= within - 1  # the tail of a peak just beyond reach
            if top < BEYOND_REACH * highest or (on_edge and top < highest):
                beyond.append((a, b))
        if reference_frame in (a, b):  # how clearly the whole image moves as one: the tiles' check needed?
            ambiguity[b if a == reference_frame else a] = second_peak_ratio(surface, d, radius, within)
        return d, peak_error(top, energy(a), energy(b), surface.size)

    def kept_gradients():
        return tuple(gradients.get(k) for k in range(K))

    idx = np.flatnonzero(usable)
    every = [(int(a), int(b)) for i, a in enumerate(idx) for b in idx[i + 1:] if b - a <= max_gap]
    to_reference = [(min(reference_frame, int(k)), max(reference_frame, int(k))) for k in idx if k != reference_frame]
    links = every if pairs == "all" or (pairs == "auto" and not fit) else to_reference
    first_round = set(links)  # the pairs whose peaks say whether the motion is beyond reach
    rows, rhs, errs, beyond = [], [], {}, []

    def more_links():  # "auto": every pair as well where a frame's correlation with the reference has a rival peak
        if pairs != "auto" or not fit or max(ambiguity.values(), default=0.0) <= ambiguous:
            return []
        done = set(to_reference)
        return [link for link in every if link not in done]

    def measure(pairs_):
        for a, b in pairs_:
            d, err = register(a, b)
            row = np.zeros(K)
            row[b], row[a] = 1.0, -1.0
            rows.append(row)
            rhs.append(d * binning)  # x, y of frame b less those of frame a
            errs.setdefault(a, []).append(err)
            errs.setdefault(b, []).append(err)

    measure(links)
    if beyond:  # a motion faster than the reach: looked for anywhere (BEYOND_REACH)
        return estimate_global_motion(frames, dark, gain, reference_frame=reference_frame, upsample=upsample,
                                      binning=binning, pairs=pairs, cutoff=cutoff, max_gap=max_gap, model=model,
                                      tiles=tiles, robust=robust, peak=peak, ambiguous=ambiguous, max_speed=None,
                                      gradients=kept_gradients())
    measure(more_links())  # after the reference pairs: their peaks say whether the others are needed
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
    # displacements from the reference time (at_reference_time: the mean of the frames' times)
    if model == "translation":
        if robust:
            reference_tiles = {}
            # with the fitted peak, only where some frame's whole-image peak has a rival: then every frame, since a
            # second motion is the scene's, not one frame's (an object's peak can fall just below the threshold in
            # the frame where it is nearest the background's, and take that frame's estimate over); and a frame
            # never correlated with the reference frame, whose peak was not looked at
            rival = max(ambiguity.values(), default=0.0) > ambiguous
            for k in idx:
                if k != reference_frame and (not fit or rival or int(k) not in ambiguity):
                    raw[k] = _dominant_translation(gradient(reference_frame), gradient(int(k)), raw[k], upsample,
                                                   cutoff, tiles, reference_tiles if fit else None)
        raw = _fill_in_time(raw, usable)
        return MotionEstimate(raw - at_reference_time(raw), usable, error, int(reference_frame), model,
                              kept_gradients())
    maps = np.tile(np.eye(3), (K, 1, 1))
    for k in idx:
        if k != reference_frame:
            maps[k] = _affine_to(gradient(reference_frame), gradient(int(k)), raw[k], upsample, cutoff, tiles)
    maps = _fill_in_time(maps, usable)
    to_mid = np.linalg.inv(at_reference_time(maps))
    return MotionEstimate((maps @ to_mid)[:, :2, :], usable, error, int(reference_frame), model, kept_gradients())


def at_reference_time(values: np.ndarray) -> np.ndarray:
    """The value at a sequence's reference time of per-frame ``values`` (K, ...): the middle frame's for odd K, the
    mean of the middle two frames' for even K (the mean of the frames' times)."""
    mid = (len(values) - 1) / 2.0
    return 0.5 * (values[int(np.floor(mid))] + values[int(np.ceil(mid))])


def frame_gradients(frames, dark=None, gain=None, gradients=None, which=None, device=None) -> list:
    """Each frame's :func:`gradient_image` (``dark``: (H, W) or one per frame), taking those already made
    (``gradients``: a sequence with None where one is to be made, or None); ``which``: only those frames, None for
    the others. The ones to make are made together on the OpenCL ``device`` (a selector or queue; default: the
    default device; :func:`specgpu.engine.gradients.gradient_images`, equal to the host's to float32 rounding, a
    tenth of its time); on the host where the device cannot take the inputs as they are (an integer type other
    than uint8 or uint16, a dark frame or flat field that is not finite)."""
    dark = None if dark is None else np.asarray(dark, np.float32)
    wanted = range(len(frames)) if which is None else {int(k) for k in which}
    out = [gradients[k] if gradients is not None and k in wanted else None for k in range(len(frames))]
    made = [k for k in range(len(frames)) if k in wanted and out[k] is None]
    if not made:
        return out

    def dark_of(k):
        return None if dark is None else (dark[k] if dark.ndim == 3 else dark)

    frames = np.asarray(frames)
    stack = frames if len(made) == len(frames) else frames[made]  # every frame (the usual case): no copy
    if _device_takes(stack, dark, gain):
        per_frame = None if dark is None else (dark[made] if dark.ndim == 3 else dark)
        for k, image in zip(made, gradient_images(stack, per_frame, gain, device=device).get()):
            out[k] = image
    else:
        for k in made:
            out[k] = gradient_image(frames[k], dark_of(k), gain)
    return out


def _device_takes(frames: np.ndarray, dark, gain) -> bool:
    """Whether :func:`specgpu.engine.gradients.gradient_images` takes these inputs as :func:`gradient_image` does:
    uint8, uint16 or float frames (float64 is made float32 by both), a finite dark frame, a flat field with no
    infinity (a NaN reads 0 in both). (The device refuses the others, the host computes on.)"""
    if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        return False
    if frames.dtype == np.float64 and np.abs(frames[np.isfinite(frames)]).max(initial=0.0) > np.finfo(np.float32).max:
        return False
    return (dark is None or bool(np.isfinite(dark).all())) and (
        gain is None or not bool(np.isinf(np.asarray(gain, np.float32)).any()))


def _fill_in_time(values: np.ndarray, usable: np.ndarray) -> np.ndarray:
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


def _tile_displacements(g_ref, g_k, shift, upsample: int, cutoff: float, tiles, max_error: float = 1.0):
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
            d, err = _register(_whitened(hann(g_ref[y0:y0 + th, x0:x0 + tw]), cutoff),
                               _whitened(hann(g_k[ys:ys + th, xs:xs + tw]), cutoff), upsample)
            if err > max_error:
                continue
            c = np.array([x0 + (tw - 1) / 2.0, y0 + (th - 1) / 2.0])
            src.append(c)
            dst.append(c + t + d)
    return np.reshape(src, (-1, 2)), np.reshape(dst, (-1, 2))


def _dominant_translation(g_ref, g_k, shift, upsample: int, cutoff: float, tiles: int,
                          reference_tiles: dict | None = None) -> np.ndarray:
    """The translation most of the field shares: ``shift`` (the whole-image registration) unless the tiles'
    median is more than :data:`OUTLIER_PX` from it (a smaller, strongly textured object moving on its own
    dominates the whole-image correlation), then the mean of the tiles within :data:`OUTLIER_PX` of their
    median, the tiles registered again at that median. ``reference_tiles``: the tiles registered by
    :func:`specgpu.pipeline.registration.tile_displacements` (the fitted peak), the reference's tiles' spectra
    kept in it across frames; None: by the upsampled DFT."""
    def tiles_at(where):
        src, dst = _tile_displacements(g_ref, g_k, where, upsample, cutoff, tiles) if reference_tiles is None \
            else tile_displacements(g_ref, g_k, where, cutoff, tiles, reference_tiles)
        return dst - src

    d = tiles_at(shift)
    if len(d) < 3:
        return np.asarray(shift, np.float64)
    med = np.median(d, axis=0)
    if np.abs(med - shift).max() <= OUTLIER_PX:
        return np.asarray(shift, np.float64)
    if np.any(np.rint(med) != np.rint(shift)):  # again where the tiles overlap fully: each peak more accurate
        again = tiles_at(med)
        if len(again) >= 3:
            d, med = again, np.median(again, axis=0)
    near = np.abs(d - med).max(axis=1) <= OUTLIER_PX
    return d[near].mean(axis=0) if near.sum() >= 3 else med


def _affine_to(g_ref: np.ndarray, g_k: np.ndarray, shift, upsample: int, cutoff: float, tiles: int) -> np.ndarray:
    """(3, 3) affine map of reference-frame positions to frame k's: the tiles' displacements
    (:func:`_tile_displacements`) fitted by least squares, tiles more than :data:`OUTLIER_PX` off the fit dropped;
    the global translation where fewer than 3 tiles register."""
    src, dst = _tile_displacements(g_ref, g_k, shift, upsample, cutoff, tiles)
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


#: A pixel is inconsistent where some frame correlates below this with the median (:func:`inconsistent_pixels`).
CHECK_THRESHOLD = 0.3


def inconsistent_pixels(frames, shifts, dark=None, gain=None, *, window: int = 9, threshold: float = CHECK_THRESHOLD,
                        texture: float = 0.5, own: float = 4.0, gradients=None) -> np.ndarray:
    """(H, W) bool: pixels where the motion-compensated frames disagree, so their decoded spectrum would mix
    surfaces.

    Each frame's :func:`gradient_image` is sampled where the motion says that frame saw each pixel; where the
    motion is right, their edges coincide whatever the illuminant (their contrasts differ, not their places). Per
    pixel, the normalised cross-correlation over a ``window`` x ``window`` neighbourhood between each compensated
    gradient image and their median is computed; a pixel is inconsistent where some frame with structure of its
    own there (local energy above ``own`` times its median: not just noise) correlates below ``threshold``,
    whether or not the median has texture: a wrong motion leaves the median of misaligned images flat where each
    frame has an edge. Where no frame has structure this check cannot judge; the residual check of the decoding
    does (:mod:`specgpu.pipeline.moving_residual`). ``gradients``: the frames' gradient images already made
    (:attr:`MotionEstimate.gradients`; a None entry is made here).
    """
    _, worst = consistency(frames, shifts, dark, gain, window=window, texture=texture, own=own,
                                  gradients=gradients)
    return worst < threshold


def consistency(frames, shifts, dark=None, gain=None, *, window: int = 9, texture: float = 0.5, own: float = 4.0,
                gradients=None) -> tuple[np.ndarray, np.ndarray]:
    """The two maps :func:`inconsistent_pixels` thresholds, (H, W) each: ``textured`` (bool: the median
    compensated gradient image has structure there) and ``worst`` (float32: the lowest normalised
    cross-correlation of a frame with structure of its own against that median; 1 where none has). Two
    hypotheses of a pixel's motion are compared by their ``worst``. The per-pixel work runs on the default OpenCL
    device (:func:`specgpu.engine.consistency.consistency_maps`); where no gradient image is given, they are made
    there too and never read back (:func:`specgpu.engine.consistency.consistency_from_frames`)."""
    frames = np.asarray(frames)
    none_given = gradients is None or all(g is None for g in gradients)
    if none_given and np.all(np.isfinite(np.asarray(shifts, np.float64))) and _device_takes(
            frames, None if dark is None else np.asarray(dark, np.float32), gain):
        return consistency_from_frames(frames, shifts, dark, gain, window=window, texture=texture, own=own)
    g = frame_gradients(frames, dark, gain, gradients)
    return consistency_maps(g, shifts, window=window, texture=texture, own=own)


def check_motion_mode(motion) -> str:
    """``motion`` as a key of :data:`MOTION_MODES` (an unknown one is an error listing them)."""
    validate_method(motion, MOTION_MODES, "motion")
    return motion.lower()


#: Sub-folder of a sequence folder captured on a moving twin that holds each sequence's truth.
TRUTH_FOLDER = "motion_truth"


def truth_name(sequence: int) -> str:
    """The file name of sequence ``sequence``'s motion truth in ``motion_truth/``."""
    return f"sequence_{int(sequence):04d}.npz"


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
        return write_cube_npz(folder / truth_name(index), truth["reflectance"], rig.scene.wavelengths,
                              extra={"displacement": truth["displacement"],
                                     "reference_time_s": np.array(truth["reference_time_s"])})

    return record


def sequence_truth(directory, sequence: int | None = None) -> Path:
    """The truth file a recovery of ``directory`` (a sequence folder captured on a moving twin) is scored against:
    ``motion_truth/sequence_<sequence>.npz``; with ``sequence`` None, the folder's only one. Refused in one line
    when the folder keeps no truth, when ``sequence`` has none, or when several do and none is named."""
    directory = Path(directory)
    try:  # as a recovery's metadata records it (a number, or its text in an EXR header)
        sequence = None if sequence is None else int(sequence)
    except (TypeError, ValueError):
        sequence = None
    folder = directory / TRUTH_FOLDER
    kept = sorted(folder.glob("sequence_*.npz")) if folder.is_dir() else []
    if not kept:
        raise ValueError(f"{directory}: holds no motion truth ({TRUTH_FOLDER}/sequence_NNNN.npz: a capture on a "
                         "moving twin keeps it); give the true scene (colorchecker, white, natural or a cube file)")
    if sequence is not None:
        path = folder / truth_name(sequence)
        if not path.is_file():
            raise ValueError(f"{directory}: holds no motion truth of sequence {int(sequence)} ({len(kept)} kept: "
                             f"{kept[0].name} .. {kept[-1].name})")
        return path
    if len(kept) > 1:
        raise ValueError(f"{directory}: holds the motion truth of {len(kept)} sequences and the recovery does not "
                         f"record which it is; give --truth {folder}/sequence_NNNN.npz")
    return kept[0]
