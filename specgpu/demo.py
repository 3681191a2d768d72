"""``specgpu demo``: the main job on the built-in twin, with the paper's tables beside ours and a report folder.

Calibrates the twin (both feedback loops), builds the reflectance basis with the evaluation chart left out,
plans narrowband-31, biased-6, symmetric-9 and the tristimulus imager for D65 and A, captures the 24-patch chart
at the camera's resolution through the capture path, recovers on the OpenCL device, evaluates per patch and per
pixel, prints Tables 1, 2 and 3 beside the paper's, and writes a report folder:

    index.html                  the tables and every figure, one page
    report.json                 every figure of the run, machine-readable
    calibration.npz, basis.npz  the calibration bundle and the basis table
    plans/<method>.npz          the plans (illuminant sequences and decoders)
    sequences/<method>/         the captured frames (16-bit TIFF, sequence.json, plan and calibration)
    cubes/<method>.exr          recovered reflectance cubes (JCGT spectral EXR, half) or XYZ maps
    maps/<method>-dE2000.exr    per-pixel CIEDE2000 against the truth (and a heat-map PNG beside it)
    png/<method>.png            sRGB renderings of the recoveries; png/truth.png the scene itself
    figures/*.png               spectra of the 24 patches (paper Fig. 15), illuminant sequences (Figs. 12, 14, 16)
"""

from __future__ import annotations

import html
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import io, paper
from .basis import save_basis
from .calibration import calibrate, save_calibration
from .evaluate import (evaluate_pixels, evaluate_reflectance, evaluate_XYZ, patch_means, scene_XYZ,
                       true_patch_spectra)
from .pipeline import EVALUATION_CHART, capture_plan, default_basis, read_capture, recover, to_XYZ, write_capture
from .plans import make_plan, save_plan
from .rig.config import RigDescription, load_rig
from .rig.scene import colorchecker_scene

__all__ = ["DEMO_METHODS", "DemoResult", "run_demo", "format_tables"]

#: The plans of the demo: name -> (method, keyword arguments besides the bundle and basis).
DEMO_METHODS = {
    "narrowband": ("narrowband", {"step_nm": 10.0}),
    "biased": ("biased", {"m": 5}),
    "symmetric": ("symmetric", {"m": 5}),
    "tristimulus-D65": ("tristimulus", {"illuminant": "D65"}),
    "tristimulus-A": ("tristimulus", {"illuminant": "A"}),
}
OUTPUT_WAVELENGTHS = np.arange(400.0, 701.0, 10.0)


def make_demo_plans(bundle, basis, names=None) -> dict:
    """The demo's plans (name -> Plan) made from a calibration bundle; ``names`` a subset of DEMO_METHODS."""
    plans = {}
    for name in (DEMO_METHODS if names is None else names):
        method, kwargs = DEMO_METHODS[name]
        args = (basis,) if method in ("biased", "symmetric") else ()
        extra = {"output_wavelengths": OUTPUT_WAVELENGTHS} if method in ("biased", "symmetric") else {}
        plans[name] = make_plan(method, bundle, *args, **kwargs, **extra)
    return plans


@dataclass
class DemoResult:
    out: Path
    seconds: float
    calibration: dict
    basis_variance: list
    methods: dict = field(default_factory=dict)  # name -> {"patch": PatchReport, "pixels": stats, "K", ...}


def _steps(echo, progress):
    from tqdm import tqdm

    return tqdm(total=3 + 2 * len(DEMO_METHODS) + 2, desc="demo", unit="step", leave=False, disable=not progress)


