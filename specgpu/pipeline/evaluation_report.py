"""The report of ``specgpu evaluate``: a recovered cube (or a tristimulus recovery's XYZ map) read back, scored
per pixel and, for a chart, per patch against the true scene, with its headline figures (per patch for a chart,
like the paper's tables), the pixels left out and why, whether the truth is the one the cube was recovered from,
and the lines that print them."""

from __future__ import annotations

import math
import re
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu import io
from specgpu.core.spectra import DEFAULT_CMFS
from specgpu.io.motion_truth import TRUTH_FOLDER, sequence_truth
from specgpu.io.sequence import SEQUENCE_FILE, capture_hash, read_sequence_header
from specgpu.pipeline.evaluate import (
    EXCLUSION_CAUSES,
    PLAUSIBLE_RANGE,
    evaluate_pixels,
    evaluate_reflectance,
    evaluate_XYZ,
    evaluation_illuminant,
    evaluation_integration,
)

if TYPE_CHECKING:
    from specgpu.rig.scene import SpectralScene

__all__ = ["evaluation_report", "headline_line", "pixel_line", "patch_table", "read_recovered", "truth_file",
           "truth_mismatch"]

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


def truth_file(truth, meta) -> str:
    """``--truth`` as a scene :func:`specgpu.rig.scene.load_scene` reads: a capture folder (of a moving twin) is
    its ``motion_truth/`` at the sequence the cube records; anything else is itself."""
    if Path(truth).is_dir():
        return str(sequence_truth(truth, meta.get("sequence")))
    return str(truth)


def _capture_of(truth) -> Path | None:
    """The capture folder a truth belongs to (the folder itself, or the one whose ``motion_truth/`` holds the
    file); None for a built-in scene or a file outside a capture."""
    path = Path(truth)
    folder = path if path.is_dir() else path.parent.parent if path.parent.name == TRUTH_FOLDER else None
    return folder if folder is not None and (folder / SEQUENCE_FILE).is_file() else None


def truth_mismatch(cube, meta, truth, scene) -> str | None:
    """What a cube's metadata says against the truth it is scored with, in one line, or None.

    The cube records the capture it was recovered from (``capture``: its identity, ``sequence_folder``,
    ``sequence``, ``sequences_averaged`` and the ``scene`` the capture recorded, see
    :func:`specgpu.pipeline.outputs.recovery_metadata`). A truth in a capture folder (the folder or a file of its
    ``motion_truth/``) must be of that capture and of the sequence the cube holds; any other truth must be the
    scene the capture recorded. A cube that records none of it is taken as it is.
    """
    recorded = f"{cube} was recovered from {meta.get('sequence_folder') or 'a capture'}"
    capture = _capture_of(truth)
    if capture is None:
        scene_name = meta.get("scene")
        if isinstance(scene_name, str) and scene_name != scene.name:
            named = "" if str(truth) == scene.name else f" ({scene.name!r})"
            return f"{recorded}, a capture of scene {scene_name!r}, not of --truth {truth}{named}"
        return None
    if isinstance(meta.get("capture"), str):
        try:
            theirs = capture_hash(read_sequence_header(capture)[0])
        except (OSError, ValueError):
            theirs = None  # an unreadable sequence.json names no capture: nothing to compare
        if theirs is not None and theirs != meta["capture"]:
            return (f"{recorded} (capture {meta['capture'][:12]}), not from the capture --truth {truth} belongs to "
                    f"({capture}, capture {theirs[:12]})")
    number = re.fullmatch(r"sequence_(\d+)\.npz", Path(truth).name) if not Path(truth).is_dir() else None
    if number is None:
        return None
    if meta.get("sequence") is not None and int(meta["sequence"]) != int(number.group(1)):
        return (f"{cube} holds sequence {int(meta['sequence'])} of its capture, --truth {truth} is the truth of "
                f"sequence {int(number.group(1))}")
    averaged = meta.get("sequences_averaged")
    if meta.get("sequence") is None and isinstance(averaged, int) and averaged > 1:
        return (f"{cube} averages {averaged} sequences of its capture, --truth {truth} is the truth of sequence "
                f"{int(number.group(1))} only")
    return None


