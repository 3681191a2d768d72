"""Live accuracy study: a chart of measured spectra with a white strip, still and moving 3 px per frame, recovered
by the best still path, by ``recover`` and by the stream with motion compensation, the white and the denoiser.

On the default twin (the paper's rig and noise), calibrated by both feedback loops, the chart of
``measured_chart.measured_chart_with_white`` (colour-science's 99 CIE 2017 CES samples, in neither the prior nor
the basis, with the bench's reference white strip above the patches), the plan of the budget study's best 9-frame
row (``specgpu plan optimal --sequence-ms 60 --denoise``: optimal-9 designed for the filter within 60 ms):

* ``still``: the chart still, ``recover --white-roi --denoise`` (the still chart's best path);
* ``recover``: the chart moving 3 px a frame (x), one capture per draw, ``recover --motion global --denoise
  --white-roi ROI --white-roi-moves scene``, its sigma at the warped samples (``uncertainty(motion="global")``)
  carried through the filter (``uncertainty(denoise=...)``);
* ``stream``: the same moving twin streamed (``pipeline.stream.Stream``, the twin driver) with ``motion="global"``,
  the denoiser, the white measured on the compensated samples, and the ``cube`` and ``sigma`` outputs (the sigma
  only where the stream accepts it with the denoiser: the table says when it did not);
* ``stream raw``: the same stream without the denoiser, with its sigma (the z-scores of the stream's own sigma
  at the warped samples);
* ``recover strip``: ``recover`` as above with the whole strip's ROI, as for the still chart (what a ROI that
  the moving strip leaves costs).

The white strip moves with the chart: ``--white-roi`` names where it is at the sequence's reference time, so the
ROI is the part of the strip that stays white over every sequence scored (the strip less the chart's travel).
Each figure is per pixel over the patches' interiors (the central 70 % of each patch, moved with the chart, pixels
the compensation left NaN excluded) and per patch (each patch's mean spectrum): RMSE over the bands and dE2000
(D65), and the standard deviation of the z-scores ``(estimate - truth) / sigma`` over the patches' pixels and bands;
mean +- std over ``--draws`` noise draws. The moving paths' ratio to the still path is printed beside the 1.3
target.

    PYTHONPATH=. python tools/studies/live_accuracy.py [--draws N] [--sequences N] [--small] [--json OUT.json]

``--small`` runs at 320 x 240 (development; the figures are 640 x 480). The JSON (default
``results/live_accuracy.json``) holds every draw's figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from budget_study import _optimal9, chart_setup  # noqa: E402

from specgpu.apps.demo_measure import mean_std  # noqa: E402
from specgpu.calibration import calibrate  # noqa: E402
from specgpu.capture.session import capture_sequences  # noqa: E402
from specgpu.capture.twin_driver import TwinDriver  # noqa: E402
from specgpu.pipeline.capture_folder import SequenceFolder  # noqa: E402
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS, denoise_recovery  # noqa: E402
from specgpu.pipeline.evaluate import evaluate_pixels, truth_cube  # noqa: E402
from specgpu.pipeline.recovery import recover, uncertainty  # noqa: E402
from specgpu.pipeline.stream import Stream  # noqa: E402
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import RigDescription  # noqa: E402
from specgpu.rig.motion import MotionParameters  # noqa: E402
from specgpu.rig.scene import SpectralScene  # noqa: E402
from specgpu.rig.twin import TwinRig  # noqa: E402

VELOCITY = (3.0, 0.0)  # px per frame
TARGET = 1.3  # the moving paths' RMSE and dE2000 at most this times the still path's
DENOISE = (DENOISE_RADIUS, DENOISE_EPS)


def moving_rig(description, bundle, plan, scene, seed):
    """The twin as ``capture_plan`` builds it (its clock where the calibration ended), its chart moving."""
    clock = description.capture_delay + float(bundle.reports.get("rig_clock_end_s", 0.0))
    rig = TwinRig(plan.rig_description(description), scene=scene, clock_start_s=clock)
    rig.seed = seed
    return rig


def moved_scene(scene, truth, frame_period_s, velocity=VELOCITY) -> SpectralScene:
    """The chart as it is at a sequence's reference time: the twin's truth cube, the patches' masks moved by the
    chart's displacement then (rounded to whole pixels: the masks are the patches' interiors)."""
    shift = np.rint(np.asarray(velocity) * truth["reference_time_s"] / frame_period_s).astype(int)
    h, w = scene.reflectance.shape[:2]
    masks = {}
    for name, m in scene.masks.items():
        moved = np.zeros_like(m)
        ys, xs = np.nonzero(m)
        ys, xs = ys + shift[1], xs + shift[0]
        keep = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
        moved[ys[keep], xs[keep]] = True
        if moved.sum() >= 0.5 * m.sum():  # a patch mostly out of the field is not scored
            masks[name] = moved
    return SpectralScene(scene.wavelengths, truth["reflectance"], masks, scene.name)


def score(y, sigma, scene, wavelengths) -> dict:
    """Per-pixel and per-patch RMSE and dE2000 (D65) of cube ``y`` over ``scene``'s masks, and the z-scores'
    standard deviation (``sigma`` None: not measured)."""
    mask = np.any(list(scene.masks.values()), axis=0)
    px = evaluate_pixels(y, scene, wavelengths=wavelengths, illuminant="D65")
    truth = truth_cube(scene, wavelengths)
    row = {"px_rmse": float(np.nanmean(px.rmse[mask])), "px_dE00": float(np.nanmean(px.delta_E_2000[mask])),
           "nan_share": float(np.mean(~np.isfinite(y[mask]).all(axis=-1)))}
    names = list(scene.masks)
    means = np.stack([np.nanmean(y[scene.masks[n]], axis=0) for n in names])[None].astype(np.float32)
    truths = np.stack([truth[scene.masks[n]].mean(axis=0) for n in names])
    patch_wl = scene.wavelengths
    patch_truth = np.stack([scene.reflectance[scene.masks[n]].mean(axis=0) for n in names])[None]
    patches = SpectralScene(patch_wl, patch_truth.astype(np.float32), {}, "patch means")
    pp = evaluate_pixels(means, patches, wavelengths=wavelengths, illuminant="D65")
    row["patch_rmse"] = float(np.sqrt(np.mean((means[0] - truths) ** 2, axis=-1)).mean())
    row["patch_dE00"] = float(np.nanmean(pp.delta_E_2000))
    if sigma is not None:
        z = ((y - truth) / sigma)[mask]
        row["z"] = float(np.nanstd(z))
    return row


def still_draw(description, bundle, plan, scene, roi, seed) -> dict:
    """The still chart's best path: ``recover --white-roi --denoise``, its sigma carried through the filter."""
    rig = moving_rig(description, bundle, plan, scene, seed)
    seq = capture_sequences(TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K, pacing="free"), plan.K)
    folder = SequenceFolder(Path("<memory>"), seq.sequences[0].frames[None], plan, bundle, [], {})
    y = denoise_recovery(folder, recover(folder, white_roi=roi), radius=DENOISE[0], eps=DENOISE[1])
    sigma = uncertainty(folder, white_roi=roi, denoise=DENOISE)[0]
    return score(y, sigma, scene, plan.output_wavelengths)