def run_demo(out="specgpu-report", *, rig=None, seed: int = 0, echo=print, progress: bool = True,
             device=None) -> DemoResult:
    """Run the demo and write its report folder; returns the figures (also in ``report.json``).

    Parameters
    ----------
    out : path
        Report folder (created; files of an earlier demo there are replaced).
    rig : path or RigDescription, optional
        The rig (default: the paper's, 640 x 480).
    seed : int
        Seed of the twin's noise.
    """
    t_start = time.perf_counter()
    out = Path(out)
    for sub in ("plans", "sequences", "cubes", "maps", "png", "figures"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    description = rig if isinstance(rig, RigDescription) else load_rig(rig)
    cam = description.camera
    scene = colorchecker_scene(cam.roi_height, cam.roi_width, chart=EVALUATION_CHART)
    bar = _steps(echo, progress)

    bar.set_description("calibrating")
    bundle = calibrate(description, seed=seed)
    save_calibration(out / "calibration.npz", bundle)
    bar.update()
    bar.set_description("basis")
    basis = default_basis(EVALUATION_CHART)
    save_basis(out / "basis.npz", basis)
    bar.update()
    bar.set_description("planning")
    plans = {}
    for name, (method, kwargs) in DEMO_METHODS.items():
        args = (basis,) if method in ("biased", "symmetric") else ()
        extra = {"output_wavelengths": OUTPUT_WAVELENGTHS} if method in ("biased", "symmetric") else {}
        plans[name] = make_plan(method, bundle, *args, **kwargs, **extra)
        save_plan(out / "plans" / f"{name}.npz", plans[name])
    bar.update()

    io.write_sRGB_preview(out / "png" / "truth.png", scene_XYZ(scene, "D65", device=device), exposure=0.0)
    result = DemoResult(out, 0.0, bundle.reports, basis.cumulative_variance[:9].tolist())
    for i, (name, plan) in enumerate(plans.items()):
        bar.set_description(f"capturing {name}")
        seq_dir = out / "sequences" / name
        captured = capture_plan(description, plan, scene, noise_seed=1000 + 17 * seed + i)
        write_capture(seq_dir, captured.sequences, captured.assembly, out / "plans" / f"{name}.npz",
                      out / "calibration.npz", metadata={"scene": scene.name}, overwrite=True)
        bar.update()
        bar.set_description(f"recovering {name}")
        folder = read_capture(seq_dir)  # the files, as `specgpu recover` reads them
        y = recover(folder, device=device)
        result.methods[name] = _evaluate(out, name, plan, y, scene, device)
        bar.update()

    bar.set_description("figures")
    _figures(out, plans, result, scene, bundle)
    bar.update()
    result.seconds = time.perf_counter() - t_start
    (out / "report.json").write_text(json.dumps(_report_json(result), indent=1))
    (out / "index.html").write_text(_html(result, plans))
    bar.update()
    bar.close()
    return result


def _evaluate(out, name, plan, y, scene, device):
    meta = {"plan_method": plan.method, "projections": plan.K, "plan_hash": plan.hash}
    if plan.output == "reflectance":
        io.write_cube(out / "cubes" / f"{name}.exr", y, plan.output_wavelengths, half=True, metadata=meta)
        patch = evaluate_reflectance(y, plan.output_wavelengths, scene, illuminant="D65")
        pixels = evaluate_pixels(y, scene, wavelengths=plan.output_wavelengths, illuminant="D65", device=device)
        XYZ = to_XYZ(y, plan, "D65", device=device)
        _, spectra = patch_means(y, scene.masks)
    else:
        io.write_map(out / "cubes" / f"{name}.exr", y, "XYZ", half=True, metadata=meta)
        patch = evaluate_XYZ(y, scene, illuminant=plan.illuminant)
        pixels = evaluate_pixels(y, scene, illuminant=plan.illuminant, device=device)
        XYZ, spectra = y, None
    io.write_map(out / "maps" / f"{name}-dE2000.exr", pixels.delta_E_2000, "dE2000", metadata=meta)
    io.write_delta_E_png(out / "maps" / f"{name}-dE2000.png", pixels.delta_E_2000, vmax=10.0)
    illuminant = None if plan.output == "reflectance" else _xy(plan.illuminant)
    io.write_sRGB_preview(out / "png" / f"{name}.png", XYZ, exposure=0.0, illuminant=illuminant)
    return {"patch": patch, "pixels": pixels.statistics(), "K": plan.K, "exposure_ms": plan.exposure_s * 1e3,
            "spectra": spectra, "wavelengths": plan.output_wavelengths, "output": plan.output}


def _xy(illuminant):
    import colour

    return colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"][illuminant]


# ---------------------------------------------------------------------------------------------------- tables


def format_tables(result: DemoResult) -> str:
    """Tables 1, 2 and 3 of the paper, ours beside theirs."""
    m = result.methods
    lines = ["Table 1: spectral reflectance recovery, 24 patches (patch means; dE under D65, 400-700 nm)",
             f"{'method':<12}{'':<7}{'RMSE avg':>9}{'RMSE max':>9}{'dEab avg':>9}{'dEab max':>9}"
             f"{'dE00 avg':>9}{'dE00 max':>9}{'proj.':>6}"]
    for name in ("narrowband", "biased", "symmetric"):
        s = m[name]["patch"].summary()
        p = paper.TABLE1[name]
        lines.append(f"{name:<12}{'ours':<7}{s['rmse'][0]:9.4f}{s['rmse'][1]:9.4f}{s['delta_E_ab'][0]:9.2f}"
                     f"{s['delta_E_ab'][1]:9.2f}{s['delta_E_2000'][0]:9.2f}{s['delta_E_2000'][1]:9.2f}"
                     f"{m[name]['K']:6d}")
        lines.append(f"{'':<12}{'paper':<7}{p[0]:9.4f}{p[1]:9.4f}{p[2]:9.2f}{p[3]:9.2f}{'-':>9}{'-':>9}{p[4]:6d}")
    nb, sy = m["narrowband"]["patch"], m["symmetric"]["patch"]
    lines += ["", "Table 2: per patch, narrowband (NB) and symmetric basis (SB); ours / paper",
              f"{'#':>2} {'patch':<14}{'RMSE NB':>16}{'RMSE SB':>16}{'dEab NB':>14}{'dEab SB':>14}"]
    for i, name in enumerate(paper.PATCHES):
        p = paper.TABLE2[i]
        lines.append(f"{i + 1:>2} {name:<14}{nb.rmse[i]:8.4f}/{p[0]:.4f}{sy.rmse[i]:9.4f}/{p[1]:.4f}"
                     f"{nb.delta_E_ab[i]:8.2f}/{p[2]:5.2f}{sy.delta_E_ab[i]:8.2f}/{p[3]:5.2f}")
    lines += ["", "Table 3: tristimulus imager, dE*ab per patch under D65 and A; ours / paper",
              f"{'#':>2} {'patch':<14}{'D65':>14}{'A':>14}"]
    d65, a = m["tristimulus-D65"]["patch"], m["tristimulus-A"]["patch"]
    for i, name in enumerate(paper.PATCHES):
        p = paper.TABLE3[i]
        lines.append(f"{i + 1:>2} {name:<14}{d65.delta_E_ab[i]:8.2f}/{p[0]:5.2f}{a.delta_E_ab[i]:8.2f}/{p[1]:5.2f}")
    sd, sa = d65.summary()["delta_E_ab"], a.summary()["delta_E_ab"]
    pd, pa = paper.TABLE3_SUMMARY["D65"], paper.TABLE3_SUMMARY["A"]
    lines.append(f"{'':>2} {'average':<14}{sd[0]:8.2f}/{pd[0]:5.2f}{sa[0]:8.2f}/{pa[0]:5.2f}")
    lines.append(f"{'':>2} {'maximum':<14}{sd[1]:8.2f}/{pd[1]:5.2f}{sa[1]:8.2f}/{pa[1]:5.2f}")
    lines.append(f"{'':>2} {'dE2000 avg':<14}{d65.summary()['delta_E_2000'][0]:8.2f}{'':>6}"
                 f"{a.summary()['delta_E_2000'][0]:8.2f}   (worst dE*ab: D65 {d65.worst()}, A {a.worst()})")
    cv = result.basis_variance
    lines += ["", f"basis: cumulative variance m=5 {cv[4]:.4f} (paper {paper.BASIS_VARIANCE_M5})",
              "per-pixel dE2000 mean (patches and surround): "
              + ", ".join(f"{k} {v['pixels']['delta_E_2000']['mean']:.2f}" for k, v in m.items())]
    return "\n".join(lines)


def _report_json(result: DemoResult) -> dict:
    methods = {}
    for name, r in result.methods.items():
        s = r["patch"].summary()
        rows = []
        for i, patch in enumerate(r["patch"].names):
            row = {"patch": patch, "dE76": float(r["patch"].delta_E_ab[i]),
                   "dE2000": float(r["patch"].delta_E_2000[i])}
            if r["patch"].rmse is not None:
                row["rmse"] = float(r["patch"].rmse[i])
            rows.append(row)
        methods[name] = {"projections": r["K"], "exposure_ms": r["exposure_ms"],
                         "rmse_mean": s.get("rmse", (None,))[0], "rmse_max": s.get("rmse", (None, None))[1],
                         "dE76_mean": s["delta_E_ab"][0], "dE76_max": s["delta_E_ab"][1],
                         "dE2000_mean": s["delta_E_2000"][0], "dE2000_max": s["delta_E_2000"][1],
                         "pixels": r["pixels"], "patches": rows}
    return {"seconds": result.seconds, "calibration": result.calibration, "basis_cumulative_variance":
            result.basis_variance, "methods": methods,
            "paper": {"table1": paper.TABLE1, "table3": paper.TABLE3_SUMMARY}}


# --------------------------------------------------------------------------------------------------- figures


def _figures(out, plans, result, scene, bundle):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names, truth = true_patch_spectra(scene, OUTPUT_WAVELENGTHS)
    for method in ("narrowband", "biased", "symmetric"):
        r = result.methods[method]
        fig, axes = plt.subplots(4, 6, figsize=(15, 9), sharex=True, sharey=True)
        for i, ax in enumerate(axes.flat):
            ax.plot(OUTPUT_WAVELENGTHS, truth[i], "k--", lw=1, label="truth")
            ax.plot(r["wavelengths"], r["spectra"][i], "C3", lw=1.3, label="recovered")
            ax.set_title(f"{i + 1} {names[i]}", fontsize=8)
            ax.set_ylim(0, 1)
        axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"{method} ({r['K']} projections): recovered (solid) vs true (broken) reflectance "
                     "(paper Fig. 15)")
        fig.supxlabel("wavelength (nm)")
        fig.supylabel("reflectance")
        fig.tight_layout()
        fig.savefig(out / "figures" / f"spectra-{method}.png", dpi=80)
        plt.close(fig)
    for name, plan in plans.items():
        fig, ax = plt.subplots(figsize=(8, 4))
        emitted = bundle.emitted(plan.patterns)  # the calibrated model of what the patterns emit
        for k in range(plan.K):
            ax.plot(plan.light_wavelengths, plan.target_spectra[k], lw=3, alpha=0.35, color=f"C{k % 10}")
            ax.plot(bundle.wavelengths, emitted[k], lw=1, color=f"C{k % 10}")
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel("spectral irradiance (W m$^{-2}$ nm$^{-1}$)")
        ax.set_title(f"{name}: {plan.K} illuminants (wide: targets; thin: emitted by the quantized patterns)",
                     fontsize=10)
        fig.tight_layout()
        fig.savefig(out / "figures" / f"illuminants-{name}.png", dpi=80)
        plt.close(fig)


