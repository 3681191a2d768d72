"""Accuracy of a recovery against a scene's ground truth: per pixel (error maps and their statistics) and, for
a chart, per patch (the paper's Tables 2 and 3).

Per patch: accuracy of a recovery against a scene's ground truth: spectral RMSE and colour differences.

A chart scene (:class:`specgpu.rig.scene.SpectralScene`) carries one boolean mask per patch. The recovered image
is averaged over each mask (the paper compares one spectrum per patch with a spectrometer reading), then:

- spectral RMSE per patch, ``sqrt(mean_lambda (R_est - R_true)^2)`` over the recovery's own wavelengths, the
  truth linearly interpolated there (paper Table 1's RMSE);
- CIELAB colour differences (CIE 1976 dE*ab, CIE 2000) per patch under an illuminant, from XYZ of the
  recovered and true spectra computed on the same wavelengths (so a method is judged on what it recovers, not
  on the range it leaves out), or from a tristimulus plan's XYZ directly against the truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.spectra import DEFAULT_CMFS, XYZ_weights, resolve_integration, white_point_XYZ
from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E, reflectance_to_XYZ
from specgpu.rig.scene import interpolation_matrix

if TYPE_CHECKING:
    from specgpu.rig.scene import SpectralScene

__all__ = ["METRICS", "PatchReport", "patch_means", "rmse_per_patch", "delta_E_per_patch", "evaluate_reflectance",
           "evaluate_XYZ", "true_patch_spectra", "PixelReport", "truth_cube", "scene_XYZ", "evaluate_pixels",
           "evaluation_illuminant", "evaluation_integration", "PLAUSIBLE_RANGE", "EXCLUSION_CAUSES",
           "screen_estimate"]


#: The error metrics of a report, in table order (``rmse`` is None for colorimetric estimates).
METRICS = ("rmse", "delta_E_ab", "delta_E_2000")

#: The values an estimate's channel may plausibly take, inclusive: a reflectance, or XYZ with Y = 1 for the
#: perfect white. Wider than a true scene's reflectance (at most 1.5): ten times the white covers fluorescence,
#: specular highlights and noise on top, minus one the noise of a dark pixel; a value outside is no measurement
#: (an overflow, a corrupt file, a fill value such as 1e30), and its square or its XYZ could overflow float32.
PLAUSIBLE_RANGE = (-1.0, 10.0)

#: Why a pixel is left out of the scores, in report order: NaN in any channel (the recovery flagged it:
#: saturated, seen outside the field), an infinite value, a finite value outside :data:`PLAUSIBLE_RANGE`, or an
#: estimate that is valid but whose error is not finite (the truth holds NaN there).
EXCLUSION_CAUSES = ("flagged", "non_finite", "out_of_range", "unscored")


def screen_estimate(estimate, *, invalid: str = "exclude", name: str = "the estimate") -> tuple[np.ndarray, dict]:
    """The pixels of an estimate that can be scored, and why the others cannot.

    Parameters
    ----------
    estimate : array_like, (H, W, C)
        Reflectance or XYZ.
    invalid : {"exclude", "refuse"}
        What to do with a pixel holding an infinite value or one outside :data:`PLAUSIBLE_RANGE` (a recovery
        writes neither: it flags a pixel it cannot recover as NaN): leave it out and count it, or refuse the
        estimate.
    name : str
        How a refusal names the estimate (its file).

    Returns
    -------
    valid : numpy.ndarray
        (H, W) bool, the pixels every channel of which is finite and plausible.
    counts : dict
        ``{cause: pixels}`` for ``flagged``, ``non_finite`` and ``out_of_range`` (each pixel counted once, under
        the first cause that applies).

    Raises
    ------
    ValueError
        ``invalid="refuse"`` and some pixel is infinite or out of range: one line naming ``name`` and both counts.
    """
    if invalid not in ("exclude", "refuse"):
        raise ValueError(f"invalid must be 'exclude' or 'refuse', got {invalid!r}")
    est = np.asarray(estimate)
    if est.ndim != 3:
        raise ValueError(f"{name}: an estimate must be (H, W, C), got shape {est.shape}")
    lo, hi = PLAUSIBLE_RANGE
    flagged = np.isnan(est).any(axis=-1)
    non_finite = np.isinf(est).any(axis=-1) & ~flagged
    out_of_range = ((est < lo) | (est > hi)).any(axis=-1) & ~flagged & ~non_finite
    counts = {"flagged": int(flagged.sum()), "non_finite": int(non_finite.sum()),
              "out_of_range": int(out_of_range.sum())}
    if invalid == "refuse" and counts["non_finite"] + counts["out_of_range"]:
        raise ValueError(f"{name}: {counts['non_finite'] + counts['out_of_range']} pixels hold values no recovery "
                         f"writes ({counts['non_finite']} infinite, {counts['out_of_range']} outside the plausible "
                         f"range {lo:g} to {hi:g}), first at row {_first(non_finite | out_of_range)}; a pixel that "
                         "cannot be recovered is NaN (evaluate --exclude-invalid leaves them out, counted)")
    return ~(flagged | non_finite | out_of_range), counts


def _first(mask) -> str:
    """'y, column x' of the first true pixel of an (H, W) mask."""
    y, x = np.argwhere(mask)[0]
    return f"{int(y)}, column {int(x)}"


def _present_metrics(report) -> dict:
    """``{metric: values}`` of the metrics a report holds."""
    return {key: getattr(report, key) for key in METRICS if getattr(report, key) is not None}


@dataclass(frozen=True)
class PatchReport:
    """Per-patch metrics.

    Attributes
    ----------
    names : tuple of str
        Patch names, in mask order.
    rmse : numpy.ndarray or None
        (P,) spectral RMSE (reflectance units), None for colorimetric outputs.
    delta_E_ab : numpy.ndarray
        (P,) CIE 1976 dE*ab.
    delta_E_2000 : numpy.ndarray
        (P,) CIE 2000 dE00.
    illuminant : str
        Illuminant of the colour differences.
    """

    names: tuple
    rmse: np.ndarray | None
    delta_E_ab: np.ndarray
    delta_E_2000: np.ndarray
    illuminant: str

    def summary(self) -> dict:
        """``{metric: (average, maximum)}`` over the patches."""
        return {key: (float(np.mean(v)), float(np.max(v))) for key, v in _present_metrics(self).items()}

    def worst(self, metric: str = "delta_E_ab") -> str:
        """Name of the patch with the largest value of ``metric``."""
        v = getattr(self, metric)
        if v is None:
            raise ValueError(f"this report has no {metric}")
        return self.names[int(np.argmax(v))]


def patch_means(image, masks: dict) -> tuple[tuple, np.ndarray]:
    """Mean of an (H, W, C) image over each (H, W) boolean mask; returns (names, (P, C) float64).

    Non-finite pixels (saturated or NaN recoveries) are left out of a patch's mean; a patch with no finite
    pixel is NaN.
    """
    img = np.asarray(image)
    if img.ndim != 3:
        raise ValueError(f"image must be (H, W, C), got shape {img.shape}")
    if not masks:
        raise ValueError("masks is empty: the scene has no patches to evaluate")
    names, rows = [], []
    for name, m in masks.items():
        m = np.asarray(m, bool)
        if m.shape != img.shape[:2]:
            raise ValueError(f"mask {name!r} has shape {m.shape}, the image {img.shape[:2]}")
        px = img[m].astype(np.float64)
        px = px[np.all(np.isfinite(px), axis=1)]
        rows.append(px.mean(axis=0) if px.size else np.full(img.shape[2], np.nan))
        names.append(str(name))
    return tuple(names), np.array(rows)


def true_patch_spectra(scene, wavelengths=None) -> tuple[tuple, np.ndarray]:
    """A scene's per-patch mean reflectance, optionally interpolated to ``wavelengths`` (nm); (names, (P, B))."""
    names, spectra = patch_means(scene.reflectance, scene.masks)
    if wavelengths is None:
        return names, spectra
    return names, spectra @ _resampling(scene, wavelengths).T