def _finite_or_none(value):
    """A float for the JSON report: NaN and infinities (no value) become null."""
    value = float(value)
    return value if math.isfinite(value) else None


def _patch_rows(data, wavelengths, valid, scene, illuminant, cmfs, integration="rectangle") -> tuple[list, dict]:
    """Per-patch rows (NaN for a patch with no valid pixel: null in JSON) and the per-patch headline over the
    patches that have a value; both sides integrated to XYZ by ``integration``."""
    kept = np.where(valid[..., None], data, np.float32(np.nan))  # what the per-pixel scores left out, left out
    patch = (evaluate_reflectance(kept, wavelengths, scene, illuminant=illuminant, integration=integration)
             if wavelengths is not None
             else evaluate_XYZ(kept, scene, illuminant=illuminant, cmfs=cmfs, integration=integration))
    rows = []
    for i, name in enumerate(patch.names):
        mask = np.asarray(scene.masks[name], bool)
        pixels = int((mask & valid).sum())
        row = {"patch": name, "pixels": pixels, "excluded": int(mask.sum()) - pixels,
               "dE76": _finite_or_none(patch.delta_E_ab[i]), "dE2000": _finite_or_none(patch.delta_E_2000[i])}
        if patch.rmse is not None:
            row["rmse"] = _finite_or_none(patch.rmse[i])
        rows.append(row)
    headline = {}
    for key, v in (("rmse", patch.rmse), ("delta_E_ab", patch.delta_E_ab), ("delta_E_2000", patch.delta_E_2000)):
        if v is not None:
            v = v[np.isfinite(v)]
            headline[key] = ({"mean": float(np.mean(v)), "max": float(np.max(v))} if v.size
                             else {"mean": float("nan"), "max": float("nan")})
    return rows, headline


def evaluation_report(cube: ArrayLike, data, wavelengths: ArrayLike, meta, scene: SpectralScene, illuminant, cmfs, *,
                      device=None,
                      progress=lambda desc: nullcontext(), invalid: str = "refuse", truth=None,
                      integration=None) -> dict:
    """The evaluation report: per-pixel statistics, per-patch rows for a chart, the headline figures
    (``<short>_mean`` / ``<short>_max``; ``headline`` keeps them by long name, per patch for a chart, per pixel
    otherwise), the pixels scored and those left out by cause (``excluded``, see
    :data:`specgpu.pipeline.evaluate.EXCLUSION_CAUSES`), and ``truth_mismatch`` when the cube was recovered from
    another capture than ``truth`` (the ``--truth`` given; None: not checked).

    ``invalid``: ``"refuse"`` a cube holding an infinite or implausible value (a ValueError naming ``cube``), or
    ``"exclude"`` those pixels, counted. ``integration``: the one asked for, else the one the file records
    (:func:`specgpu.pipeline.evaluate.evaluation_integration`)."""
    integration = evaluation_integration(meta.get("integration"), integration, colorimetric=wavelengths is None,
                                         name=str(cube))
    with progress("evaluating"):
        pixels = evaluate_pixels(data, scene, wavelengths=wavelengths, illuminant=illuminant, cmfs=cmfs,
                                 integration=integration, device=device, invalid=invalid, name=str(cube))
    stats = pixels.statistics()
    counts = pixels.counts()
    report = {"cube": str(cube), "truth": scene.name, "illuminant": illuminant,
              **({"observer": cmfs} if cmfs != DEFAULT_CMFS else {}),
              **({"integration": integration} if integration != "rectangle" else {}),
              **({"truth_resampled": scene.resampled} if scene.resampled else {}),
              "projections": meta.get("projections"), "plan_method": meta.get("plan_method"),
              "pixels": {k: {s: _finite_or_none(x) for s, x in v.items()} for k, v in stats.items()},
              "pixels_total": counts["pixels"], "pixels_scored": counts["scored"], "excluded": counts["excluded"],
              "plausible_range": list(PLAUSIBLE_RANGE)}
    mismatch = None if truth is None else truth_mismatch(cube, meta, truth, scene)
    if mismatch:
        report["truth_mismatch"] = mismatch
    headline = {k: stats[k] for k in stats}
    if scene.masks:
        valid = pixels.valid if pixels.valid is not None else np.ones(data.shape[:2], bool)
        report["patches"], headline = _patch_rows(data, wavelengths, valid, scene, illuminant, cmfs, integration)
        report["patches_scored"] = sum(1 for row in report["patches"] if row["dE76"] is not None)
    for key, short in SHORT_NAMES.items():
        if key in headline:
            report[f"{short}_mean"] = _finite_or_none(headline[key]["mean"])
            report[f"{short}_max"] = _finite_or_none(headline[key]["max"])
    return {"report": report, "headline": headline, "pixel_statistics": stats}


