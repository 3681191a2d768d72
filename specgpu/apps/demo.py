"""``specgpu demo``: the main job on the built-in twin, with the paper's tables beside ours and a report folder.

Calibrates the twin (both feedback loops), builds the reflectance basis with the evaluation chart left out,
plans narrowband-31, biased-6, symmetric-9 and the tristimulus imager for D65 and A, and beyond the paper the
Wiener decoder of symmetric-9 and designed illuminants with 9, 6 and 3 frames (:data:`ESTIMATOR_ROWS`, their
prior: every colour-science set but the chart's), captures the 24-patch chart
at the camera's resolution through the capture path, recovers on the OpenCL device, evaluates per patch and per
pixel, prints Tables 1, 2 and 3 beside the paper's and a moving-scene section (symmetric-9 at 200 fps on a scene
translating 3 px per frame: still, moving as decoded, motion-compensated; :mod:`specgpu.apps.moving_demo`), with
Table 1's 60 ms rows also on an LED rig (the same camera, a 12-LED array: :mod:`specgpu.apps.demo_lights`), and
writes a report folder:

    index.html                  the tables and every figure, one page
    report.json                 every figure of the run, machine-readable
    calibration.npz, basis.npz  the calibration bundle and the basis table
    calibrations/               every rig's bundle under its key, loaded by the next run on the same rig
    plans/<method>.npz          the plans (illuminant sequences and decoders)
    sequences/<method>/         the captured frames (16-bit TIFF, sequence.json, plan and calibration)
    cubes/<method>.exr          recovered reflectance cubes (JCGT spectral EXR, half) or XYZ maps
    maps/<method>-dE2000.exr    per-pixel CIEDE2000 against the truth (and a heat-map PNG beside it)
    png/<method>.png            sRGB renderings of the recoveries; png/truth.png the scene itself
    figures/*.png               the page's spectra of the 24 patches per reflectance method (paper Fig. 15) and
                                each plan's illuminant sequence (Figs. 12, 14, 16)

By default the demo is the quick one (:mod:`specgpu.apps.demo_scope`): the lab profile only, the paper's plans,
the design of each sequence-time budget, the moving scene, one noise draw; ``full=True`` (``specgpu demo
--full``) runs every row above on both profiles with two draws. It says first what it runs and about how long.
"""

from __future__ import annotations

import html
import json
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import colour
import numpy as np
from tqdm import tqdm

from specgpu import io
from specgpu.apps import paper
from specgpu.apps.demo_lights import LED_LABEL, led_draws, led_rig
from specgpu.apps.demo_measure import chart_with_white, mean_std, measure_methods
from specgpu.apps.demo_scope import DemoScope, StepClock, announce, demo_scope, estimate_steps
from specgpu.apps.moving_demo import moving_html, moving_lines, moving_section
from specgpu.apps.report import report_page, summarise_method, table2_html, table3_html
from specgpu.apps.table1 import Table1, equal_time_rows, method_rows, table1, table1_html, table1_text
from specgpu.calibration import save_calibration
from specgpu.calibration.bundle import calibration_error
from specgpu.calibration.cache import cached_calibration, calibration_file, find_calibration
from specgpu.io.paths import atomic_path
from specgpu.pipeline.capture_folder import SequenceFolder, write_capture
from specgpu.pipeline.evaluate import scene_XYZ
from specgpu.pipeline.recovery import EVALUATION_CHART, default_basis, uncertainty
from specgpu.planning import default_prior, make_plan, save_plan
from specgpu.planning.basis import save_basis
from specgpu.planning.equal_time import equal_time_bounds, equal_time_plans
from specgpu.planning.estimator_plans import study_plans
from specgpu.planning.noise import NoiseModel
from specgpu.planning.priors import training_spectra
from specgpu.rig.config import RigDescription, load_rig, rig_from_dict
from specgpu.rig.realism import Drift, Realism

__all__ = ["DEMO_METHODS", "ESTIMATOR_ROWS", "DemoResult", "run_demo", "format_tables"]

