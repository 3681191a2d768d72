"""Drift correction at capture: a reference white in the field, and an ambient frame per sequence.

Between calibration and capture the lamp's output and colour change and the light guide's edge moves (a
``[drift]`` on the twin; hours of running on a bench). Calibration cannot know it; the scene can show it:

- **Reference white** (``specgpu recover SEQ --white-roi X,Y,W,H [--white-reflectance VALUE|CSV]``): a patch of
  known reflectance in the field. For every pattern ``k`` of a sequence the measured output on the patch
  ``O_k`` (dark-subtracted, flat-fielded, mean over the ROI) is compared with what the calibrated model predicts
  for that reflectance, ``P_k = F_k . rho_white``; the sequence's decoder is rescaled column by column,
  ``A'[:, k] = A[:, k] * P_k / O_k``. This corrects any change of each pattern's power: lamp output exactly,
  colour temperature and cut-on edge to first order (exactly for narrow bands; for a broad pattern the change of
  shape inside the band is left). Cost: no frame; the ROI's pixels (not part of the scene measured) and the
  ROI's noise (averaged over its pixels: negligible for a ROI of a few hundred pixels), and the accuracy of the
  white's reflectance (a 1 % error in it is a 1 % scale error of every recovered reflectance).
- **Ambient frame** (``specgpu plan ... --ambient``; the default where the calibration found light on the object
  with every mirror off, or could not tell: :func:`ambient_needed`): one more pattern per sequence with every
  mirror off. Its frame (camera dark + room light + the DMD's off-state background, all on this scene) replaces the
  calibration's dark level for that sequence, so light that does not come from the mirrors on is removed where
  it is, on the scene. Cost: one frame per sequence (K -> K + 1: 1/K more time, 3 % for narrowband-31, 11 % for
  symmetric-9) and the ambient frame's temporal noise, added once more to every pattern's output (variance
  of dark-level noise doubles: a few tenths of a DN on a 10-bit camera).
- **Drift probe** (``specgpu plan ... --drift-probe NM``, repeatable): one more narrow band per sequence that the
  plan's decoder does not use; only the reference white's colour fit reads it (the re-fitted decoder may read its
  frame too). A sequence of a few broad patterns (the tristimulus imager's 3) gives the white 3 numbers, each
  carrying the frame's own power fluctuation (about 2 % at the tristimulus exposure): too few to tell a cut-on
  shift from a colour-temperature change. Probes at 430 nm (the guide's cut-on) and 650 nm make the fit
  over-determined at both ends. Cost: one frame per probe per sequence (tristimulus 3 + 2 probes + ambient -> 6
  frames). Lab, drift -200 K / -3 % / +5 nm, white ROI in both runs (``tools/studies/drift_study.py --draws 3 --probes
  430,650``): tristimulus dE00 0.26 against 0.23 without drift (1.13x); one probe at 430 nm 0.33 (1.43x); none
  0.43 (1.87x).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.numerics import live_gain
from specgpu.planning.plans import _band_masks

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan

__all__ = ["ambient_needed", "with_ambient_frame", "ambient_index", "subtracting_ambient", "with_drift_probes",
           "probe_indices", "parse_roi",
           "white_reflectance_curve", "white_gains", "gain_noise", "corrected_decoder", "WhiteReference",
           "DEFAULT_WHITE_REFLECTANCE"]

#: Reflectance of the reference white when none is given (a pressed-PTFE standard's certificate value).
DEFAULT_WHITE_REFLECTANCE = 0.99


def ambient_needed(bundle) -> tuple[bool, str]:
    """Whether plans made from ``bundle`` need an ambient frame by default, and why (one clause).

    Calibration measures the dark level with every mirror off on its white; on a bench where the object also gets
    light with every mirror off (room light, the DMD's off-state background) that level holds the white's share
    of it, too much for every darker object (the calibration's step (6)). Only a bundle that measured the
    camera's own dark (a capped lens) and found no such light is trusted without an ambient frame."""
    found = bundle.mirrors_off_light
    if found is False:
        return False, "the calibration found no light with every mirror off"
    if found is None:
        return True, "the calibration could not tell the camera's dark from light with every mirror off"
    frac = bundle.reports.get("mirrors_off_fraction")
    share = f" ({float(frac):.1%} of its weakest band's signal)" if isinstance(frac, (int, float)) else ""
    return True, f"the calibration found light on the object with every mirror off{share}"


def with_ambient_frame(plan: Plan):
    """The plan with one more pattern, every mirror off, at the end of its sequence (the ambient frame).

    The decoder gets a zero column for it; :func:`ambient_index` finds it again (``params["ambient_frame"]``).
    """
    if ambient_index(plan) is not None:
        return plan
    k = plan.K
    return replace(plan, patterns=np.vstack([plan.patterns, np.zeros((1, plan.patterns.shape[1]), np.int32)]),
                   target_spectra=np.vstack([plan.target_spectra, np.zeros((1, plan.target_spectra.shape[1]))]),
                   A=np.hstack([plan.A, np.zeros((plan.A.shape[0], 1))]),
                   expected_level=np.append(plan.expected_level, 0.0),
                   params={**plan.params, "ambient_frame": k})


#: Centres (nm) and width of the default drift probes: the light guide's cut-on edge, where its shift shows most,
#: and the red end, where a colour-temperature change shows most.
DEFAULT_PROBE_NM = (430.0, 650.0)
PROBE_BANDWIDTH_NM = 20.0


def with_drift_probes(plan: Plan, bundle: CalibrationBundle, centres: ArrayLike = DEFAULT_PROBE_NM,
                      bandwidth_nm: float = PROBE_BANDWIDTH_NM):
    """The plan with a narrow band per ``centres`` (nm) appended to its sequence (drift probes, see the module
    docstring); the decoder gets zero columns for them (``params["drift_probes"]`` lists their indices).

    Each probe's mirrors are thinned so that a white gives it at most the plan's brightest frame's level (it
    never saturates where the plan does not). Apply before :func:`with_ambient_frame`.
    """
    if probe_indices(plan):
        return plan
    if ambient_index(plan) is not None:
        raise ValueError("add drift probes before the ambient frame")
    c = np.asarray(centres, np.float64).reshape(-1)
    lo, hi = float(bundle.column_wavelengths.min()), float(bundle.column_wavelengths.max())
    if c.size < 1 or not np.all(np.isfinite(c)) or np.any((c < lo) | (c > hi)):
        raise ValueError(f"--drift-probe centres must lie within the light's {lo:.0f}-{hi:.0f} nm, got {c.tolist()}")
    if not 0 < bandwidth_nm <= 100:
        raise ValueError(f"drift probe bandwidth must lie in (0, 100] nm, got {bandwidth_nm!r}")
    masks = _band_masks(bundle, c, float(bandwidth_nm))
    full = np.where(masks, bundle.rows, 0).astype(np.int32)
    grid = bundle.wavelengths
    white = bundle.forward_matrix(full, grid, plan.exposure_s).sum(axis=1)
    brightest = float(bundle.forward_matrix(plan.patterns, grid, plan.exposure_s).sum(axis=1).max())
    scale = np.minimum(1.0, brightest / np.maximum(white, 1e-30))
    pats = np.where(masks, np.maximum(1, np.floor(bundle.rows * scale[:, None])), 0).astype(np.int32)
    level = float(np.max(plan.expected_level)) / max(brightest, 1e-30)
    levels = bundle.forward_matrix(pats, grid, plan.exposure_s).sum(axis=1) * level
    k = plan.K
    return replace(plan, patterns=np.vstack([plan.patterns, pats]),
                   target_spectra=np.vstack([plan.target_spectra, bundle.emitted(pats)]),
                   A=np.hstack([plan.A, np.zeros((plan.A.shape[0], pats.shape[0]))]),
                   expected_level=np.append(plan.expected_level, levels),
                   params={**plan.params, "drift_probes": list(range(k, k + pats.shape[0])),
                           "drift_probe_nm": c.tolist()})


def probe_indices(plan) -> list[int]:
    """Indices of the plan's drift probes (frames the decoder does not use), or []."""
    idx = plan.params.get("drift_probes") if isinstance(plan.params, dict) else None
    return [int(i) for i in idx] if idx else []


def ambient_index(plan) -> int | None:
    """Index of the plan's ambient frame (every mirror off), or None."""
    i = plan.params.get("ambient_frame") if isinstance(plan.params, dict) else None
    if i is None:
        return None
    i = int(i)
    if not 0 <= i < plan.K or np.any(plan.patterns[i] != 0):
        raise ValueError(f"plan's ambient frame {i} is not an all-off pattern of its {plan.K}")
    return i


def subtracting_ambient(rows, ambient: int | None) -> np.ndarray:
    """(R, K) float64: decoder ``rows`` (R, K) that read each frame above the ambient frame ``ambient`` (None:
    ``rows`` as they are): its column becomes minus the sum of the others, ``y = sum_k A_k (s_k - s_a)``. A decoding
    that samples each frame where it saw the pixel (a moving scene) subtracts the ambient frame so, its sample taken
    where it saw the pixel too, instead of from the frames on fixed pixels."""
    R = np.array(rows, np.float64, copy=True)
    if ambient is None:
        return R
    R[:, ambient] = 0.0
    R[:, ambient] = -R.sum(axis=1)
    return R


def parse_roi(text, frame_shape, name: str = "--white-roi") -> tuple[int, int, int, int]:
    """``"X,Y,W,H"`` (pixels, origin top left) checked to lie inside a (H, W) frame; one-line errors."""
    parts = str(text).split(",") if not isinstance(text, (tuple, list)) else list(text)
    try:
        x, y, w, h = (int(str(p).strip()) for p in parts)
    except ValueError:
        raise ValueError(f"{name} must be X,Y,W,H in whole pixels, got {text!r}") from None
    fh, fw = frame_shape
    if w < 1 or h < 1:
        raise ValueError(f"{name} {x},{y},{w},{h}: width and height must be >= 1")
    if x < 0 or y < 0 or x + w > fw or y + h > fh:
        raise ValueError(f"{name} {x},{y},{w},{h} lies outside the {fw} x {fh} frame")
    return x, y, w, h


def white_reflectance_curve(value, wavelengths) -> np.ndarray:
    """The white's reflectance on ``wavelengths``: a number (flat) or a two-column CSV (wavelength nm, value)."""
    wl = np.asarray(wavelengths, np.float64)
    if value is None:
        value = DEFAULT_WHITE_REFLECTANCE
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        r = float(value)
    else:
        text = str(value)
        try:
            r = float(text)
        except ValueError:
            r = None
        if r is None:
            path = Path(text)
            if not path.is_file():
                raise ValueError(f"--white-reflectance {text!r} is neither a number nor a CSV file")
            try:
                data = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
            except ValueError as exc:
                raise ValueError(f"{path}: cannot read a two-column CSV of reflectance ({exc})") from None
            if data.shape[1] < 2 or data.shape[0] < 2 or np.any(np.diff(data[:, 0]) <= 0):
                raise ValueError(f"{path}: need two columns (wavelength nm increasing, reflectance)")
            if np.any(data[:, 1] <= 0) or np.any(data[:, 1] > 1.5) or not np.all(np.isfinite(data)):
                raise ValueError(f"{path}: reflectance must lie in (0, 1.5]")
            return np.interp(wl, data[:, 0], data[:, 1])
    if not 0 < r <= 1.5:
        raise ValueError(f"--white-reflectance must lie in (0, 1.5], got {r:g}")
    return np.full(wl.shape, r)


def white_gains(frames, plan, bundle, roi, white=None, *, dark=None) -> np.ndarray:
    """(K,) measured / predicted output of each pattern on the reference white in ``roi`` for one sequence.

    ``frames`` (K, H, W) raw; ``dark`` (H, W) the level to subtract (the calibration's at the plan's exposure by
    default). The ambient frame's gain is 1. Raises a one-line ``ValueError`` when the ROI has a saturated pixel
    in any frame, or when a pattern gives no signal on it. (One sequence of :meth:`WhiteReference.gains`.)
    """
    frames = np.asarray(frames)
    return WhiteReference(plan, bundle, roi, white, frame_shape=frames.shape[1:]).gains(frames, dark=dark)


#: Relative change of the fitted spectral ratio across 420-680 nm below which the light is taken to have changed
#: only in power (the frame-to-frame fluctuation, 0.3-0.9 % per frame, tilts a fit by about 1 %).
MIN_COLOUR_CHANGE = 0.02


#: How far (in standard deviations of its chi-square) the white's gains must depart from one common power change,
#: given the light's measured frame-to-frame fluctuation, before a colour change is fitted.
COLOUR_SIGNIFICANCE = 3.0


def gain_noise(plan, bundle, sequences: int = 1) -> float | None:
    """Relative standard deviation of one white gain from the light's own frame-to-frame fluctuation, at the plan's
    exposure, averaged over ``sequences``: the calibration's measurement (``reports["light_fluctuation"]`` at its
    exposure) scaled as ``sqrt(t_cal / t)`` (fluctuation faster than a frame averages over the exposure). None
    when the bundle did not measure it."""
    rep = bundle.reports if isinstance(bundle.reports, dict) else {}
    f, t = rep.get("light_fluctuation"), rep.get("light_fluctuation_exposure_s")
    if not f or not t:
        return None
    return float(f) * float(np.sqrt(float(t) / plan.exposure_s)) / float(np.sqrt(max(1, int(sequences))))


def corrected_decoder(plan: Plan, gains: ArrayLike, bundle: CalibrationBundle | None = None, white=None, *,
                      sequences: int = 1) -> np.ndarray:
    """The plan's decoder corrected for one sequence's white gains.

    Without ``bundle``: each column rescaled, ``A[:, k] / gains[k]`` (exact for a change of each pattern's power).
    With it, the light's change is first modelled as a smooth spectral ratio ``r(lambda) = exp(a0 + a1 u + a2 u^2)``
    (``u = (lambda - 550) / 150``; as many terms as the lit patterns allow, at most 3) fitted to the gains; the
    decoder is re-fitted so that it gives on the drifted light what it gave on the calibrated one for a set of
    smooth reflectances, ``A' = (A F R) (F diag(r) R)^+`` (``F`` the calibrated forward model, ``R`` smooth
    bumps): this follows a change of shape inside a broad pattern. What the smooth ratio leaves (a cut-on edge
    moving inside one narrow band) is then taken out column by column, as without ``bundle``. A ratio flatter
    than :data:`MIN_COLOUR_CHANGE` across 420-680 nm is taken as a power change only (column scaling), and so are
    gains whose spread about their mean is within the light's own fluctuation (:func:`gain_noise`, ``sequences``
    the number of sequences whose mean ``gains`` are): chi-square below its degrees of freedom plus
    :data:`COLOUR_SIGNIFICANCE` standard deviations.
    (One sequence of :meth:`WhiteReference.decoder`.)
    """
    g = np.asarray(gains, np.float64)
    if bundle is None:
        return plan.A / g[None, :]
    return WhiteReference(plan, bundle, None, white).decoder(g, sequences=sequences)


class WhiteReference:
    """The reference-white correction of one plan and calibration, with everything that does not depend on the
    frames computed once (the forward model on the calibration's grid, the white's predicted outputs, the smooth
    reflectances and what the decoder gives on them): a stream applies it to every sequence at a small host cost.

    :func:`white_gains` and :func:`corrected_decoder` are one sequence of it, so ``specgpu recover --white-roi``
    and ``specgpu stream --white-roi`` give the same decoder for the same frames.

    Parameters
    ----------
    plan, bundle
        The plan and the calibration it was made from.
    roi : str or (x, y, w, h), optional
        The white's region (``"X,Y,W,H"``), checked against ``frame_shape`` (None: :meth:`decoder` only).
    white : float or path, optional
        The white's reflectance (:func:`white_reflectance_curve`; 0.99 by default).
    frame_shape : (H, W), optional
        Default: the calibration's dark frame's.
    """

    def __init__(self, plan: Plan, bundle: CalibrationBundle, roi=None, white=None, *, frame_shape=None):
        self.plan, self.bundle, self.white = plan, bundle, white
        shape = tuple(np.shape(bundle.dark)[-2:]) if frame_shape is None else tuple(frame_shape)
        self.roi = None if roi is None else parse_roi(roi, shape)
        grid = bundle.wavelengths
        self.F = bundle.forward_matrix(plan.patterns, grid, plan.exposure_s)  # (K, G)
        self.rho = white_reflectance_curve(white, grid)
        self.predicted = self.F @ self.rho
        self.lit = self.predicted > 1e-6 * max(float(self.predicted.max()), 1e-30)
        amb = ambient_index(plan)
        self.lit_gain = self.lit.copy()
        if amb is not None:
            self.lit_gain[amb] = False
        self.u = (grid - 550.0) / 150.0
        self.n_par = int(min(3, max(0, self.lit.sum() - 1)))
        self.basis = np.stack([self.u**i for i in range(self.n_par)], axis=0)  # (P, G)
        self.visible = (grid >= 420.0) & (grid <= 680.0)
        self._bumps = None
        self._target = None

    def gains(self, frames: ArrayLike, *, dark: ArrayLike | None = None) -> np.ndarray:
        """(K,) gains of one sequence's frames (K, H, W) (see :func:`white_gains`)."""
        if self.roi is None:
            raise ValueError("this white reference has no --white-roi")
        plan, bundle = self.plan, self.bundle
        x, y, w, h = self.roi
        sl = (slice(y, y + h), slice(x, x + w))
        patch = np.asarray(frames)[(slice(None), *sl)]
        if patch.shape[1:] != (h, w):
            raise ValueError(f"--white-roi {x},{y},{w},{h} lies outside the {frames.shape[2]} x {frames.shape[1]} "
                             "frame")
        over = np.any(patch >= bundle.max_code, axis=(1, 2))
        if np.any(over):
            k = int(np.flatnonzero(over)[0])
            raise ValueError(f"--white-roi {x},{y},{w},{h} is saturated in frame {k}: choose a darker white or a "
                             f"shorter exposure")
        d = bundle.dark_at(plan.exposure_s) if dark is None else np.asarray(dark)
        flat = live_gain(bundle.flat_field[sl])  # a dead pixel in the ROI is left out of the white's mean
        if not np.isfinite(flat).any():
            raise ValueError(f"--white-roi {x},{y},{w},{h} holds only dead pixels (no response in the calibration)")
        measured = np.array([float(np.nanmean((patch[k] - d[sl]) * flat)) for k in range(patch.shape[0])])
        predicted, lit = self.predicted, self.lit_gain
        gains = np.ones(patch.shape[0])
        bad = lit & ~(measured > 0.02 * predicted)
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"--white-roi {x},{y},{w},{h} gives no signal in frame {k} (is the white in the ROI?)")
        gains[lit] = measured[lit] / predicted[lit]
        return gains

    def _fit_ratio(self, log_g) -> np.ndarray:
        """Coefficients ``a`` of the smooth ratio ``exp(a . u^i)`` whose predicted log-gains of the lit patterns fit
        ``log_g`` in least squares: Gauss-Newton with step halving on the analytic Jacobian (a 1-3 parameter fit,
        converged to 1e-12 in a few iterations: a stream pays it per sequence)."""
        F, rho, basis = self.F[self.lit], self.rho, self.basis
        log_base = np.log(self.predicted[self.lit])

        def model(a):
            w = np.exp(a @ basis) * rho
            o = F @ w
            return np.log(o) - log_base - log_g, w, o

        a = np.zeros(self.n_par)
        res, w, o = model(a)
        cost = float(res @ res)
        for _ in range(100):
            J = (F @ (w[:, None] * basis.T)) / o[:, None]  # d log o_k / d a_j
            step = np.linalg.lstsq(J, -res, rcond=None)[0]
            t = 1.0
            while t > 1e-6:
                trial = model(a + t * step)
                new_cost = float(trial[0] @ trial[0])
                if new_cost <= cost:
                    break
                t *= 0.5
            else:
                break
            a = a + t * step
            res, w, o = trial
            done = cost - new_cost <= 1e-15 * max(cost, 1e-30) or float(np.max(np.abs(t * step))) < 1e-12
            cost = new_cost
            if done:
                break
        return a

    def decoder(self, gains: ArrayLike, *, sequences: int = 1) -> np.ndarray:
        """The plan's decoder corrected for gains, one sequence's or the mean of ``sequences`` (see
        :func:`corrected_decoder`)."""
        plan, F, rho, base, lit = self.plan, self.F, self.rho, self.predicted, self.lit
        g = np.asarray(gains, np.float64)
        if self.n_par == 0:
            return plan.A / g[None, :]
        sigma = gain_noise(plan, self.bundle, sequences)
        if sigma:
            dev = np.log(g[lit]) - np.log(g[lit]).mean()
            dof = int(lit.sum()) - 1
            if float(np.sum(dev**2)) / sigma**2 <= dof + COLOUR_SIGNIFICANCE * np.sqrt(2.0 * dof):
                return plan.A / g[None, :]  # one power change and the frames' own fluctuation: per-pattern scaling
        a = self._fit_ratio(np.log(g[lit]))
        basis = self.basis
        r = np.exp(a @ basis)
        visible = self.visible
        if float(r[visible].max() / r[visible].min()) - 1.0 < MIN_COLOUR_CHANGE:
            return plan.A / g[None, :]  # no colour change beyond the frames' own fluctuation: per-pattern scaling
        if self._bumps is None:
            grid = self.bundle.wavelengths
            self._bumps = np.stack([np.exp(-0.5 * ((grid - c) / 20.0) ** 2) for c in np.arange(380.0, 781.0, 10.0)]
                                   + [np.ones_like(grid)], axis=1)  # (G, N) smooth reflectances
            self._target = plan.A @ (F @ self._bumps)  # what the decoder gives on the calibrated light
        drifted = F @ (r[:, None] * self._bumps)  # (K, N) the outputs on the drifted light
        A_new = self._target @ np.linalg.pinv(drifted, rcond=1e-3)
        predicted = (F @ (r * rho)) / np.where(lit, base, 1.0)
        residual = np.where(lit, g / np.where(lit, predicted, 1.0), 1.0)
        return A_new / residual[None, :]
