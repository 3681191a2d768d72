"""The report of ``specgpu evaluate``: a recovered cube (or a tristimulus recovery's XYZ map) read back, scored
per pixel and, for a chart, per patch against the true scene, with its headline figures (per patch for a chart,
like the paper's tables) and the lines that print them."""

from __future__ import annotations

from contextlib import nullcontext

import numpy as np

from specgpu import io
from specgpu.core.spectra import DEFAULT_CMFS
from specgpu.pipeline.evaluate import (
    evaluate_pixels,
    evaluate_reflectance,
    evaluate_XYZ,
    evaluation_illuminant,
    evaluation_integration,
)

__all__ = ["evaluation_report", "headline_line", "patch_table", "read_recovered"]

#: The report's short names of the headline figures.
SHORT_NAMES = {"rmse": "rmse", "delta_E_ab": "dE76", "delta_E_2000": "dE2000"}


def read_recovered(path):
    """(data, wavelengths, metadata) of a recovered cube, or of an XYZ map (wavelengths None); a file that is
    neither raises the cube reader's error."""
    try:
        return io.read_cube(path)
    except ValueError as cube_error:
        try:  # a tristimulus recovery: an XYZ map
            data, _, meta = io.read_map(path, "XYZ")
            return data, None, meta
        except ValueError:
            raise cube_error from None


def colorimetry(path, meta, illuminant, colorimetric):
    """The (illuminant, observer) a recovery is scored under: the one it records unless another is asked (refused
    for an XYZ map); XYZ is also relative to the observer it was made for."""
    illuminant = evaluation_illuminant(meta.get("illuminant"), illuminant, colorimetric=colorimetric, name=str(path))
    cmfs = meta.get("observer") if colorimetric and isinstance(meta.get("observer"), str) else DEFAULT_CMFS
    return illuminant, cmfs


def evaluation_report(cube, data, wavelengths, meta, scene, illuminant, cmfs, *, device=None,
                      progress=lambda desc: nullcontext(), integration=None) -> dict:
    """The evaluation report: per-pixel statistics, per-patch rows for a chart, and the headline figures
    (``<short>_mean`` / ``<short>_max``; ``headline`` keeps them by long name). ``integration``: the one asked
    for, else the one the file records (:func:`specgpu.pipeline.evaluate.evaluation_integration`)."""
    integration = evaluation_integration(meta.get("integration"), integration, colorimetric=wavelengths is None,
                                         name=str(cube))
    with progress("evaluating"):
        pixels = evaluate_pixels(data, scene, wavelengths=wavelengths, illuminant=illuminant, cmfs=cmfs,
                                 integration=integration, device=device)
    stats = pixels.statistics()
    report = {"cube": str(cube), "truth": scene.name, "illuminant": illuminant,
              **({"observer": cmfs} if cmfs != DEFAULT_CMFS else {}),
              **({"integration": integration} if integration != "rectangle" else {}),
              **({"truth_resampled": scene.resampled} if scene.resampled else {}),
              "projections": meta.get("projections"), "plan_method": meta.get("plan_method"), "pixels": stats}
    headline = {k: stats[k] for k in stats}
    if scene.masks:
        patch = (evaluate_reflectance(data, wavelengths, scene, illuminant=illuminant, integration=integration)
                 if wavelengths is not None
                 else evaluate_XYZ(data, scene, illuminant=illuminant, cmfs=cmfs, integration=integration))
        rows = []
        for i, name in enumerate(patch.names):
            row = {"patch": name, "dE76": float(patch.delta_E_ab[i]), "dE2000": float(patch.delta_E_2000[i])}
            if patch.rmse is not None:
                row["rmse"] = float(patch.rmse[i])
            rows.append(row)
        report["patches"] = rows
        # the headline figures of a chart are per patch, like the paper's tables
        headline = {k: {"mean": float(np.mean(v)), "max": float(np.max(v))} for k, v in
                    (("rmse", patch.rmse), ("delta_E_ab", patch.delta_E_ab), ("delta_E_2000", patch.delta_E_2000))
                    if v is not None}
    for key, short in SHORT_NAMES.items():
        if key in headline:
            report[f"{short}_mean"] = headline[key]["mean"]
            report[f"{short}_max"] = headline[key]["max"]
    return {"report": report, "headline": headline}


def patch_table(rows) -> list[str]:
    """The per-patch table: RMSE (- for an XYZ map), dE*ab and dE2000 of each patch, under a header."""
    lines = [f"{'patch':<22}{'RMSE':>8}{'dE*ab':>8}{'dE2000':>8}"]
    for row in rows:
        rmse = f"{row['rmse']:8.4f}" if "rmse" in row else f"{'-':>8}"
        lines.append(f"{row['patch']:<22}{rmse}{row['dE76']:8.2f}{row['dE2000']:8.2f}")
    return lines


def headline_line(report, headline, per_patch) -> str:
    """The summary line: each headline figure's mean and max, and the projections."""
    basis = "per patch" if per_patch else "per pixel"
    return (f"{basis} under {report['illuminant']}: "
            + ", ".join(f"{SHORT_NAMES[k]} mean {v['mean']:.4g} max {v['max']:.4g}" for k, v in headline.items())
            + (f"; {report['projections']} projections" if report["projections"] else ""))