#: The plans of the demo: name -> (method, keyword arguments besides the bundle and basis).
DEMO_METHODS = {
    "narrowband": ("narrowband", {"step_nm": 10.0}),
    "biased": ("biased", {"m": 5}),
    "symmetric": ("symmetric", {"m": 5}),
    "tristimulus-D65": ("tristimulus", {"illuminant": "D65"}),
    "tristimulus-A": ("tristimulus", {"illuminant": "A"}),
}
OUTPUT_WAVELENGTHS = np.arange(400.0, 701.0, 10.0)
#: Rows beyond the paper (names of :data:`specgpu.planning.estimator_plans.STUDY_METHODS`): Wiener decoder of
#: symmetric-9 and the designed illuminants, decoded with the prior of every colour-science set but the evaluation
#: chart's, each recording the RMSE it expects on that prior.
ESTIMATOR_ROWS = ("wiener-9", "optimal-9", "optimal-6", "optimal-3")
#: The caption of the report's Table 1.
TABLE1_CAPTION = ("Table 1: spectral reflectance recovery, 24 patches (ΔE under D65, 400-700 nm); mean ± std "
                  "over the noise draws; the paper's row in italics; beneath, the methods at equal sequence time")


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
    """What ``specgpu demo`` made: its folder, how long it took, and the numbers its report shows."""

    out: Path
    seconds: float
    calibration: dict
    basis_variance: list
    methods: dict = field(default_factory=dict)  # name -> {"patch": PatchReport, "pixels": stats, "K", ...}
    #: profile label -> method name -> {metric: [value per noise draw]}
    #: (:func:`specgpu.apps.demo_measure.measure_methods`)
    draws: dict = field(default_factory=dict)
    #: profile label -> what was done (corrections, calibration error against the twin's truth)
    profiles: dict = field(default_factory=dict)
    main: str = ""
    #: budget (ms) -> the limit of any design of the equal-time rows' frame count (main profile)
    bounds: dict = field(default_factory=dict)
    #: the moving-scene section (:func:`specgpu.apps.moving_demo.moving_section`)
    moving: dict = field(default_factory=dict)
    #: step -> {"cpu_s", "wall_s", "estimate_s"}: what each step of the run took and what the estimate gave it
    #: (:meth:`specgpu.apps.demo_scope.StepClock.steps`)
    steps: dict = field(default_factory=dict)


def _steps(progress, scope: DemoScope):
    return tqdm(total=len(scope.profiles) * (2 + scope.plans()) + 3, desc="demo", unit="step", leave=False,
                disable=not progress)


def scope_of(profiles: dict, *, full: bool = False, draws: int | None = None) -> DemoScope:
    """The demo's scope on ``profiles`` (:func:`demo_profiles`): the quick demo, or every row with ``full``
    (:func:`specgpu.apps.demo_scope.demo_scope`)."""
    return demo_scope(profiles, full=full, draws=draws, methods=tuple(DEMO_METHODS), estimator_rows=ESTIMATOR_ROWS)


def demo_profiles(rig=None) -> dict:
    """label -> RigDescription the demo runs: the lab profile by default (or ``rig``), and beside it the same rig
    with every imperfection off (the ideal profile) when the main one has any."""
    if rig is None:
        description = rig_from_dict({"twin": {"profile": "lab"}}, source="<lab profile>")
    else:
        description = rig if isinstance(rig, RigDescription) else load_rig(rig)
    label = description.profile if description.realism.any or description.profile == "ideal" else "custom"
    profiles = {label: description}
    if description.realism.any or description.drift.any:
        profiles["ideal"] = replace(description, profile="ideal", realism=Realism(), drift=Drift(),
                                    capture_delay_s=None)
    return profiles