def rmse_per_patch(estimate, truth) -> np.ndarray:
    """(P,) root-mean-square difference over the last axis of two (P, B) spectra sets."""
    e, t = np.asarray(estimate, np.float64), np.asarray(truth, np.float64)
    if e.shape != t.shape or e.ndim != 2:
        raise ValueError(f"estimate {e.shape} and truth {t.shape} must both be (P, B)")
    return np.sqrt(np.mean((e - t) ** 2, axis=1))


def delta_E_per_patch(XYZ_estimate, XYZ_truth, illuminant="D65", observer: str = DEFAULT_CMFS, *,
                      wavelengths=None, integration: str = "rectangle") -> tuple:
    """(dE*ab, dE2000), each (P,), between two (P, 3) XYZ sets (Y = 1 for the white) under ``illuminant``, the
    white integrated on ``wavelengths`` by ``integration`` as the XYZ were
    (:func:`specgpu.core.spectra.white_point_XYZ`)."""
    a = np.asarray(XYZ_truth, np.float32)
    b = np.asarray(XYZ_estimate, np.float32)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"XYZ_estimate {b.shape} and XYZ_truth {a.shape} must both be (P, 3)")
    white = white_point_XYZ(illuminant, observer, wavelengths=wavelengths, integration=integration)
    lab_t = XYZ_to_Lab(a, white)
    lab_e = XYZ_to_Lab(b, white)
    return (np.asarray(delta_E(lab_t, lab_e, "CIE 1976"), np.float64),
            np.asarray(delta_E(lab_t, lab_e, "CIE 2000"), np.float64))


