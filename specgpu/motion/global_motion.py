"""The ``global`` method: a translation per frame of one sequence (and the pairwise registration the ``affine``
method refines), estimated on the host.

A sequence takes K frame periods; anything that moves in that time lands on different pixels in different frames.
**Global** motion (the scene or the camera translates, shakes on its tripod) is one displacement per frame. It is
estimated here by phase correlation between each frame and a reference frame of the same sequence (real
single-precision FFTs, the sub-pixel peak by a Gaussian fit: :mod:`specgpu.motion.registration`; or
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
found from their compensated gradient images (:func:`specgpu.motion.consistency.inconsistent_pixels`) and,
where those cannot tell (no frame has structure there), from the decoding's residual (:mod:`specgpu.motion.residual`),
flagged and left NaN.

The displacements are taken relative to the sequence's reference time, the mean of its frames' times (the middle
frame's time for odd K), which is where the twin's truth puts the scene
(``TwinRig.motion_truth``). (A displacement per pixel, ``--motion flow``, starts from this estimate:
:mod:`specgpu.motion.flow`.) The decoder then samples frame k at x + d_k in the same device pass
(:func:`specgpu.engine.warp_map.apply_linear_warped`); pixels some frame saw outside the field are NaN and flagged.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from specgpu.motion.affine import affine_estimate
from specgpu.motion.candidates import CANDIDATE_SHARE, choose_candidates, peak_candidates
from specgpu.motion.estimate import MotionEstimate, at_reference_time, fill_in_time, one_blas_thread
from specgpu.motion.images import gradient_image
from specgpu.motion.registration import (
    bin_image,
    correlation_surface,
    fit_peak_within,
    half_spectrum_energy,
    peak_error,
    second_peak_ratio,
)
from specgpu.motion.tiles import OUTLIER_PX, dominant_translation, register_dft
from specgpu.motion.whitening import hann, whitened_half_spectrum, whitened_spectrum

__all__ = ["GlobalOptions", "estimate_global_motion", "estimate_with_options", "MIN_SIGNAL_SHARE", "OUTLIER_PX",
           "AMBIGUOUS_PEAK", "MAX_SPEED_PX_PER_FRAME", "BEYOND_REACH"]

#: A frame whose mean signal is below this share of the brightest frame's is not registered (a dark or ambient
#: frame): its displacement is interpolated in time from the others.
MIN_SIGNAL_SHARE = 0.05

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
#: the speeds the object layers separate (:data:`specgpu.motion.object_motion.MAX_LAYER_SPEED_PX`).
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
class GlobalOptions:
    """How :func:`estimate_global_motion` registers a sequence: its keywords, described there, checked once
    (:meth:`check`)."""

    upsample: int = 10
    binning: int = 1
    pairs: str = "auto"
    cutoff: float = 0.12
    max_gap: int = 8
    model: str = "translation"
    tiles: int = 4
    robust: bool = True
    peak: str = "fit"
    ambiguous: float = AMBIGUOUS_PEAK
    max_speed: float | None = MAX_SPEED_PX_PER_FRAME

    @property
    def fit(self) -> bool:
        """The peak is located by the Gaussian fit on real FFTs (not skimage's upsampled DFT)."""
        return self.peak == "fit"

    @property
    def radius(self) -> int:
        """1.5 standard deviations of the correlation peak, px."""
        return max(1, int(np.ceil(1.5 / (2.0 * np.pi * self.cutoff))))

    def check(self) -> None:
        """A one-line ValueError naming the first keyword out of its range."""
        if self.upsample < 1:
            raise ValueError(f"upsample must be >= 1, got {self.upsample}")
        if self.model not in ("translation", "affine"):
            raise ValueError(f"model must be one of translation, affine, got {self.model!r}")
        if self.model != "translation" and self.binning != 1:
            raise ValueError(f"model={self.model!r} registers tiles at full resolution: binning must be 1")
        if self.pairs not in ("auto", "reference", "all"):
            raise ValueError(f"pairs must be one of auto, reference, all, got {self.pairs!r}")
        if self.peak not in ("fit", "dft"):
            raise ValueError(f"peak must be one of fit, dft, got {self.peak!r}")
        if self.max_speed is not None and not (np.isfinite(self.max_speed) and self.max_speed > 0):
            raise ValueError(f"max_speed must be a positive number of px per frame or None, got {self.max_speed!r}")


class SequenceImages:
    """One sequence's frames and what is made of them once, on first use: each frame's full-resolution gradient
    image (the consistency check reads them again), its whitened spectrum (binned) and that spectrum's energy."""

    def __init__(self, frames: np.ndarray, dark, gain, options: GlobalOptions, given=None):
        self.frames, self.gain, self.options = frames, gain, options
        self.dark = None if dark is None else np.asarray(dark, np.float32)
        self.gradients, self.spectra, self.energies = _given_gradients(given, frames), {}, {}

    def dark_of(self, k: int):
        """Frame k's dark level: (H, W), or None."""
        if self.dark is None:
            return None
        return self.dark[k] if self.dark.ndim == 3 else self.dark

    def levels(self) -> np.ndarray:
        """(K,) each frame's mean signal above its dark level."""
        dark, K = self.dark, len(self.frames)
        dark_level = None if dark is None else np.mean(dark, axis=(-2, -1), dtype=np.float64)  # one per dark frame
        return np.array([float(np.mean(self.frames[k], dtype=np.float64))
                         - (0.0 if dark is None else float(dark_level[k] if dark.ndim == 3 else dark_level))
                         for k in range(K)])

    def gradient(self, k: int) -> np.ndarray:
        if k not in self.gradients:
            self.gradients[k] = gradient_image(self.frames[k], self.dark_of(k), self.gain)
        return self.gradients[k]

    def spectrum(self, k: int) -> np.ndarray:
        if k not in self.spectra:
            image = bin_image(self.gradient(k), self.options.binning)
            cutoff = self.options.cutoff
            self.spectra[k] = whitened_half_spectrum(image, cutoff) if self.options.fit \
                else whitened_spectrum(hann(image), cutoff)
        return self.spectra[k]

    def energy(self, k: int) -> float:
        if k not in self.energies:
            self.energies[k] = half_spectrum_energy(self.spectrum(k), self.gradient(k).shape[1] // self.options.binning)
        return self.energies[k]

    def kept(self) -> tuple:
        """The gradient images made or given, per frame (None for the others)."""
        return tuple(self.gradients.get(k) for k in range(len(self.frames)))


def _given_gradients(given, frames: np.ndarray) -> dict:
    """Frame -> gradient image of those ``given`` (K entries, None where one is to be made), checked."""
    out = {}
    if given is None:
        return out
    K = frames.shape[0]
    if len(given) != K:
        raise ValueError(f"gradients must hold one image (or None) per frame, {K}, got {len(given)}")
    for k, g in enumerate(given):
        if g is not None:
            if np.shape(g) != frames.shape[1:]:
                raise ValueError(f"gradients[{k}] is {np.shape(g)}, the frames are {frames.shape[1:]}")
            out[k] = np.asarray(g, np.float32)
    return out


class PairRegistrations:
    """The pairs of frames registered so far and the linear system they make: each pair (a, b) a row saying
    "frame b's displacement less frame a's is d". Also what the pairs with the reference frame said: how clearly
    the whole image moves as one (``ambiguity``, :data:`AMBIGUOUS_PEAK`), and which pairs of the first round have
    their peak beyond reach (``beyond``, :data:`BEYOND_REACH`). Where a correlation has rival peaks each row keeps
    its candidates, and :meth:`resolve` chooses among them the ones on a steady motion
    (:func:`~specgpu.motion.candidates.choose_candidates`)."""

    def __init__(self, images: SequenceImages, reference_frame: int, prior_velocity=None):
        self.images, self.reference_frame = images, reference_frame
        self.prior_velocity = prior_velocity
        self.pairs, self.rhs, self.candidates = [], [], []
        self.ambiguity, self.beyond, self.first_round = {}, [], set()
        self.velocity = None  # the steady motion chosen among rival peaks (px per frame), once resolved
        self.surfaces = {}  # the reference pairs' correlation surfaces and reach, until resolved

    def register(self, a: int, b: int):
        """(x, y) displacement of frame b's content relative to frame a's (binned px), its error, and the
        candidates ((N, 2) displacements, binned px, (N,) heights and (N,) errors): a reference pair's highest
        peak alone until :meth:`resolve` (which makes its candidates where some frame has a rival), every peak
        within reach for the other pairs."""
        images, options = self.images, self.images.options
        if not options.fit:
            d, err = register_dft(images.spectrum(a), images.spectrum(b), options.upsample)
            return d, err, (d[None], np.ones(1), np.array([err]))
        binning = options.binning
        shape = tuple(n // binning for n in images.gradient(a).shape)
        surface = correlation_surface(images.spectrum(a), images.spectrum(b), shape)
        radius = options.radius
        # the displacements the motion can have reached between the two frames (binned px)
        within = None if options.max_speed is None else int(np.ceil(options.max_speed * abs(b - a) / binning)) + radius
        d, top = fit_peak_within(surface, within)
        if within is not None and (a, b) in self.first_round:
            highest = float(surface.max())
            on_edge = float(np.abs(d).max()) >= within - 1  # the tail of a peak just beyond reach
            if top < BEYOND_REACH * highest or (on_edge and top < highest):
                self.beyond.append((a, b))
        err = peak_error(top, images.energy(a), images.energy(b), surface.size)
        if self.reference_frame in (a, b):  # how clearly the whole image moves as one: the tiles' check needed?
            self.ambiguity[b if a == self.reference_frame else a] = second_peak_ratio(surface, d, radius, within)
            if self.velocity is None:  # its surface kept for the candidates, should some frame have a rival
                self.surfaces[(a, b)] = (surface, within, top)
                return d, err, (d[None], np.array([top]), np.array([err]))
        return d, err, self.candidates_of(a, b, surface, within, top)

    def candidates_of(self, a: int, b: int, surface: np.ndarray, within, top: float) -> tuple:
        """The peaks of pair (a, b)'s ``surface`` within reach (:func:`~specgpu.motion.candidates.peak_candidates`,
        above :data:`~specgpu.motion.candidates.CANDIDATE_SHARE` of the highest): (N, 2) displacements (binned
        px), (N,) heights and (N,) errors; ``top`` the highest sample within reach."""
        images = self.images
        peaks, heights = peak_candidates(surface, images.options.radius, within, CANDIDATE_SHARE, top=top)
        energies = images.energy(a), images.energy(b)
        return peaks, heights, np.array([peak_error(v, *energies, surface.size) for v in heights])

    def measure(self, pairs, *, first_round: bool = False) -> None:
        """Register each pair of ``pairs`` and add its row; ``first_round``: the pairs whose peaks say whether the
        motion is beyond reach."""
        if first_round:
            self.first_round = set(pairs)
        binning = self.images.options.binning
        for a, b in pairs:
            d, err, (peaks, heights, errors) = self.register(a, b)
            self.pairs.append((a, b))
            self.rhs.append((d * binning, err))  # x, y of frame b less those of frame a
            self.candidates.append((peaks * binning, heights, errors))

    def choose(self, pairs=None):
        """:func:`~specgpu.motion.candidates.choose_candidates` over the rows registered (or those of ``pairs``,
        indices), the frames' index as their time."""
        rows = range(len(self.pairs)) if pairs is None else pairs
        options = self.images.options
        return choose_candidates(np.arange(len(self.images.frames)), [self.pairs[i] for i in rows],
                                 [self.candidates[i][0] for i in rows], [self.candidates[i][1] for i in rows],
                                 prior_velocity=self.prior_velocity, ambiguous=options.ambiguous)

    def resolve(self, usable: np.ndarray, every: list) -> np.ndarray:
        """Where some frame's correlation with the reference frame has a rival peak (a scene that repeats
        itself, two motions), or where the frames' highest peaks lie on no steady motion (a repeating scene whose
        true peak is the lower in a few frames): with ``pairs="auto"`` every pair of ``every`` registered as
        well, and each row's displacement chosen among its candidates, on the steady motion most pairs agree
        on, or nearest the prior (:func:`~specgpu.motion.candidates.choose_candidates`); a row with rivals and
        none on it dropped. Returns ``usable`` less the frames left with no row (their displacement is then
        filled in time)."""
        surfaces, self.surfaces = self.surfaces, {}
        options = self.images.options
        if not options.fit:
            return usable
        ref = self.reference_frame
        reference_rows = [i for i, pair in enumerate(self.pairs) if ref in pair]
        if not self.rival() and self.choose(reference_rows).on_line.all():  # one clear peak each, one motion
            return usable
        for i, (a, b) in enumerate(self.pairs):
            if (a, b) in surfaces:
                peaks, heights, errors = self.candidates_of(a, b, *surfaces[(a, b)])
                self.candidates[i] = (peaks * options.binning, heights, errors)
        if options.pairs == "auto":  # the other pairs outvote a peak a period off in one pair
            done = set(self.pairs)
            self.measure([link for link in every if link not in done])
        choice = self.choose()
        self.velocity = choice.velocity
        self.rhs = [(choice.displacements[i], float(self.candidates[i][2][choice.index[i]]))
                    if choice.resolved[i] else None for i in range(len(self.pairs))]
        seen = np.zeros_like(usable)
        for (a, b), kept in zip(self.pairs, self.rhs):
            if kept is not None:
                seen[[a, b]] = True
        return usable & (seen | (np.arange(len(usable)) == ref))

    def rival(self) -> bool:
        """Some frame's correlation with the reference frame has a second peak above ``ambiguous``."""
        return max(self.ambiguity.values(), default=0.0) > self.images.options.ambiguous

    def error(self) -> np.ndarray:
        """(K,) the mean error of each frame's registrations kept (NaN: none)."""
        errs = {}
        for (a, b), kept in zip(self.pairs, self.rhs):
            if kept is not None:
                errs.setdefault(a, []).append(kept[1])
                errs.setdefault(b, []).append(kept[1])
        return np.array([np.mean(errs[k]) if k in errs else np.nan for k in range(len(self.images.frames))])

    def solve(self, usable: np.ndarray) -> np.ndarray:
        """(K, 2) each usable frame's displacement from the reference frame (NaN for the others): the
        least-squares solution of the pairs, registrations that disagree with the others by more than
        :data:`OUTLIER_PX` (a failed peak) dropped and the system solved again."""
        K, reference_frame = len(self.images.frames), self.reference_frame
        raw = np.full((K, 2), np.nan)
        raw[reference_frame] = 0.0
        others = [int(k) for k in np.flatnonzero(usable) if k != reference_frame]
        if not others:
            return raw
        rows = [(a, b, kept[0]) for (a, b), kept in zip(self.pairs, self.rhs)
                if kept is not None and usable[a] and usable[b]]
        M = np.zeros((len(rows), K))
        for i, (a, b, _) in enumerate(rows):
            M[i, b], M[i, a] = 1.0, -1.0
        M, rhs = M[:, others], np.array([d for _, _, d in rows]).reshape(-1, 2)
        keep = np.ones(len(rows), bool)
        for _ in range(4):
            sol, *_ = np.linalg.lstsq(M[keep], rhs[keep], rcond=None)  # the reference frame is held at 0
            residual = np.abs(M @ sol - rhs).max(axis=1)
            bad = residual > max(OUTLIER_PX, 4.0 * float(np.median(residual[keep])))
            if not (bad & keep).any() or np.linalg.matrix_rank(M[keep & ~bad]) < len(others):
                break
            keep &= ~bad
        raw[others] = sol
        return raw


def usable_frames(levels: np.ndarray) -> np.ndarray:
    """(K,) bool: the frames with signal enough to register (:data:`MIN_SIGNAL_SHARE` of the brightest)."""
    usable = levels >= MIN_SIGNAL_SHARE * max(float(levels.max()), 1e-30)
    if usable.sum() < 1:
        raise ValueError("no frame of the sequence has signal to register")
    return usable


def pick_reference(levels: np.ndarray, usable: np.ndarray, reference_frame: int | None) -> int:
    """The frame the others are registered to: ``reference_frame`` (checked), or the brightest usable one of
    the middle three."""
    K = len(levels)
    if reference_frame is None:
        middle = [k for k in range(max(0, K // 2 - 1), min(K, K // 2 + 2)) if usable[k]]
        reference_frame = max(middle or list(np.flatnonzero(usable)), key=lambda k: levels[k])
    if not 0 <= reference_frame < K or not usable[reference_frame]:
        raise ValueError(f"reference_frame {reference_frame} is not a usable frame of the {K}")
    return reference_frame


def pair_lists(usable: np.ndarray, reference_frame: int, options: GlobalOptions) -> tuple[list, list, list]:
    """Every pair of usable frames at most ``max_gap`` apart, the pairs with the reference frame, and those of
    the first round (:attr:`GlobalOptions.pairs`)."""
    idx = np.flatnonzero(usable)
    every = [(int(a), int(b)) for i, a in enumerate(idx) for b in idx[i + 1:] if b - a <= options.max_gap]
    to_reference = [(min(reference_frame, int(k)), max(reference_frame, int(k))) for k in idx if k != reference_frame]
    links = every if options.pairs == "all" or (options.pairs == "auto" and not options.fit) else to_reference
    return every, to_reference, links


def translation_estimate(registered: PairRegistrations, raw: np.ndarray, usable: np.ndarray) -> MotionEstimate:
    """The translation estimate from each usable frame's displacement ``raw`` to the reference frame: with
    ``robust``, each checked against its tiles (:func:`~specgpu.motion.tiles.dominant_translation`) where the
    fitted peak saw a rival (then every frame, since a second motion is the scene's, not one frame's: an object's
    peak can fall just below the threshold in the frame where it is nearest the background's, and take that
    frame's estimate over) or was not looked at; always with the DFT. Then the frames not usable filled in time,
    and the displacements taken from the reference time."""
    images, options, reference_frame = registered.images, registered.images.options, registered.reference_frame
    raw = raw.copy()
    if options.robust:
        reference_tiles = {}
        rival = registered.rival()
        for k in np.flatnonzero(usable):
            if k != reference_frame and (not options.fit or rival or int(k) not in registered.ambiguity):
                raw[k] = dominant_translation(images.gradient(reference_frame), images.gradient(int(k)), raw[k],
                                              options.upsample, options.cutoff, options.tiles,
                                              reference_tiles if options.fit else None)
    raw = fill_in_time(raw, usable)
    return MotionEstimate(raw - at_reference_time(raw), usable, registered.error(), int(reference_frame),
                          "translation", images.kept())


@one_blas_thread
def estimate_global_motion(frames: ArrayLike, dark: ArrayLike | None = None, gain: ArrayLike | None = None, *,
                           reference_frame: int | None = None,
                           upsample: int = 10, binning: int = 1, pairs: str = "auto", cutoff: float = 0.12,
                           max_gap: int = 8, model: str = "translation", tiles: int = 4,
                           robust: bool = True, peak: str = "fit",
                           ambiguous: float = AMBIGUOUS_PEAK,
                           max_speed: float | None = MAX_SPEED_PX_PER_FRAME, gradients=None,
                           prior_velocity=None) -> MotionEstimate:
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
        (:func:`specgpu.motion.registration.fit_peak`; the weighted surface is a Gaussian, so this is exact to
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
        displacement per pixel: :mod:`specgpu.motion.flow`, from this estimate.)
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
        The frames' gradient images already made (:func:`~specgpu.motion.images.gradient_image`; K entries, None
        where one is to be made here; e.g. on the device, :func:`~specgpu.motion.images.frame_gradients`):
        registered as they are.
    prior_velocity : array_like, (2,), optional
        The velocity (x, y, px per frame) expected, e.g. the previous sequence's; default zero. Where a
        correlation has rival peaks (a scene that repeats itself), each frame's displacement is the candidate on
        the steady motion most frames agree on (:func:`specgpu.motion.candidates.choose_candidates`), and, where
        candidates agree equally, on the one whose velocity is nearest this.

    Returns
    -------
    MotionEstimate
        Each frame's displacement from the position at the reference time (the middle frame's for odd K, the mean
        of the middle two's for even K); a frame too dark to register (below :data:`MIN_SIGNAL_SHARE` of the
        brightest) is interpolated linearly in time.
    """
    options = GlobalOptions(upsample=int(upsample), binning=binning, pairs=pairs, cutoff=cutoff, max_gap=max_gap,
                            model=model, tiles=tiles, robust=robust, peak=peak, ambiguous=ambiguous,
                            max_speed=max_speed)
    return estimate_with_options(frames, dark, gain, options, reference_frame=reference_frame, gradients=gradients,
                                 prior_velocity=prior_velocity)


def estimate_with_options(frames: ArrayLike, dark, gain, options: GlobalOptions, *, reference_frame: int | None = None,
                          gradients=None, prior_velocity=None) -> MotionEstimate:
    """:func:`estimate_global_motion` with its keywords in ``options``."""
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (K, H, W), got shape {frames.shape}")
    options.check()
    images = SequenceImages(frames, dark, gain, options, gradients)
    levels = images.levels()
    usable = usable_frames(levels)
    reference_frame = pick_reference(levels, usable, reference_frame)
    registered = PairRegistrations(images, reference_frame, prior_velocity)
    every, to_reference, links = pair_lists(usable, reference_frame, options)
    registered.measure(links, first_round=True)
    if registered.beyond:  # a motion faster than the reach: looked for anywhere (BEYOND_REACH)
        return estimate_with_options(frames, images.dark, gain, replace(options, max_speed=None),
                                     reference_frame=reference_frame, gradients=images.kept(),
                                     prior_velocity=prior_velocity)
    usable = registered.resolve(usable, every)  # rival peaks: the candidates on a steady motion
    raw = registered.solve(usable)
    if options.model == "translation":
        return translation_estimate(registered, raw, usable)
    return affine_estimate(raw, usable, registered.error(), reference_frame, images.gradient, options.upsample,
                           options.cutoff, options.tiles, images.kept())