def run_demo(out="specgpu-report", *, rig=None, seed: int = 0, echo=print, progress: bool = True,
             device=None, draws: int | None = None, full: bool = False) -> DemoResult:
    """Run the demo and write its report folder; returns the figures (also in ``report.json``).

    Parameters
    ----------
    out : path
        Report folder (created; files of an earlier demo there are replaced).
    rig : path or RigDescription, optional
        The rig (default: the lab profile of the paper's rig, 640 x 480: every imperfection of a real bench on).
        With ``full``, when it has imperfections, the same rig with none (the ideal profile) is run beside it.
    seed : int
        Seed of the twin's noise.
    draws : int, optional
        Noise draws per method and profile: every table gives mean +- std over them (default 1, with ``full`` 2).
    full : bool
        Every row on every profile: the paper's plans, the estimator rows and every method at equal sequence
        time; else the quick demo: the main profile, the paper's plans and the design of each sequence-time
        budget (:mod:`specgpu.apps.demo_scope`). Either way the first line echoed says what runs and about how
        long it takes.

    Each rig is calibrated once: its bundle is kept under ``calibrations/`` in ``out`` and in the user's cache
    (:mod:`specgpu.calibration.cache`) and loaded, its hash checked, by a later run on the same rig. The time each
    step took (CPU and wall seconds) is recorded beside the estimate's share of it in ``report.json``
    (``steps``).

    On a rig with imperfections every sequence gets an ambient frame (every mirror off, subtracted: the DMD's
    off-state light and the room light are on the scene) and the chart has a reference white tile whose ROI
    rescales each sequence's decoder for the lamp's drift since calibration (:mod:`specgpu.planning.correction`).
    """
    t_start = time.perf_counter()
    clock = StepClock()
    out = Path(out)
    every_profile = demo_profiles(rig)  # a bad rig refused before the report folder is made
    scope = scope_of(every_profile, full=full, draws=draws)
    profiles = {label: every_profile[label] for label in scope.profiles}
    led_base = profiles.get("ideal", next(iter(profiles.values())))  # the LED rig: this one with 12 LEDs
    rigs = {**profiles, LED_LABEL: led_rig(led_base)}
    found = {label: find_calibration(d, [out / "calibrations"], seed=seed) for label, d in rigs.items()}
    calibrated = sum(f is not None for f in found.values())
    estimate = estimate_steps(scope, calibrated=calibrated)
    echo(announce(scope, full_scope=None if full else scope_of(every_profile, full=True), calibrated=calibrated))
    draws = scope.draws
    for sub in ("plans", "sequences", "cubes", "maps", "png", "figures"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    main = next(iter(profiles))
    bar = _steps(progress, scope)
    bar.set_description("basis")
    with clock("start"):
        basis = default_basis(EVALUATION_CHART)
        save_basis(out / "basis.npz", basis)
        prior = default_prior(EVALUATION_CHART)
        training = training_spectra(EVALUATION_CHART, prior.wavelengths)
    bar.update()

    def calibration(label):  # the bundle kept from an earlier run on this rig, else calibrated now and kept
        with clock("calibration"):
            if found[label] is not None:
                return found[label]
            bundle, path = cached_calibration(rigs[label], [out / "calibrations"], seed=seed)
            return bundle, path or calibration_file(rigs[label], out / "calibrations", seed=seed)
    result = DemoResult(out, 0.0, {}, basis.cumulative_variance[:9].tolist(), main=main)
    main_bundle = main_scene = None
    for label, description in profiles.items():
        is_main = label == main
        bar.set_description(f"calibrating ({label})")
        bundle, kept = calibration(label)
        bar.update()
        bar.set_description(f"planning ({label})")
        with clock("planning"):
            plans = make_demo_plans(bundle, basis)
            # one start (the smooth bumps; four gave the same designs on both profiles' calibrations, in twice the
            # time) and 100 iterations (the design's expected error within 0.2 % of 300 iterations', in a third)
            if scope.estimator_rows:
                plans.update(study_plans(description, bundle, prior, basis, methods=scope.estimator_rows,
                                         training=training, chart=EVALUATION_CHART, starts=1, iterations=100))
            lab = description.realism.any or description.drift.any
            # the methods at equal sequence time (an ambient frame per sequence on a lab rig, within the budget)
            plans.update(equal_time_plans(description, bundle, prior, basis, training=training, extra_frames=int(lab),
                                          rows=scope.equal_time_rows))
            if is_main:
                result.bounds = equal_time_bounds(description, bundle, prior, extra_frames=int(lab))
        scene, roi = chart_with_white(description, EVALUATION_CHART)
        corrections = {"white_roi": roi, "ambient": True} if lab else {}
        error = calibration_error(bundle, description)
        result.profiles[label] = {
            "corrections": ("ambient frame per sequence, white ROI " + ",".join(map(str, roi))) if lab else "none",
            "calibration_error": {k: error[k] for k in ("rms_relative", "max_relative", "rms_centroid_nm")},
            "realism": description.realism.to_dict(), "drift": description.drift.to_dict()}
        if is_main:
            result.calibration = bundle.reports
            _copy_calibration(kept, out / "calibration.npz", bundle)
            io.write_sRGB_preview(out / "png" / "truth.png", scene_XYZ(scene, "D65", device=device), exposure=0.0)
            main_bundle, main_scene = bundle, scene
        bar.update()

        def keep(name, draw, y, plan, captured, patch, pixels, _main=is_main, _scene=scene, _bundle=bundle,
                 _roi=roi, _rig=description):
            if _main and draw == 0:  # the report's files: the first draw of the main profile
                save_plan(out / "plans" / f"{name}.npz", plan)
                white = {"white_roi": ",".join(map(str, _roi)), "white_tile": float(_scene.reflectance[
                    _roi[1], _roi[0], 0]), "chart": EVALUATION_CHART} if corrections else {}
                # frames to look at and recover again, uncompressed: deflate keeps 4/5 of a noisy frame's size
                # and costs 40 times the CPU of writing it
                write_capture(out / "sequences" / name, captured.sequences, captured.assembly,
                              out / "plans" / f"{name}.npz", out / "calibration.npz",
                              metadata={"scene": _scene.name, **white}, overwrite=True, compression="none")
                sigma = None
                if plan.output == "reflectance":  # the rig's noise model's per-pixel sigma: the spectra's band
                    frames = np.stack([seq.frames for seq in captured.sequences])
                    noisy = replace(plan, params={"noise": NoiseModel.from_rig(_rig, plan.exposure_s).as_params(),
                                                  **plan.params})
                    sigma = uncertainty(SequenceFolder(out, frames, noisy, _bundle, [], {}), device=device,
                                        white_roi=white.get("white_roi"))[0]
                result.methods[name] = _evaluate(out, name, plan, y, _scene, device, sigma, patch, pixels)
            if draw == draws - 1:
                bar.set_description(f"{label}: {name}")
                bar.update()

        with clock("measuring"):
            result.draws[label] = measure_methods(description, bundle, plans, scene, draws=draws, seed=seed,
                                                  device=device, on_scored=keep, **corrections)
        for rows in result.draws[label].values():
            rows.pop("reports", None)

    bar.set_description("an LED rig")  # Table 1's 60 ms rows again with a 12-LED array as the light
    led_bundle = calibration(LED_LABEL)[0]
    with clock("led"):
        result.draws.update(led_draws(led_base, prior, basis, training, seed=seed, draws=draws, device=device,
                                      rows=scope.equal_time_rows, bundle=led_bundle))
    bar.set_description("a moving scene")
    with clock("moving"):
        result.moving = moving_section(every_profile.get("ideal", profiles[main]), basis, seed=seed,
                                       size=scope.moving_size)
    bar.update()
    bar.set_description("report")
    with clock("report"):  # the page with its figures, each spectra and illuminant figure also a file
        page = _html(result, main_scene, main_bundle, device, t_start,
                     keep=lambda name, png: (out / "figures" / f"{name}.png").write_bytes(png))
    result.steps = clock.steps(estimate)
    (out / "report.json").write_text(json.dumps(_report_json(result), indent=1))
    (out / "index.html").write_text(page)
    bar.update()
    bar.close()
    return result


def _copy_calibration(kept, path, bundle):
    """The report's ``calibration.npz``: a copy of the file ``bundle`` is kept in (written once, not compressed
    again), or ``bundle`` saved when that file is missing (a folder that could not be written)."""
    if kept is not None and Path(kept).is_file():
        with atomic_path(path) as tmp:
            shutil.copyfile(kept, tmp)
    else:
        save_calibration(path, bundle)


def _evaluate(out, name, plan, y, scene, device, sigma=None, patch=None, pixels=None):
    # the illuminant of the colours (a tristimulus plan's own): what `specgpu evaluate` of these files judges under
    meta = {"plan_method": plan.method, "projections": plan.K, "plan_hash": plan.hash,
            "illuminant": plan.resolve_illuminant(), **({"observer": plan.observer} if plan.output == "XYZ" else {})}
    summary = summarise_method(name, plan, y, scene, sigma=sigma, device=device, patch=patch, pixels=pixels)
    if plan.output == "reflectance":
        io.write_cube(out / "cubes" / f"{name}.exr", y, plan.output_wavelengths, half=True, metadata=meta)
    else:
        io.write_map(out / "cubes" / f"{name}.exr", y, "XYZ", half=True, metadata=meta)
    io.write_map(out / "maps" / f"{name}-dE2000.exr", summary.delta_E, "dE2000", metadata=meta)
    io.write_delta_E_png(out / "maps" / f"{name}-dE2000.png", summary.delta_E, vmax=10.0)
    illuminant = None if plan.output == "reflectance" else _xy(plan.illuminant)
    io.write_sRGB_preview(out / "png" / f"{name}.png", summary.XYZ, exposure=0.0, illuminant=illuminant)
    return {"patch": summary.patch, "pixels": summary.pixels, "K": plan.K, "exposure_ms": plan.exposure_s * 1e3,
            "spectra": summary.spectra, "wavelengths": plan.output_wavelengths, "output": plan.output,
            "summary": summary}


def _xy(illuminant):
    return colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"][illuminant]


# ---------------------------------------------------------------------------------------------------- tables


def table1_lines(result: DemoResult, methods) -> list[str]:
    """The console's Table 1 for ``methods`` (names of ``result.draws``' methods): the header and, for every
    profile run, mean +- std over the noise draws of per-patch RMSE, dE*ab, dE2000 (patch means), per-pixel RMSE
    and dE2000 means, the sequence time and frame count, then, for a plan that records an expected RMSE (an
    estimator's or a design's), the measured RMS error over the patches' pixels, the expected RMSE and their
    ratio; then the paper's row where it has one (:mod:`specgpu.apps.table1`, which the report's page renders
    too)."""
    return table1_text(Table1(method_rows(result.draws, methods)))


def equal_time_lines(result: DemoResult) -> list[str]:
    """Table 1's equal-time rows on the console: per budget, its methods (each within the budget, ambient frame
    included) and the limit of any design of that frame count at that budget (expected RMSE on the prior)."""
    return table1_text(Table1(equal_time_rows(result.draws, result.bounds)), header=False)


#: Table 1's methods beside the paper's, before the equal-time rows.
TABLE1_METHODS = ("narrowband", "biased", "symmetric", "tristimulus-D65", "tristimulus-A") + ESTIMATOR_ROWS


def format_tables(result: DemoResult) -> str:
    """Tables 1, 2 and 3 of the paper, ours beside theirs."""
    m = result.methods
    draws = len(next(iter(next(iter(result.draws.values())).values()))["dE00"]) if result.draws else 1
    lines = ["profiles: " + "; ".join(f"{k}: corrections {v['corrections']}, calibration vs the twin's truth "
                                       f"{v['calibration_error']['rms_relative'] * 100:.2f} % RMS band response, "
                                       f"{v['calibration_error']['rms_centroid_nm']:.2f} nm RMS centroid"
                                       for k, v in result.profiles.items()),
             f"Table 1: spectral reflectance recovery, 24 patches (dE under D65, 400-700 nm); mean +- std over "
             f"{draws} noise draws; patch means and per-pixel means; beyond the paper, wiener-9 and optimal-K "
             f"(prior without the chart): RMS pixel error over the patches beside the RMSE expected on the prior"]
    lines += table1_text(table1(result.draws, TABLE1_METHODS, result.bounds))
    if result.moving:
        lines += moving_lines(result.moving)
    if result.main:
        lines.append(f"(Tables 2 and 3: the {result.main} profile, first draw)")
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

    draws = {label: {name: {k: {"values": v, "mean": mean_std(v)[0], "std": mean_std(v)[1]}
                            for k, v in rows.items() if isinstance(v, list)} | {"K": rows["K"]}
                     | {"sequence_ms": rows.get("sequence_ms")}
                     | ({"expected_rmse": rows["expected_rmse"]} if "expected_rmse" in rows else {})
                     for name, rows in runs.items()} for label, runs in result.draws.items()}
    bounds = {f"{T:g}ms": {"frames": b.frames, "lower_rmse": b.lower_rmse, "achieved_rmse": b.achieved_rmse,
                           "noise_free_rmse": b.noise_free_rmse, "exposure_s": b.exposure_s}
              for T, b in result.bounds.items()}
    moving = {k: v for k, v in result.moving.items() if k != "maps"}
    return {"main_profile": result.main, "profiles": result.profiles, "draws": draws, "bounds": bounds,
            "moving_scene": moving, "steps": result.steps,
            "seconds": result.seconds, "calibration": result.calibration, "basis_cumulative_variance":
            result.basis_variance, "methods": methods,
            "paper": {"table1": paper.TABLE1, "table3": paper.TABLE3_SUMMARY}}


def _html(result: DemoResult, scene, bundle, device, t_start: float, keep=None) -> str:
    """The report page (:func:`specgpu.apps.report.report_page`) with Tables 1-3, ours beside the paper's; the
    run time it states, and ``result.seconds``, count the whole job from ``t_start`` (``time.perf_counter``), the
    page's figures included; ``keep``: :func:`specgpu.apps.report.report_page`'s."""
    m = result.methods
    tables = table1_html(table1(result.draws, TABLE1_METHODS, result.bounds), TABLE1_CAPTION)
    if all(k in m for k in ("narrowband", "symmetric")):
        tables += table2_html(m["narrowband"]["patch"], m["symmetric"]["patch"])
    if all(k in m for k in ("tristimulus-D65", "tristimulus-A")):
        tables += table3_html(m["tristimulus-D65"]["patch"], m["tristimulus-A"]["patch"])
    profiles = "; ".join(f"{html.escape(k)}: corrections {html.escape(v['corrections'])}, calibration vs the "
                         f"twin's truth {v['calibration_error']['rms_relative'] * 100:.2f} % RMS band response"
                         for k, v in result.profiles.items())

    def intro():  # made once every figure of the page is drawn: the run time counts them
        result.seconds = time.perf_counter() - t_start
        return (f"<p>The paper's experiment (Tominaga and Horiuchi, JOSA A 29(9) 2012) on the digital twin: chart "
                f"{html.escape(EVALUATION_CHART)}, left out of the basis training; profiles {profiles}. Tables 2, "
                f"3 and the figures: the {html.escape(result.main)} profile, first noise draw. Run time "
                f"{result.seconds:.1f} s, figures included; every figure in <a href='report.json'>report.json</a>."
                "</p>")

    summaries = {name: r["summary"] for name, r in m.items()}
    return report_page("specgpu demo: the paper's experiment on the digital twin", intro, summaries, scene=scene,
                       bundle=bundle, tables=tables, device=device,
                       sections=moving_html(result.moving) if result.moving else "", keep=keep)