def evaluate_reflectance(cube: ArrayLike, wavelengths: ArrayLike, scene: SpectralScene, *, illuminant: str = "D65",
                         cmfs=DEFAULT_CMFS,
                         integration: str = "rectangle") -> PatchReport:
    """Per-patch RMSE and colour differences of a recovered reflectance cube against a chart scene.

    Parameters
    ----------
    cube : array_like, (H, W, B)
        Recovered reflectance (the scene's frame size).
    wavelengths : array_like, (B,)
        Evenly spaced wavelengths of the cube, nm, within the scene's range.
    scene : SpectralScene
        The truth, with patch masks.
    illuminant, cmfs, integration
        For the colour differences (XYZ on the cube's wavelengths for both, and the white of that grid).

    Returns
    -------
    PatchReport
        Per patch: RMSE, dE*ab and dE2000; ``summary()`` gives (mean, max) of each.

    Examples
    --------
    >>> import numpy as np
    >>> from specgpu.pipeline import evaluate_reflectance, truth_cube
    >>> from specgpu.rig import colorchecker_scene
    >>> scene = colorchecker_scene(24, 36)
    >>> wavelengths = np.arange(400.0, 701.0, 10.0)
    >>> report = evaluate_reflectance(truth_cube(scene, wavelengths), wavelengths, scene)
    >>> report.summary()["rmse"]
    (0.0, 0.0)
    """
    wl = np.asarray(wavelengths, np.float64)
    names, est = patch_means(cube, scene.masks)
    _, truth = true_patch_spectra(scene, wl)
    W = XYZ_weights(wl, illuminant, cmfs, integration=integration)
    dab, d00 = delta_E_per_patch(est @ W.T, truth @ W.T, illuminant, cmfs, wavelengths=wl, integration=integration)
    return PatchReport(names, rmse_per_patch(est, truth), dab, d00, str(illuminant))