def recover_draw(moving, bundle, plan, scene, roi, seed) -> dict:
    """The moving chart by ``recover --motion global --denoise --white-roi ROI --white-roi-moves scene``."""
    rig = moving_rig(moving, bundle, plan, scene, seed)
    seq = capture_sequences(TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K, pacing="free"), plan.K)
    s = seq.sequences[0]
    folder = SequenceFolder(Path("<memory>"), s.frames[None], plan, bundle, [], {})
    y = recover(folder, white_roi=roi, motion="global", denoise=DENOISE, white_moves="scene")
    sigma = uncertainty(folder, white_roi=roi, motion="global", white_moves="scene", denoise=DENOISE)[0]
    truth = moved_scene(scene, rig.motion_truth(s.timestamps_s), rig.frame_period_s,
                        moving.motion.velocity_px_per_frame)
    return score(y, sigma, truth, plan.output_wavelengths)


def stream_draws(moving, bundle, plan, scene, roi, seed, sequences, denoise=DENOISE) -> tuple[list, str | None]:
    """The moving chart streamed with ``motion="global"``, the denoiser (None: without) and the white on the
    compensated samples: one row per sequence; and why the stream refused the sigma output, if it did."""
    rig = moving_rig(moving, bundle, plan, scene, seed)
    truth_rig = moving_rig(moving, bundle, plan, scene, seed)
    kept = []

    def keep(result):
        cube = result.arrays["cube"].astype(np.float32)
        sigma = result.arrays.get("sigma")  # each band's standard deviation, then their RMS
        kept.append((cube, None if sigma is None else sigma[..., :cube.shape[-1]].astype(np.float32),
                     np.array(result.timestamps_s), np.array(result.motion.shifts)))

    refused = None
    for outputs in (("cube", "sigma"), ("cube",)):
        try:
            stream = Stream(TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K * sequences, pacing="free"),
                            plan, bundle, outputs=outputs, sinks=[keep], illuminant="D65", cube_dtype=np.float32,
                            policy="block", white_roi=roi, white_moves="scene", denoise=denoise, motion="global")
            break
        except ValueError as exc:
            refused = str(exc)
    stream.run()
    rows = []
    for y, sigma, timestamps, shifts in kept:
        truth = truth_rig.motion_truth(timestamps)
        row = score(y, sigma, moved_scene(scene, truth, rig.frame_period_s, moving.motion.velocity_px_per_frame),
                    plan.output_wavelengths)
        row["shift_error_px"] = float(np.abs(shifts - truth["displacement"]).max())
        rows.append(row)
    return rows, refused