def patch_table(rows) -> list[str]:
    """The per-patch table: RMSE (- for an XYZ map), dE*ab and dE2000 of each patch (- for a patch with no valid
    pixel), under a header; an ``excluded`` column (pixels left out of each patch) when any pixel was."""
    excluded = any(row.get("excluded") for row in rows)
    lines = [f"{'patch':<22}{'RMSE':>8}{'dE*ab':>8}{'dE2000':>8}" + (f"{'excluded':>10}" if excluded else "")]

    def cell(value, digits):
        return f"{'-':>8}" if value is None else f"{value:8.{digits}f}"

    for row in rows:
        lines.append(f"{row['patch']:<22}{cell(row.get('rmse'), 4)}{cell(row['dE76'], 2)}{cell(row['dE2000'], 2)}"
                     + (f"{row.get('excluded', 0):>10}" if excluded else ""))
    return lines


def headline_line(report, headline, per_patch) -> str:
    """The summary line: each headline figure's mean and max, the projections and, for a chart some patch of
    which has no valid pixel, the patches scored."""
    basis = "per patch" if per_patch else "per pixel"
    patches = report.get("patches") or []
    scored = report.get("patches_scored", len(patches))
    return (f"{basis} under {report['illuminant']}: "
            + ", ".join(f"{SHORT_NAMES[k]} mean {v['mean']:.4g} max {v['max']:.4g}" for k, v in headline.items())
            + (f"; {report['projections']} projections" if report["projections"] else "")
            + (f"; {scored} of {len(patches)} patches scored (the others have no valid pixel)"
               if per_patch and scored < len(patches) else ""))


#: How the report line names each cause of :data:`specgpu.pipeline.evaluate.EXCLUSION_CAUSES`.
CAUSE_WORDS = {"flagged": "NaN (flagged by the recovery)", "non_finite": "infinite",
               "out_of_range": "outside {lo:g} to {hi:g}", "unscored": "with no finite error (NaN in the truth)"}


def pixel_line(report, statistics, per_patch) -> str:
    """The per-pixel line: each metric's mean, median, 95th percentile and max over the scored pixels (after
    the per-patch headline of a chart, the headline itself otherwise), the pixels scored and, by cause, those
    left out."""
    lo, hi = PLAUSIBLE_RANGE
    left = [f"{n} {CAUSE_WORDS[c].format(lo=lo, hi=hi)}" for c in EXCLUSION_CAUSES
            if (n := report["excluded"].get(c, 0))]
    count = (f"{report['pixels_scored']} of {report['pixels_total']} pixels scored"
             + (f", left out: {', '.join(left)}" if left else ""))
    if not per_patch:  # the headline is already per pixel: add median, p95 and the counts
        figures = ", ".join(f"{SHORT_NAMES[k]} median {v['median']:.4g} p95 {v['p95']:.4g}"
                            for k, v in statistics.items())
        return f"per pixel: {figures}; {count}"
    figures = ", ".join(f"{SHORT_NAMES[k]} mean {v['mean']:.4g} median {v['median']:.4g} p95 {v['p95']:.4g} "
                        f"max {v['max']:.4g}" for k, v in statistics.items())
    return f"per pixel under {report['illuminant']}: {figures}; {count}"