def evaluate_XYZ(xyz: ArrayLike, scene: SpectralScene, *, illuminant: str = "D65", cmfs=DEFAULT_CMFS,
                 wavelengths: ArrayLike | None = None,
                 integration: str = "rectangle") -> PatchReport:
    """Per-patch colour differences of an XYZ image (a tristimulus plan's output) against a chart scene.

    The truth is the XYZ of each patch's mean reflectance under ``illuminant`` on ``wavelengths`` (the scene's
    own grid by default), integrated by ``integration``; both Labs take the white of that grid.
    """
    names, est = patch_means(xyz, scene.masks)
    if est.shape[1] != 3:
        raise ValueError(f"xyz must have 3 channels, got {est.shape[1]}")
    wl = scene.wavelengths if wavelengths is None else np.asarray(wavelengths, np.float64)
    _, truth = true_patch_spectra(scene, wl)
    W = XYZ_weights(wl, illuminant, cmfs, integration=integration)
    dab, d00 = delta_E_per_patch(est, truth @ W.T, illuminant, cmfs, wavelengths=wl, integration=integration)
    return PatchReport(names, None, dab, d00, str(illuminant))


def evaluation_integration(recorded, requested=None, *, colorimetric: bool, name: str = "the estimate") -> str:
    """The integration to judge an estimate with (as :func:`evaluation_illuminant` for the illuminant): the one
    asked for, else the one its file records, else ``"rectangle"``; an XYZ estimate made with another than the
    one asked for is refused (its truth would be integrated otherwise than it was)."""
    asked = None if requested is None else resolve_integration(requested)
    kept = resolve_integration(recorded) if isinstance(recorded, str) and recorded else None
    if asked is None:
        return kept or "rectangle"
    if colorimetric and kept and kept != asked:
        raise ValueError(f"{name} holds XYZ integrated by {kept}, not {asked}: leave --integration out to use "
                         f"{kept}")
    return asked


def evaluation_illuminant(recorded, requested=None, *, colorimetric: bool, name: str = "the estimate") -> str:
    """The illuminant to judge an estimate under, from the one its file records and the one asked for.

    Parameters
    ----------
    recorded : str or None
        The ``illuminant`` an estimate's metadata records (``specgpu recover`` writes the plan's for a tristimulus
        plan, the one of its XYZ / Lab / dE outputs otherwise); None for a file that records none.
    requested : str, optional
        The one asked for; None: the recorded one, else D65.
    colorimetric : bool
        The estimate holds XYZ (relative to its illuminant's white): judging it under another illuminant compares
        colours taken under two lights, so a contradiction is refused. A reflectance cube holds under any
        illuminant and takes the one asked for.
    name : str
        How an error names the estimate (its file).

    Raises
    ------
    ValueError
        One line naming the file and both illuminants.
    """
    if recorded is not None and (not isinstance(recorded, str) or not recorded.strip()):
        raise ValueError(f"{name}: the recorded illuminant {recorded!r} is not an illuminant name")
    if requested is None:
        return recorded or "D65"
    if colorimetric and recorded and recorded.lower() != str(requested).lower():
        raise ValueError(f"{name} holds XYZ under illuminant {recorded}, not {requested}: evaluating it under "
                         f"{requested} would compare colours taken under two lights (leave --illuminant out to use "
                         f"{recorded})")
    return str(requested)


