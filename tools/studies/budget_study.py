"""Budget study: every method at equal sequence time, raw and denoised, on two measured charts in neither the
training prior nor the ColorChecker, each figure beside the limit of any design of its frame count at its
budget; and the denoiser at the edges of the natural scene.

On the default twin (the paper's rig and noise: 640 x 480, 44.2 dB camera, 10-bit, the light's frame-to-frame
fluctuation), calibrated by both feedback loops, for each chart:

* "CIE 2017 CES": colour-science's 99 CIE 2017 colour evaluation samples (measured spectra), 10 x 10 patches;
* "CIE 1995 TCS": the 14 Munsell chips of the CIE 1995 test colour samples,

the prior and the basis are trained on every other set colour-science ships minus the chart (and any spectrum
within 0.01 RMS of one of its patches); the rows of ``specgpu.planning.equal_time.EQUAL_TIME`` (9 frames in 60 ms,
6 in 40, 3 in 20; each optimal row also designed for the filter, ``+denoise``: ``specgpu plan --denoise``) are
captured ``--draws`` times with fresh noise, recovered on the device, and denoised (the guided filter of
``recover --denoise``); the optimal rows also as ``white+dn``: ``recover --white-roi --denoise`` on the chart's
reference white, which divides each frame's light fluctuation (common to every pixel of a frame, so no spatial
filter removes it) out by the white's own reading; per-pixel means over the patches' pixels of
RMSE, dE2000 and dE*ab (D65), and the standard deviation of the standardised error (error / the per-pixel
sigma, raw and carried through the filter), mean +- std over the draws; beside them the RMSE the plan expects on
its prior (denoised rows: where the filter flattens the noise, for a plan designed for it) and its noise-free
RMSE on the chart's patch spectra (``floor``: the decoder's mismatch on this chart, which no denoiser removes).

Then the natural scene ("natural": scikit-image's chelsea photograph upsampled to spectra, fine fur texture): the
optimal 9-frame design within 60 ms, and the same designed for the filter, the per-pixel RMSE within 2 px of the
scene's edges (the pixels whose true mean-reflectance gradient is in the top 10 %) and elsewhere, raw and
denoised, each as a ratio to the plain design's raw error.

``--tune`` measures the denoiser's radius and eps on the CES chart and the natural scene instead.

    PYTHONPATH=. python tools/studies/budget_study.py [--draws N] [--charts ces,tcs] [--budgets 60,40,20] \
        [--small] [--tune]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from measured_chart import measured_chart_with_white  # noqa: E402

import specgpu.planning as E  # noqa: E402
from specgpu.apps.demo_measure import mean_std  # noqa: E402
from specgpu.calibration import calibrate  # noqa: E402
from specgpu.engine.guided import flat_variance_reduction  # noqa: E402
from specgpu.pipeline.capture_folder import SequenceFolder  # noqa: E402
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS, denoise_recovery  # noqa: E402
from specgpu.pipeline.evaluate import evaluate_pixels, truth_cube  # noqa: E402
from specgpu.pipeline.recovery import recover, uncertainty  # noqa: E402
from specgpu.pipeline.twin_capture import capture_plan  # noqa: E402
from specgpu.planning.basis import DEFAULT_WAVELENGTHS, evaluation_exclusions, load_reflectances  # noqa: E402
from specgpu.planning.equal_time import EQUAL_TIME, equal_time_bounds, equal_time_plans, row_name  # noqa: E402
from specgpu.planning.estimators import forward, output_weights  # noqa: E402
from specgpu.planning.priors import HELD_OUT_CHART, held_out_basis, held_out_spectra
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import RigDescription  # noqa: E402
from specgpu.rig.scene import (  # noqa: E402
    natural_scene,
    patch_scene,  # noqa: E402
    white_tile_roi,
)

CHARTS = {"ces": "CIE 2017 CES", "tcs": "CIE 1995 TCS"}


def chart_setup(description, key):
    """(scene, prior, basis, training, white ROI) for a chart: the scene at the camera's size with a reference
    white beside the patches (the bench's, 0.99 off by its ``white_error``) and that white's ROI for
    ``recover --white-roi``, and the prior, basis and training spectra without the chart's set and any spectrum
    within 0.01 RMS of one of its patches."""
    cam = description.camera
    chart = CHARTS[key]
    if key == "ces":
        scene, roi, basis = measured_chart_with_white(description, cam.roi_height, cam.roi_width, basis=True)
    else:
        names, wl, spectra = held_out_spectra(chart)
        scene = patch_scene(names, wl, spectra, cam.roi_height, cam.roi_width, name=chart,
                            white_tile=0.99 * (1.0 + description.realism.white_error))
        roi = white_tile_roi(cam.roi_height, cam.roi_width)
        basis = held_out_basis(chart)
    test = np.stack([np.interp(DEFAULT_WAVELENGTHS, scene.wavelengths, scene.reflectance[m].mean(axis=0))
                     for m in scene.masks.values()])
    db = load_reflectances(exclude=evaluation_exclusions(chart), exclude_similar_to=test)
    prior = E.prior_from_spectra(db.reflectance, DEFAULT_WAVELENGTHS, f"colour-science sets without {chart}")
    return scene, prior, basis, db.reflectance, ",".join(str(int(v)) for v in roi)


def measure(description, bundle, plan, scene, seed, denoise=(DENOISE_RADIUS, DENOISE_EPS), mask=None,
            white_roi=None):
    """One capture of ``plan`` on ``scene``: {raw, denoised and, given the reference white's ROI, white+dn
    (``recover --white-roi --denoise``: each frame's light fluctuation divided out by the white's own reading)} ->
    per-pixel RMSE / dE2000 / dE*ab means over ``mask`` (default the patches), z std, and the seconds the
    denoising took."""
    res = capture_plan(description, plan, scene, noise_seed=seed, calibration=bundle)
    folder = SequenceFolder(Path("<memory>"), np.stack([s.frames for s in res.sequences]), plan, bundle, [], {})
    y = recover(folder)
    mask = np.any(list(scene.masks.values()), axis=0) if mask is None else mask
    refl = plan.output == "reflectance"
    wl = plan.output_wavelengths if refl else None
    ill = "D65" if refl else plan.illuminant
    out = {}
    sigma = uncertainty(folder)[0] if refl else None
    variants = {"raw": (y, sigma)}
    if denoise is not None:
        t0 = time.perf_counter()
        yd = denoise_recovery(folder, y, radius=denoise[0], eps=denoise[1])
        seconds = time.perf_counter() - t0
        variants["denoised"] = (yd, None if sigma is None else uncertainty(folder, denoise=denoise)[0])
        if white_roi is not None:
            yw = recover(folder, white_roi=white_roi)
            sw = uncertainty(folder, white_roi=white_roi)[0] if refl else None
            variants["white+dn"] = (denoise_recovery(folder, yw, radius=denoise[0], eps=denoise[1]),
                                    None if sw is None else uncertainty(folder, white_roi=white_roi,
                                                                        denoise=denoise)[0])
    truth = truth_cube(scene, wl) if refl else None
    for name, (v, s) in variants.items():
        px = evaluate_pixels(v, scene, wavelengths=wl, illuminant=ill)
        row = {"dE00": float(np.nanmean(px.delta_E_2000[mask])), "dEab": float(np.nanmean(px.delta_E_ab[mask]))}
        if refl:
            row["rmse"] = float(np.nanmean(px.rmse[mask]))
            z = ((v - truth) / s)[mask]
            row["z"] = float(np.nanstd(z))
        out[name] = row
    if denoise is not None:
        out["denoised"]["seconds"] = seconds
    return out, y


def chart_table(description, bundle, key, draws, budgets, seed):
    scene, prior, basis, training, roi = chart_setup(description, key)
    plans = equal_time_plans(description, bundle, prior, basis, training=training, budgets=budgets, starts=4,
                             iterations=300, denoise_radius=DENOISE_RADIUS)
    bounds = equal_time_bounds(description, bundle, prior, budgets=budgets)
    filtered = equal_time_bounds(description, bundle, prior, budgets=budgets,
                                 averaged=flat_variance_reduction(DENOISE_RADIUS))
    print(f"\n{CHARTS[key]} ({len(scene.masks)} patches), {scene.reflectance.shape[1]} x "
          f"{scene.reflectance.shape[0]}, per-pixel means over the patches' pixels, mean +- std over {draws} draws")
    print(f"{'method':<22}{'seq ms':>7}{'':>10}{'RMSE':>17}{'dE2000':>13}{'dE*ab':>13}{'z std':>12}"
          f"{'expected':>9}{'floor':>8}")
    test = np.stack([scene.reflectance[m].mean(axis=0) for m in scene.masks.values()])
    for T in budgets:
        K, rows = EQUAL_TIME[T]
        names = [n for name in rows for n in (name, f"{name}+denoise") if row_name(n, T) in plans]
        for name in names:
            plan = plans[row_name(name, T)]
            acc = {}
            for d in range(draws):
                m, _ = measure(description, bundle, plan, scene, 1000 * seed + 31 * d + K,
                               white_roi=roi if plan.method == "optimal" else None)
                for variant, vals in m.items():
                    for k, v in vals.items():
                        acc.setdefault(variant, {}).setdefault(k, []).append(v)
            expected = plan.params.get("expected", {})
            floor = noise_free_rmse(bundle, plan, scene.wavelengths, test)
            for variant, vals in acc.items():
                def pm(k, digits):
                    if k not in vals:
                        return "-"
                    mu, sd = mean_std(vals[k])
                    return f"{mu:.{digits}f}+-{sd:.{digits}f}"
                # raw: at the camera's noise; denoised: where the filter flattens it (a plan designed for it)
                exp = expected.get({"raw": "rmse", "denoised": "rmse_at_decoder_noise"}.get(variant, ""))
                print(f"{(name if variant == 'raw' else ''):<22}"
                      f"{(f'{plan.sequence_s * 1e3:.1f}' if variant == 'raw' else ''):>7}{variant:>10}"
                      f"{pm('rmse', 4):>17}{pm('dE00', 2):>13}{pm('dEab', 2):>13}{pm('z', 2):>12}"
                      f"{(f'{exp:.4f}' if exp else ''):>9}"
                      f"{(f'{floor:.4f}' if floor is not None and variant == 'raw' else ''):>8}")
        b = bounds[T]
        print(f"{'':<22}limit at {T:g} ms ({K} frames), expected RMSE on the prior: any design >= "
              f"{b.lower_rmse:.4f}; best found {b.achieved_rmse:.4f}; noise-free rank limit {b.noise_free_rmse:.4f}")
        f = filtered[T]
        print(f"{'':<22}where the filter flattens the noise ({f.averaged:.0f} pixels): any design >= "
              f"{f.lower_rmse:.4f}; best found {f.achieved_rmse:.4f}")


def noise_free_rmse(bundle, plan, wavelengths, spectra):
    """The plan's decoder on the chart's patch spectra without noise (the error no denoiser removes: its mismatch on
    this chart): the mean over the patches of each patch's RMSE over the bands, as the per-pixel figures beside
    it; None for a colorimetric plan."""
    if plan.output != "reflectance":
        return None
    F = forward(bundle, plan, wavelengths)
    W = output_weights(plan, wavelengths)
    e = np.asarray(spectra, np.float64) @ (W - plan.A @ F).T
    return float(np.mean(np.sqrt(np.mean(e ** 2, axis=1))))


def edge_mask(scene, width=2, top=0.10):
    """Pixels within ``width`` px of the scene's edges: those whose true mean-reflectance gradient magnitude is
    in the top ``top`` fraction."""
    from scipy import ndimage

    m = scene.reflectance.mean(axis=-1).astype(np.float64)
    g = np.hypot(ndimage.sobel(m, axis=0), ndimage.sobel(m, axis=1))
    edges = g > np.quantile(g, 1.0 - top)
    return ndimage.binary_dilation(edges, iterations=width)


def natural_table(description, bundle, draws, seed, denoise=(DENOISE_RADIUS, DENOISE_EPS)):
    cam = description.camera
    scene = natural_scene(cam.roi_height, cam.roi_width)
    prior = E.default_prior(HELD_OUT_CHART)
    plans = {"optimal-9": _optimal9(description, bundle, prior),
             "optimal-9+denoise": _optimal9(description, bundle, prior, denoise_radius=denoise[0])}
    near = edge_mask(scene)
    masks = {"within 2 px of edges": near, "elsewhere": ~near}
    print(f"\nnatural scene ({scene.name}), optimal-9 within 60 ms "
          f"({plans['optimal-9'].sequence_s * 1e3:.1f} ms), per-pixel RMSE, mean +- std over {draws} draws; "
          "ratio: to optimal-9 raw")
    for label, mask in masks.items():
        acc = {}
        for name, plan in plans.items():
            for d in range(draws):
                m, _ = measure(description, bundle, plan, scene, 7000 + d, denoise=denoise, mask=mask)
                for variant, vals in m.items():
                    acc.setdefault((name, variant), []).append(vals["rmse"])
        base = mean_std(acc[("optimal-9", "raw")])[0]
        for (name, variant), vals in acc.items():
            mu, sd = mean_std(vals)
            print(f"  {label:<22} ({mask.mean() * 100:4.1f} % of pixels) {name:<18} {variant:<9} {mu:.4f}+-{sd:.4f} "
                  f"(ratio {mu / base:.2f})")


def _optimal9(description, bundle, prior, denoise_radius=None):
    return E.budget_plan("optimal", bundle, 0.060, prior, lambda t: E.NoiseModel.from_rig(description, t),
                         frames=9, starts=4, min_frame_period_s=description.camera.min_frame_period_s,
                         denoise_radius=denoise_radius)


def tune(description, bundle, seed):
    """Per-pixel RMSE of optimal-9 within 60 ms, raw and denoised for a grid of (radius, eps), on the CES chart's
    patches and the natural scene within 2 px of its edges and elsewhere."""
    scene, prior, _, _, _ = chart_setup(description, "ces")
    plan = _optimal9(description, bundle, prior)
    cam = description.camera
    nat = natural_scene(cam.roi_height, cam.roi_width)
    near = edge_mask(nat)
    print(f"{'radius':>6}{'eps':>9}{'CES RMSE':>10}{'CES z':>7}{'nat edges':>11}{'nat else':>10}{'s':>6}")
    grid = [(None, None)] + [(r, e) for r in (2, 3, 5) for e in (1e-4, 1e-3, 1e-2)]
    for r, e in grid:
        dn = None if r is None else (r, e)
        m, _ = measure(description, bundle, plan, scene, 11, denoise=dn)
        a, _ = measure(description, bundle, plan, nat, 12, denoise=dn, mask=near)
        b, _ = measure(description, bundle, plan, nat, 12, denoise=dn, mask=~near)
        v = "raw" if r is None else "denoised"
        print(f"{r if r else 'raw':>6}{e if e else '':>9}{m[v]['rmse']:>10.4f}{m[v]['z']:>7.2f}{a[v]['rmse']:>11.4f}"
              f"{b[v]['rmse']:>10.4f}{m[v].get('seconds', 0.0):>6.2f}")


def subspace_table(description, keys):
    """Per chart, the mean over its patches of the RMSE of each patch's spectrum projected onto the best
    K-dimensional subspace of the training spectra its plans are designed on (uncentred: a linear decoder;
    centred: an affine one), and onto the chart's own best K-dimensional subspace. A decoder of K noise-free
    measurements writes spectra in a K-dimensional subspace, and a design optimal for the training spectra
    converges to their best one as the noise vanishes: the first two columns are what such designs reach with no
    noise at all (a reference, not a strict bound: another subspace could suit this chart better by chance); the
    third is what no training set could improve much on."""
    print("noise-free subspace reference on each chart's patches (mean over patches of the RMSE), K measurements, "
          "subspaces of the plans' training spectra")
    print(f"{'chart':<26}{'K':>3}{'linear':>9}{'affine':>9}{'own K':>9}")

    def mean_rmse(training, test, K, centred=False):
        mu = training.mean(axis=0) if centred else np.zeros(training.shape[1])
        U = np.linalg.eigh((training - mu).T @ (training - mu))[1][:, ::-1][:, :K]
        e = (test - mu) - (test - mu) @ U @ U.T
        return float(np.mean(np.sqrt(np.mean(e ** 2, axis=1))))

    for key in keys:
        scene, _, _, training, _ = chart_setup(description, key)
        test = np.stack([np.interp(DEFAULT_WAVELENGTHS, scene.wavelengths, scene.reflectance[m].mean(axis=0))
                         for m in scene.masks.values()])
        training = np.asarray(training, np.float64)  # on DEFAULT_WAVELENGTHS, as the prior built from it
        for K in (3, 6, 9):
            print(f"{CHARTS[key]:<26}{K:>3}{mean_rmse(training, test, K):>9.4f}"
                  f"{mean_rmse(training, test, K, True):>9.4f}{mean_rmse(test, test, K):>9.4f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=2)
    ap.add_argument("--charts", default="ces,tcs")
    ap.add_argument("--budgets", default="60,40,20")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small", action="store_true", help="320 x 240 (development; figures are 640 x 480)")
    ap.add_argument("--tune", action="store_true", help="measure the denoiser's radius and eps")
    ap.add_argument("--no-natural", action="store_true")
    ap.add_argument("--subspace-bound", action="store_true",
                    help="only: each chart's noise-free subspace reference with K = 3, 6, 9 (no capture, no "
                         "calibration)")
    a = ap.parse_args(argv)
    w, h = (320, 240) if a.small else (640, 480)
    description = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h))
    if a.subspace_bound:
        subspace_table(description, a.charts.split(","))
        return
    t0 = time.perf_counter()
    bundle = calibrate(description, seed=a.seed)
    print(f"default twin, paper noise, {w} x {h}; calibrated in {time.perf_counter() - t0:.0f} s")
    if a.tune:
        tune(description, bundle, a.seed)
        return
    budgets = tuple(float(x) for x in a.budgets.split(","))
    for key in a.charts.split(","):
        chart_table(description, bundle, key, a.draws, budgets, a.seed)
    if not a.no_natural:
        natural_table(description, bundle, a.draws, a.seed)
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
