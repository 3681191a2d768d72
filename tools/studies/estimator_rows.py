"""The estimator study's measurements on the twin, run by ``tools/studies/estimator_study.py`` (which imports this
module as ``estimator_rows``): each plan captured with fresh noise, recovered and measured on the chart's patches
beside the error it expects (:func:`study_rows`, printed by :func:`format_study`), the held-out error against the
prior's size (:func:`prior_size_rows`) and Hadamard's measured gain over narrowband (:func:`hadamard_gain`). The
plans themselves come from :mod:`specgpu.planning.estimator_plans`.
"""

from __future__ import annotations

import math
from pathlib import Path

import colour
import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.core.spectra import XYZ_weights
from specgpu.engine.colorimetry import XYZ_to_Lab
from specgpu.engine.linear_map import apply_linear
from specgpu.pipeline.evaluate import evaluate_pixels, patch_means, scene_XYZ, truth_cube
from specgpu.pipeline.recovery import SequenceFolder, capture_plan, recover, to_XYZ
from specgpu.planning import (
    NoiseModel,
    default_prior,
    delta_E_sigma,
    make_plan,
    plan_hadamard,
    plan_optimal,
    prior_from_spectra,
    sigma_map,
)
from specgpu.planning.correction import ambient_index, with_ambient_frame
from specgpu.planning.estimator_plans import chart_error
from specgpu.planning.priors import HELD_OUT_CHART, held_out_spectra, training_spectra
from specgpu.planning.uncertainty import output_covariance
from specgpu.rig.scene import SpectralScene

__all__ = ["study_rows", "format_study", "prior_size_rows", "hadamard_gain"]


def study_rows(description, bundle, scene, plans: dict, *, runs: int = 3, seed: int = 0, de_sigma: bool = True,
               device=None, white_roi=None) -> list:
    """Capture each plan ``runs`` times with fresh noise on the twin, recover, and measure on the chart's patch
    pixels: per-pixel means of RMSE, dE2000 and dE*ab (D65; a tristimulus plan under its own illuminant), the
    same of the patch means (per patch), the RMS error beside the plan's expected RMSE, and the standard deviation
    of the standardised errors (error / sigma) and, with ``de_sigma``, the RMS dE2000 over the RMS of the
    predicted dE2000 sigma (:func:`delta_E_sigma`; first run only). Returns one dict per plan with mean and std
    over the runs.

    ``white_roi`` (a lab rig: a white tile in the scene there): the corrections of ``specgpu demo``'s lab profile,
    an ambient frame per sequence (subtracted instead of the dark) and the white's rescaling of the decoder for the
    lamp's drift (:func:`specgpu.pipeline.recovery.recover`). The sigma is then the plan's own decoder's on the frames
    above the ambient frame (the dark the recovery subtracts) with that frame's own noise and the room light's shot
    noise, without the light's fluctuation (the white's gains divide it out); the decoder's rescaling by a few per
    cent is not in it."""
    mask = np.any(list(scene.masks.values()), axis=0)
    rows = []
    for i, (name, plan) in enumerate(plans.items()):
        if white_roi is not None:
            plan = with_ambient_frame(plan)
        acc = {k: [] for k in ("rmse", "dE2000", "dEab", "patch_rmse", "patch_dE2000", "patch_dEab", "rms", "z",
                               "dE_ratio")}
        for run in range(runs):
            res = capture_plan(description, plan, scene, noise_seed=10_000 + 97 * seed + 13 * i + run,
                               calibration=bundle)
            frames = res.sequences[0].frames
            dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
            if white_roi is None:
                y = np.asarray(apply_linear(frames, plan.A, dark, gain, device=device), np.float64)
            else:
                folder = SequenceFolder(Path("<memory>"), frames[None], plan, bundle, [], {})
                y = np.asarray(recover(folder, white_roi=white_roi, device=device), np.float64)
                dark = frames[ambient_index(plan)].astype(np.float32)  # what the recovery subtracted
            # the white's per-sequence gains divide each frame's fluctuation out; the ambient frame's noise stays
            kw = {"light": white_roi is None, "device": device,
                  "ambient_dark": None if white_roi is None else bundle.dark_at(plan.exposure_s)}
            sig = sigma_map(frames, plan, dark, gain, **kw)
            refl = plan.output == "reflectance"
            wl = plan.output_wavelengths if refl else None
            ill = "D65" if refl else plan.illuminant
            px = evaluate_pixels(y.astype(np.float32), scene, wavelengths=wl, illuminant=ill, device=device)
            truth = truth_cube(scene, wl) if refl else scene_XYZ(scene, ill, device=device)
            err = (y - truth)[mask]
            acc["z"].append(float((err / sig[mask]).std()))
            acc["dE2000"].append(float(px.delta_E_2000[mask].mean()))
            if de_sigma and run == 0:
                xyz = to_XYZ(y.astype(np.float32), plan, ill, device=device)
                cov = output_covariance(frames, plan, dark, gain, plan.outputs_to_XYZ(ill), **kw)
                ds = delta_E_sigma(np.asarray(xyz)[mask], cov[mask], plan.white_XYZ(ill))
                acc["dE_ratio"].append(float(np.sqrt((px.delta_E_2000[mask] ** 2).mean() / (ds ** 2).mean())))
            acc["dEab"].append(float(px.delta_E_ab[mask].mean()))
            if refl:
                acc["rmse"].append(float(px.rmse[mask].mean()))
                acc["rms"].append(float(np.sqrt((err ** 2).mean())))
            # per patch: the patch means' errors
            _, ym = patch_means(y.astype(np.float32), scene.masks)
            _, tm = patch_means(np.asarray(truth, np.float32), scene.masks)
            pe = _patch_errors(np.asarray(ym, np.float64), np.asarray(tm, np.float64), plan, ill)
            for k, v in pe.items():
                acc[k].append(v)
        expected = plan.params.get("expected", {})
        row = {"name": name, "method": plan.method, "estimator": plan.params.get("estimator", "projection"),
               "K": plan.K, "exposure_ms": plan.exposure_s * 1e3, "runs": runs,
               "expected_rmse": expected.get("rmse") if plan.output == "reflectance" else None,
               "expected_rmse_cv": expected.get("rmse_cv")}
        for k, v in acc.items():
            if v:
                row[k] = (float(np.mean(v)), float(np.std(v)))
        rows.append(row)
    return rows