def strip_roi(roi: str, travel_px: float) -> str:
    """The part of the white strip's ROI (x, y, w, h) that stays on the strip while it moves ``travel_px`` right."""
    x, y, w, h = (int(v) for v in roi.split(","))
    d = int(math.ceil(travel_px)) + 2  # and the bilinear sample's neighbour
    return f"{x + d},{y},{w - d},{h}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--sequences", type=int, default=2, help="sequences streamed per draw")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small", action="store_true", help="320 x 240 (development; figures are 640 x 480)")
    ap.add_argument("--velocity", type=float, default=VELOCITY[0],
                    help="the chart's speed, px per frame rightwards (> 0)")
    ap.add_argument("--blur", action="store_true", help="each frame integrated over its exposure (motion blur)")
    ap.add_argument("--json", default=str(Path(__file__).resolve().parents[2] / "results" / "live_accuracy.json"))
    a = ap.parse_args(argv)
    if not a.velocity > 0:
        ap.error(f"--velocity must be a positive speed (the white ROI is kept where the strip stays), got {a.velocity}")
    w, h = (320, 240) if a.small else (640, 480)
    description = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h))
    t0 = time.perf_counter()
    bundle = calibrate(description, seed=a.seed)
    scene, prior, _, _, roi = chart_setup(description, "ces")
    plan = _optimal9(description, bundle, prior, denoise_radius=DENOISE_RADIUS)
    print(f"default twin, paper noise, {w} x {h}; calibrated and planned in {time.perf_counter() - t0:.0f} s; "
          f"{plan.method} K={plan.K}, sequence {plan.sequence_s * 1e3:.1f} ms, planned for the filter")
    velocity = (a.velocity, 0.0)
    moving = replace(description, motion=MotionParameters(velocity_px_per_frame=velocity, blur=a.blur))
    travel = abs(a.velocity) * (plan.K * (a.sequences - 1) + plan.K)  # the strip's furthest reference-time shift
    moving_roi = strip_roi(roi, travel)
    print(f"chart {scene.name}: {len(scene.masks)} patches; white ROI still {roi}, moving {moving_roi}; "
          f"chart moving {a.velocity:g} px/frame{' with motion blur' if a.blur else ''}")
    rows = {"still": [], "recover": [], "stream": [], "stream raw": [], "recover strip": []}
    refused = None
    for d in range(a.draws):
        seed = 1000 * a.seed + 31 * d + 7
        rows["still"].append(still_draw(description, bundle, plan, scene, roi, seed))
        rows["recover"].append(recover_draw(moving, bundle, plan, scene, moving_roi, seed))
        streamed, refused = stream_draws(moving, bundle, plan, scene, moving_roi, seed, a.sequences)
        rows["stream"].extend(streamed)
        rows["stream raw"].extend(stream_draws(moving, bundle, plan, scene, moving_roi, seed, a.sequences, None)[0])
        rows["recover strip"].append(recover_draw(moving, bundle, plan, scene, roi, seed))
        print(f"  draw {d + 1}/{a.draws} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    print_table(rows, a.draws, a.sequences, refused)
    out = {"size": [w, h], "velocity_px_per_frame": list(velocity), "blur": a.blur, "draws": a.draws,
           "sequences": a.sequences,
           "plan": {"method": plan.method, "K": plan.K, "sequence_ms": plan.sequence_s * 1e3},
           "white_roi": {"still": roi, "moving": moving_roi}, "stream_sigma_refused": refused, "rows": rows}
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(out, indent=1))
    print(f"\n{time.perf_counter() - t0:.0f} s; {a.json}")


def print_table(rows, draws, sequences, refused):
    cols = (("px_rmse", "px RMSE", 4), ("px_dE00", "px dE00", 3), ("patch_rmse", "patch RMSE", 4),
            ("patch_dE00", "patch dE00", 3), ("z", "z std", 2), ("nan_share", "NaN share", 4))
    print(f"\nper pixel over the patches' interiors and per patch, mean +- std over {draws} draws "
          f"(stream: {sequences} sequences each)")
    print(f"{'path':<14}" + "".join(f"{label:>19}" for _, label, _ in cols) + f"{'RMSE ratio':>12}{'dE ratio':>10}")
    still = {k: mean_std([r[k] for r in rows["still"]])[0] for k in ("px_rmse", "px_dE00")}
    for name, rs in rows.items():
        line = f"{name:<14}"
        for key, _, digits in cols:
            vals = [r[key] for r in rs if key in r]
            mu, sd = mean_std(vals)
            line += f"{(f'{mu:.{digits}f}+-{sd:.{digits}f}' if vals else '-'):>19}"
        ratio = [mean_std([r[k] for r in rs])[0] / still[k] for k in ("px_rmse", "px_dE00")]
        line += f"{ratio[0]:>12.2f}{ratio[1]:>10.2f}"
        print(line)
    if rows["stream"] and "shift_error_px" in rows["stream"][0]:
        print(f"stream: largest shift error {max(r['shift_error_px'] for r in rows['stream']):.3f} px")
    if refused:
        print(f"stream sigma refused with the denoiser: {refused}")
    print(f"target: the moving paths within {TARGET:g} x the still path's RMSE and dE2000; z std in [0.8, 1.25]")


if __name__ == "__main__":
    main()