# ---- per pixel ---------------------------------------------------------------------------------------------
@dataclass
class PixelReport:
    """Per-pixel error maps of an estimate against the truth scene (float32, (H, W)); ``rmse`` is None for
    colorimetric estimates.

    ``valid`` marks the pixels the estimate could be scored at (None: every pixel) and ``excluded`` counts the
    others by cause (see :func:`screen_estimate`); their maps are NaN. :meth:`counts` adds the pixels whose error
    came out non-finite all the same."""

    rmse: np.ndarray | None
    delta_E_ab: np.ndarray
    delta_E_2000: np.ndarray
    illuminant: str
    valid: np.ndarray | None = None
    excluded: dict | None = None

    def scored(self) -> np.ndarray:
        """(H, W) bool: the pixels where every metric is finite, the ones the statistics are over."""
        return np.logical_and.reduce([np.isfinite(v) for v in _present_metrics(self).values()])

    def counts(self) -> dict:
        """``{"pixels": total, "scored": n, "excluded": {cause: n}}``, one count per cause of
        :data:`EXCLUSION_CAUSES`; ``scored`` plus the excluded is the total."""
        scored = self.scored()
        valid = np.ones(scored.shape, bool) if self.valid is None else self.valid
        excluded = {"flagged": 0, "non_finite": 0, "out_of_range": 0, **(self.excluded or {})}
        if self.valid is None:  # maps made without screening: what is not finite was flagged
            excluded["flagged"] = int((~scored).sum())
        excluded["unscored"] = int((valid & ~scored).sum())
        return {"pixels": int(scored.size), "scored": int(scored.sum()), "excluded": excluded}

    def statistics(self) -> dict:
        """``{metric: {"mean", "median", "p95", "max"}}`` over the scored pixels (:meth:`scored`)."""
        out = {}
        scored = self.scored()
        for key, v in _present_metrics(self).items():
            v = v[scored]
            if v.size == 0:  # no valid pixel (a saturated capture): say so, do not crash
                out[key] = {"mean": float("nan"), "median": float("nan"), "p95": float("nan"), "max": float("nan")}
                continue
            out[key] = {"mean": float(v.mean()), "median": float(np.median(v)),
                        "p95": float(np.percentile(v, 95)), "max": float(v.max())}
        return out


def _resampling(scene, wavelengths) -> np.ndarray:
    """(B, B_scene) linear interpolation from the scene's bands to ``wavelengths``; a scene whose bands do not
    cover them is an error (the truth is never extrapolated)."""
    wl = np.asarray(wavelengths, np.float64)
    lo, hi = float(scene.wavelengths[0]), float(scene.wavelengths[-1])
    if wl.min() < lo - 1e-6 or wl.max() > hi + 1e-6:
        raise ValueError(f"the truth scene {scene.name!r} covers {lo:g}-{hi:g} nm, not the estimate's "
                         f"{wl.min():g}-{wl.max():g} nm")
    return interpolation_matrix(wl, scene.wavelengths)


def truth_cube(scene, wavelengths) -> np.ndarray:
    """The scene's reflectance on ``wavelengths`` (H, W, B), float32 (see :func:`_resampling`)."""
    M = _resampling(scene, wavelengths).astype(np.float32)
    return np.einsum("hwk,bk->hwb", scene.reflectance, M, optimize=True).astype(np.float32)


def scene_XYZ(scene, illuminant="D65", cmfs=DEFAULT_CMFS, *, wavelengths=None, integration: str = "rectangle",
              device=None) -> np.ndarray:
    """XYZ (Y = 1 for the white) of a scene under ``illuminant``: over the scene's own bands (its true colour), or
    over ``wavelengths`` (the truth resampled to an estimate's bands, to judge a method on what it recovers); its
    white is :func:`specgpu.core.spectra.white_point_XYZ` on the same grid."""
    if wavelengths is None:
        return reflectance_to_XYZ(scene.reflectance, scene.wavelengths, illuminant, cmfs, integration=integration,
                                  device=device)
    return reflectance_to_XYZ(truth_cube(scene, wavelengths), wavelengths, illuminant, cmfs,
                              integration=integration, device=device)


