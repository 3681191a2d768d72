"""Measure methods on the twin in memory: capture, recover (optionally drift-corrected), evaluate, over several
noise draws: what ``specgpu demo``'s tables are made of (also run by ``tools/studies/error_budget.py`` and
``tools/studies/drift_study.py``).

Every figure is a list over noise draws (fresh temporal noise per draw, the same calibration and plans), so a
table can print mean +- std; per-patch figures (patch means) sit beside per-pixel ones (what an image user sees).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from specgpu.pipeline.evaluate import evaluate_pixels, evaluate_reflectance, evaluate_XYZ, truth_cube
from specgpu.pipeline.recovery import SequenceFolder, capture_plan, recover
from specgpu.planning.correction import with_ambient_frame, with_drift_probes
from specgpu.rig.scene import colorchecker_scene, white_tile_roi

__all__ = ["measure_methods", "chart_with_white", "mean_std", "METRICS"]

#: Figures kept per draw: patch RMSE / dE*ab / dE2000 averages, per-pixel means, and the RMS reflectance error
#: over the patches' pixels (every band; what a plan's expected RMSE predicts).
METRICS = ("rmse", "dEab", "dE00", "px_rmse", "px_dE00", "px_rms")


def chart_with_white(description, chart: str):
    """The evaluation chart with the reference white tile above it (the twin's white: the certificate's 0.99 off
    by the bench's ``white_error``) and the tile's ROI."""
    cam = description.camera
    true_white = 0.99 * (1.0 + description.realism.white_error)
    scene = colorchecker_scene(cam.roi_height, cam.roi_width, chart=chart, white_tile=true_white)
    return scene, white_tile_roi(cam.roi_height, cam.roi_width)


def measure_methods(description, bundle, plans: dict, scene, *, draws: int = 1, seed: int = 0,
                    white_roi=None, white_reflectance=None, ambient: bool = False, probes=None, pixels: bool = True,
                    device=None, on_result=None, on_scored=None) -> dict:
    """Capture each plan ``draws`` times on ``scene`` with fresh noise and evaluate.

    Parameters
    ----------
    description : RigDescription
        The rig at capture (its ``[drift]`` is the change since ``bundle`` was made).
    plans : dict
        name -> Plan (made from ``bundle``).
    white_roi, white_reflectance
        Drift correction with a reference white in the field (:mod:`specgpu.planning.correction`); off when None.
    ambient : bool
        Add an ambient frame to every plan (subtracted at recovery instead of the calibration's dark).
    probes : sequence of float, optional
        Drift probe centres (nm) added to every plan (:func:`specgpu.planning.correction.with_drift_probes`).
    on_result : callable, optional
        ``on_result(name, draw, y, plan, res)`` for every recovery (e.g. to write files for the first draw).
    on_scored : callable, optional
        ``on_scored(name, draw, y, plan, res, patch, pixels)`` for every recovery once scored: its
        :class:`~specgpu.pipeline.evaluate.PatchReport` and :class:`~specgpu.pipeline.evaluate.PixelReport` (None
        with ``pixels=False``), so that a caller reporting on it need not score it again.

    Returns
    -------
    dict
        name -> {metric: [value per draw]} for :data:`METRICS` (``rmse``/``px_rmse``/``px_rms`` absent for XYZ
        plans), plus ``"K"`` (frames per sequence), ``"sequence_ms"`` (the plan's sequence time) and, for a plan that
        records one (an estimator's, a design's), ``"expected_rmse"``: the RMSE its decoder expects on its training
        prior.
    """
    out = {}
    patches = np.any(list(scene.masks.values()), axis=0) if scene.masks else None
    for i, (name, plan) in enumerate(plans.items()):
        if probes:
            plan = with_drift_probes(plan, bundle, probes)
        if ambient:
            plan = with_ambient_frame(plan)
        rows = {m: [] for m in METRICS}
        for draw in range(int(draws)):
            res = capture_plan(description, plan, scene, noise_seed=1000 + 17 * seed + i + 7919 * draw,
                               calibration=bundle)
            frames = np.stack([s.frames for s in res.sequences])
            folder = SequenceFolder(Path("<memory>"), frames, plan, bundle, [], {})
            y = recover(folder, device=device, white_roi=white_roi, white_reflectance=white_reflectance)
            if on_result is not None:
                on_result(name, draw, y, plan, res)
            if plan.output == "reflectance":
                rep = evaluate_reflectance(y, plan.output_wavelengths, scene, illuminant="D65")
                px = evaluate_pixels(y, scene, wavelengths=plan.output_wavelengths, illuminant="D65",
                                     device=device) if pixels else None
            else:
                rep = evaluate_XYZ(y, scene, illuminant=plan.illuminant)
                px = evaluate_pixels(y, scene, illuminant=plan.illuminant, device=device) if pixels else None
            s = rep.summary()
            if "rmse" in s:
                rows["rmse"].append(s["rmse"][0])
            rows["dEab"].append(s["delta_E_ab"][0])
            rows["dE00"].append(s["delta_E_2000"][0])
            if px is not None:
                st = px.statistics()
                if "rmse" in st:
                    rows["px_rmse"].append(st["rmse"]["mean"])
                rows["px_dE00"].append(st["delta_E_2000"]["mean"])
                if plan.output == "reflectance" and patches is not None:
                    err = (np.asarray(y, np.float64) - truth_cube(scene, plan.output_wavelengths))[patches]
                    rows["px_rms"].append(float(np.sqrt(np.mean(err ** 2))))
            rows.setdefault("reports", []).append(rep)
            if on_scored is not None:
                on_scored(name, draw, y, plan, res, rep, px)
        out[name] = {k: v for k, v in rows.items() if v} | {"K": plan.K, "sequence_ms": plan.sequence_s * 1e3}
        expected = plan.params.get("expected", {}).get("rmse") if plan.output == "reflectance" else None
        if expected is not None:
            out[name]["expected_rmse"] = float(expected)
    return out


def mean_std(values) -> tuple[float, float]:
    """(mean, standard deviation over draws; 0 for one draw) of a list of figures."""
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0