def _html(result: DemoResult, plans) -> str:
    tables = html.escape(format_tables(result))
    items = []
    for name in result.methods:
        items.append(f"<h3>{html.escape(name)}</h3><p><img src='png/{name}.png' width=320> "
                     f"<img src='maps/{name}-dE2000.png' width=320> "
                     f"<img src='figures/illuminants-{name}.png' width=480></p>")
    spectra = "".join(f"<p><img src='figures/spectra-{m}.png' width=900></p>"
                      for m in ("narrowband", "biased", "symmetric"))
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>specgpu demo</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}} pre{{font-size:12px}}</style></head>
<body><h1>specgpu demo: the paper's experiment on the digital twin</h1>
<p>Tominaga and Horiuchi, JOSA A 29(9) 2012. Chart: {html.escape(EVALUATION_CHART)}, excluded from basis
training. Run time {result.seconds:.1f} s. Figures: <a href="report.json">report.json</a>.</p>
<p><img src="png/truth.png" width=320> (the scene under D65)</p>
<h2>Tables</h2><pre>{tables}</pre>
<h2>Recoveries: sRGB rendering, dE2000 against the truth (0-10), illuminant sequence</h2>{''.join(items)}
<h2>Recovered vs true spectra</h2>{spectra}
</body></html>
"""
