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
- **Ambient frame** (``specgpu plan ... --ambient``): one more pattern per sequence with every mirror off. Its
  frame (camera dark + room light + the DMD's off-state background, all on this scene) replaces the
  calibration's dark level for that sequence, so light that does not come from the mirrors on is removed where
  it is, on the scene. Cost: one frame per sequence (K -> K + 1: 1/K more time, 3 % for narrowband-31, 11 % for
  symmetric-9) and the ambient frame's temporal noise, added once more to every pattern's output (variance
  of dark-level noise doubles: a few tenths of a DN on a 10-bit camera).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["with_ambient_frame", "ambient_index", "parse_roi", "white_reflectance_curve", "white_gains",
           "corrected_decoder", "WhiteReference",
           "DEFAULT_WHITE_REFLECTANCE"]

#: Reflectance of the reference white when none is given (a pressed-PTFE standard's certificate value).
DEFAULT_WHITE_REFLECTANCE = 0.99


def with_ambient_frame(plan):
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


def ambient_index(plan) -> int | None:
    """Index of the plan's ambient frame (every mirror off), or None."""
    i = plan.params.get("ambient_frame") if isinstance(plan.params, dict) else None
    if i is None:
        return None
    i = int(i)
    if not 0 <= i < plan.K or np.any(plan.patterns[i] != 0):
        raise ValueError(f"plan's ambient frame {i} is not an all-off pattern of its {plan.K}")
    return i


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


def corrected_decoder(plan, gains, bundle=None, white=None) -> np.ndarray:
    """The plan's decoder corrected for one sequence's white gains.

    Without ``bundle``: each column rescaled, ``A[:, k] / gains[k]`` (exact for a change of each pattern's power).
    With it, the light's change is first modelled as a smooth spectral ratio ``r(lambda) = exp(a0 + a1 u + a2 u^2)``
    (``u = (lambda - 550) / 150``; as many terms as the lit patterns allow, at most 3) fitted to the gains; the
    decoder is re-fitted so that it gives on the drifted light what it gave on the calibrated one for a set of
    smooth reflectances, ``A' = (A F R) (F diag(r) R)^+`` (``F`` the calibrated forward model, ``R`` smooth
    bumps): this follows a change of shape inside a broad pattern. What the smooth ratio leaves (a cut-on edge
    moving inside one narrow band) is then taken out column by column, as without ``bundle``. A ratio flatter
    than :data:`MIN_COLOUR_CHANGE` across 420-680 nm is taken as a power change only (column scaling).
    (One sequence of :meth:`WhiteReference.decoder`.)
    """
    g = np.asarray(gains, np.float64)
    if bundle is None:
        return plan.A / g[None, :]
    return WhiteReference(plan, bundle, None, white).decoder(g)


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

    def __init__(self, plan, bundle, roi=None, white=None, *, frame_shape=None):
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

    def gains(self, frames, *, dark=None) -> np.ndarray:
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
        flat = bundle.flat_field[sl]
        measured = np.array([float(np.mean((patch[k] - d[sl]) * flat)) for k in range(patch.shape[0])])
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

    def decoder(self, gains) -> np.ndarray:
        """The plan's decoder corrected for one sequence's gains (see :func:`corrected_decoder`)."""
        plan, F, rho, base, lit = self.plan, self.F, self.rho, self.predicted, self.lit
        g = np.asarray(gains, np.float64)
        if self.n_par == 0:
            return plan.A / g[None, :]
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