def _patch_errors(ym, tm, plan, illuminant) -> dict:
    """RMSE / dE2000 / dE*ab of patch means (N, P) against the truth's patch means."""
    out = {}
    if plan.output == "reflectance":
        out["patch_rmse"] = float(np.sqrt(((ym - tm) ** 2).mean(axis=1)).mean())
        C = XYZ_weights(plan.output_wavelengths, illuminant)
        xe, xt = ym @ C.T, tm @ C.T
    else:
        xe, xt = ym, tm
    white = plan.white_XYZ(illuminant)  # of the grid the XYZ were integrated on
    le = np.asarray(XYZ_to_Lab(xe, white), np.float64)
    lt = np.asarray(XYZ_to_Lab(xt, white), np.float64)
    out["patch_dE2000"] = float(np.mean(colour.delta_E(lt, le, method="CIE 2000")))
    out["patch_dEab"] = float(np.mean(colour.delta_E(lt, le, method="CIE 1976")))
    return out


def format_study(rows) -> str:
    """The study table as text: mean +- std over the runs."""
    def f(row, key, digits):
        v = row.get(key)
        return "-" if v is None else f"{v[0]:.{digits}f} +- {v[1]:.{digits}f}"

    head = (f"{'method':<16} {'K':>3} {'ms':>7} {'RMSE (pixel)':>18} {'dE2000 (pixel)':>16} {'dE*ab (pixel)':>16} "
            f"{'RMSE (patch)':>18} {'dE2000 (patch)':>16} {'expected':>8} {'RMS':>8} {'ratio':>6} {'cv':>7} "
            f"{'ratio':>6} {'z std':>6} {'dE/sig':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        exp = r.get("expected_rmse")
        rms = r.get("rms")
        ratio = f"{rms[0] / exp:.2f}" if exp and rms else "-"
        cv = r.get("expected_rmse_cv")
        cv_text, cv_ratio = (f"{cv:.4f}", f"{rms[0] / cv:.2f}") if cv and rms else ("-", "-")
        lines.append(f"{r['name']:<16} {r['K']:>3} {r['exposure_ms']:>7.1f} {f(r, 'rmse', 4):>18} "
                     f"{f(r, 'dE2000', 2):>16} {f(r, 'dEab', 2):>16} {f(r, 'patch_rmse', 4):>18} "
                     f"{f(r, 'patch_dE2000', 2):>16} {'-' if exp is None else round(exp, 4)!s:>8} "
                     f"{'-' if rms is None else round(rms[0], 4)!s:>8} {ratio:>6} {cv_text:>7} {cv_ratio:>6} "
                     f"{r['z'][0]:>6.2f} "
                     f"{r['dE_ratio'][0] if 'dE_ratio' in r else float('nan'):>6.2f}")
    return "\n".join(lines)


def prior_size_rows(description, bundle, sizes, *, frames: int = 9, chart: str = HELD_OUT_CHART,
                    seed: int = 0) -> list:
    """How the held-out error depends on the prior's size: for each size, a random subset of the training
    spectra, an optimal plan designed and decoded with it, and its expected RMSE on the prior beside the RMSE it
    reaches on the held-out chart (:func:`chart_error`)."""
    full = training_spectra(chart)
    wl = default_prior(chart).wavelengths
    _, _, test = held_out_spectra(chart, wl)
    rng = np.random.default_rng(seed)
    rows = []
    for n in sizes:
        n = min(int(n), full.shape[0])
        sub = full[rng.choice(full.shape[0], n, replace=False)]
        prior = prior_from_spectra(sub, wl, f"{n} random training spectra")
        plan = plan_optimal(bundle, prior, lambda t: NoiseModel.from_rig(description, t), frames=frames,
                            starts=1, seed=seed)
        rows.append({"n": n, "expected_rmse": plan.params["expected"]["rmse"],
                     "chart_rmse": chart_error(plan, bundle, test, wl)})
    return rows


def hadamard_gain(description, *, bands: int = 31, exposure_s: float = 0.002, reflectance: float = 0.5,
                  seed: int = 0, bundle=None) -> dict:
    """Measure Hadamard's SNR gain over plain narrowband at equal capture time on the twin: both plans with
    ``bands`` equal bands at one exposure, a uniform grey scene, the per-band noise as the pixel-to-pixel standard
    deviation over the central region (averaged over bands). Returns the two noises, the gain (narrowband noise
    / Hadamard noise) and the read-noise-limited theory ``(N + 1) / (2 sqrt N)``."""
    bundle = bundle or oracle_calibration(description)
    had = plan_hadamard(bundle, bands=bands, max_exposure_s=exposure_s)
    nb = make_plan("narrowband", bundle, centres=had.output_wavelengths, bandwidth_nm=had.params["bandwidth_nm"],
                   max_exposure_s=exposure_s)
    cam = description.camera
    h, w = cam.roi_height, cam.roi_width
    scene = SpectralScene(np.array([380.0, 780.0]), np.full((h, w, 2), reflectance, np.float32), name="grey")
    noise = {}
    for plan in (had, nb):
        frames = capture_plan(description, plan, scene, noise_seed=seed).sequences[0].frames
        y = apply_linear(frames, plan.A, bundle.dark_at(plan.exposure_s), bundle.flat_field)
        c = y[h // 4:3 * h // 4, w // 4:3 * w // 4]
        noise[plan.method] = float(c.std(axis=(0, 1)).mean())
        noise[plan.method + "_mean"] = c.mean(axis=(0, 1)).tolist()
    return {"bands": bands, "exposure_ms": had.exposure_s * 1e3, "narrowband_exposure_ms": nb.exposure_s * 1e3,
            "narrowband_mean": noise["narrowband_mean"], "hadamard_mean": noise["hadamard_mean"],
            "narrowband_noise": noise["narrowband"], "hadamard_noise": noise["hadamard"],
            "gain": noise["narrowband"] / noise["hadamard"], "theory": (bands + 1) / (2 * math.sqrt(bands)),
            "read_noise_e": float(cam.read_noise_e)}
