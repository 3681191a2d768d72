"""A chart of measured spectra the project does not ship, and the figures of a recovery on it, shared by
``tools/studies/bench_default_study.py`` and ``tools/studies/budget_study.py`` (scripts of this folder import it as
``measured_chart``).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from specgpu.pipeline.evaluate import evaluate_pixels, evaluate_reflectance, truth_cube
from specgpu.planning.basis import DEFAULT_WAVELENGTHS, REFLECTANCE_SETS, load_reflectances, pca_basis
from specgpu.rig.scene import SpectralScene

__all__ = ["MEASURED_CHART_SET", "measured_chart_with_white", "LEVEL_EDGES", "chart_errors"]

#: The measured spectra of :func:`measured_chart_with_white` (a set of :data:`specgpu.planning.basis.REFLECTANCE_SETS`).
MEASURED_CHART_SET = "CIE 2017 CES"


def measured_chart_with_white(description, height: int, width: int, *, basis: bool = False, surround: float = 0.03,
                              white: float | None = None):
    """A chart of colour-science's 99 CIE 2017 colour evaluation samples (measured spectra; 10 x 10 patches, one
    mask each over its central 70 %) on a dark ``surround``, with a white strip above it of flat reflectance
    ``white`` (default: the bench's reference white, the certificate's 0.99 off by the bench's ``white_error``),
    and the strip's ROI (x, y, w, h) for
    ``recover --white-roi``. With ``basis``, also the PCA basis trained without the set (and without any spectrum
    within 0.01 RMS of a patch): a basis plan evaluated on it has never seen its patches.

    Returns (scene, roi) or (scene, roi, basis).
    """
    h, w = int(height), int(width)
    if h < 60 or w < 60:
        raise ValueError(f"the measured chart needs at least 60 x 60 pixels, got {w} x {h}")
    samples = REFLECTANCE_SETS[MEASURED_CHART_SET]()
    wl = np.arange(380.0, 780.0 + 1e-9, 5.0)
    spectra = np.stack([np.interp(wl, swl, v) for _, swl, v in samples])
    refl = np.full((h, w, wl.size), float(surround), np.float32)
    x0, x1, y0, y1 = int(0.1 * w), int(0.9 * w), int(0.03 * h), max(int(0.12 * h), int(0.03 * h) + 8)
    refl[y0:y1, x0:x1] = 0.99 * (1.0 + description.realism.white_error) if white is None else float(white)
    roi = (x0 + 3, y0 + 3, x1 - x0 - 6, y1 - y0 - 6)
    n = 10
    pitch = min((h - y1 - 0.03 * h) / n, 0.96 * w / n)
    size = 0.84 * pitch
    gx = (w - n * pitch) / 2 + (pitch - size) / 2
    gy = y1 + 0.015 * h + (pitch - size) / 2
    masks = {}
    for k, (name, _, _) in enumerate(samples):
        row, col = divmod(k, n)
        ya, xa = gy + row * pitch, gx + col * pitch
        refl[int(round(ya)):int(round(ya + size)), int(round(xa)):int(round(xa + size))] = spectra[k]
        m = np.zeros((h, w), bool)
        i = 0.15 * size
        m[int(round(ya + i)):int(round(ya + size - i)), int(round(xa + i)):int(round(xa + size - i))] = True
        masks[f"{k + 1:02d} {name}"] = m
    scene = SpectralScene(wl, refl, masks, "CIE 2017 CES chart")
    if not basis:
        return scene, roi
    test = np.stack([np.interp(DEFAULT_WAVELENGTHS, wl, s) for s in spectra])
    table = pca_basis(load_reflectances(exclude=(MEASURED_CHART_SET,), exclude_similar_to=test))
    return scene, roi, table


#: Edges of the true-reflectance levels :func:`chart_errors` reports the bias at.
LEVEL_EDGES = (0.0, 0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 1.5)


def chart_errors(cube, wavelengths, scene) -> dict:
    """Figures of a recovered reflectance cube (H, W, B) on ``wavelengths`` against a chart scene: ``px_rmse``
    (per-pixel RMSE over the bands, mean over the whole frame: what ``specgpu evaluate`` prints),
    ``px_rmse_patches`` (the same over the patches' pixels), ``px_rmse_off_edges`` (over the pixels more than 3
    pixels from any change of the scene's reflectance: the frame less the edges, where lens blur and lateral colour
    mix neighbours), ``patch_rmse`` (RMSE of the patch means, mean over the
    patches), ``bias_400nm`` (mean recovered - true at the band nearest 400 nm over the patches' pixels) and
    ``bias_by_level`` (mean recovered - true over the patches' pixels and bands whose true reflectance lies in each
    :data:`LEVEL_EDGES` interval; NaN where none does)."""
    y = np.asarray(cube, np.float64)
    wl = np.asarray(wavelengths, np.float64)
    truth = truth_cube(scene, wl).astype(np.float64)
    px = evaluate_pixels(y.astype(np.float32), scene, wavelengths=wl, illuminant="D65").statistics()
    patches = np.any(list(scene.masks.values()), axis=0)
    err = (y - truth)[patches]
    t = truth[patches]
    rep = evaluate_reflectance(y.astype(np.float32), wl, scene, illuminant="D65").summary()
    mean_refl = scene.reflectance.mean(axis=-1)
    edge = np.zeros(mean_refl.shape, bool)
    for ax in (0, 1):
        edge |= np.abs(np.diff(mean_refl, axis=ax, prepend=np.take(mean_refl, [0], axis=ax))) > 1e-4
    off_edges = ~ndimage.binary_dilation(edge, iterations=3)
    px_all = np.sqrt(np.mean((y - truth) ** 2, axis=-1))
    levels = []
    for a, b in zip(LEVEL_EDGES[:-1], LEVEL_EDGES[1:]):
        sel = (t >= a) & (t < b) & np.isfinite(err)
        levels.append(float(err[sel].mean()) if sel.any() else float("nan"))
    return {"px_rmse": px["rmse"]["mean"],
            "px_rmse_patches": float(np.nanmean(np.sqrt(np.mean(err ** 2, axis=-1)))),
            "px_rmse_off_edges": float(np.nanmean(px_all[off_edges])),
            "patch_rmse": float(rep["rmse"][0]), "bias_400nm": float(np.nanmean(err[:, int(np.argmin(abs(wl - 400)))])),
            "bias_by_level": levels}