def evaluate_pixels(estimate: ArrayLike, scene: SpectralScene, *, wavelengths: ArrayLike | None = None,
                    illuminant: str = "D65", cmfs=DEFAULT_CMFS,
                    integration: str = "rectangle", device=None, invalid: str = "exclude",
                    name: str = "the estimate") -> PixelReport:
    """Per-pixel RMSE (reflectance estimates), dE*ab and dE2000 of an estimate against the truth scene.

    Parameters
    ----------
    estimate : array_like, (H, W, B) or (H, W, 3)
        Reflectance on ``wavelengths``, or XYZ (Y = 1 for white) when ``wavelengths`` is None.
    scene : SpectralScene
        The truth, of the estimate's frame size.
    illuminant, cmfs
        Of the colour differences: XYZ of the truth under ``illuminant`` on its own bands (on the estimate's
        wavelengths for a reflectance estimate, so both sides see the same sampling); both Labs take the white of
        that grid.
    integration : str
        ``"rectangle"`` (default) or ``"ASTM E308"``: how both are integrated to XYZ.
    wavelengths : array_like, (B,), optional
        Band centres of a reflectance estimate, nm; None for an XYZ estimate.
    device : optional
        OpenCL device selector.
    invalid : {"exclude", "refuse"}
        A pixel holding an infinite or implausible value (:func:`screen_estimate`): left out and counted, or a
        ValueError naming ``name``. NaN pixels (flagged by the recovery) are always left out and counted.
    name : str
        How a refusal names the estimate.

    Returns
    -------
    PixelReport
        Per-pixel maps (``rmse`` None for an XYZ estimate), NaN where a pixel was left out; ``statistics()``
        summarises them, ``counts()`` says how many pixels were scored and why the others were not.

    Examples
    --------
    An estimate one percent too reflective everywhere has an RMSE of 0.01 at every pixel:

    >>> import numpy as np
    >>> from specgpu import pipeline, rig
    >>> chart, grid = rig.colorchecker_scene(24, 36), np.arange(400.0, 701.0, 10.0)
    >>> maps = pipeline.evaluate_pixels(pipeline.truth_cube(chart, grid) + 0.01, chart, wavelengths=grid)
    >>> maps.rmse.shape, round(float(np.median(maps.rmse)), 4)
    ((24, 36), 0.01)
    """
    est = np.asarray(estimate, np.float32)
    if est.shape[:2] != scene.reflectance.shape[:2]:
        raise ValueError(f"estimate is {est.shape[1]} x {est.shape[0]} pixels, the truth scene "
                         f"{scene.reflectance.shape[1]} x {scene.reflectance.shape[0]}")
    valid, excluded = screen_estimate(est, invalid=invalid, name=name)
    est = np.where(valid[..., None], est, np.float32(np.nan))  # nothing left out reaches the arithmetic
    if wavelengths is not None:
        wl = np.asarray(wavelengths, np.float64)
        if est.shape[2] != wl.size:
            raise ValueError(f"estimate has {est.shape[2]} bands but {wl.size} wavelengths")
        truth = truth_cube(scene, wl)
        rmse = np.sqrt(np.mean((est - truth) ** 2, axis=-1))
        XYZ_est = reflectance_to_XYZ(est, wl, illuminant, cmfs, integration=integration, device=device)
        XYZ_true = reflectance_to_XYZ(truth, wl, illuminant, cmfs, integration=integration,
                                      device=device)  # scene_XYZ on wl, truth reused
    else:
        if est.shape[2] != 3:
            raise ValueError(f"an XYZ estimate must have 3 channels, got {est.shape[2]}")
        rmse = None
        XYZ_est = est
        wl = scene.wavelengths
        XYZ_true = scene_XYZ(scene, illuminant, cmfs, integration=integration, device=device)
    white = white_point_XYZ(illuminant, cmfs, wavelengths=wl, integration=integration)
    Lab_est = XYZ_to_Lab(XYZ_est, white, device=device)
    Lab_true = XYZ_to_Lab(XYZ_true, white, device=device)
    return PixelReport(rmse, delta_E(Lab_true, Lab_est, "CIE 1976", device=device),
                       delta_E(Lab_true, Lab_est, "CIE 2000", device=device), str(illuminant), valid, excluded)
