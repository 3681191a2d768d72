"""LED study: what an LED array of 6, 12 or 16 narrowband LEDs recovers against the DMD light, at one sequence
time, on measured charts the designs were not built on; so a lab can decide what to build.

For each light (the paper's DMD rig, and ``[light] kind = "led"`` with the presets ``led6``, ``led12``,
``led16`` of :mod:`specgpu.rig.led`; the same camera and noise), the twin is calibrated by the real procedure
(both feedback loops; each LED measured whole by the spectroradiometer) and, for each held-out chart:

* "CIE 2017 CES": colour-science's 99 CIE 2017 colour evaluation samples (measured spectra), 10 x 10 patches;
* "CIE 1995 TCS": the 14 Munsell chips of the CIE 1995 test colour samples,

the prior is trained on every other set colour-science ships minus the chart (and any spectrum within 0.01 RMS of
one of its patches), as ``tools/studies/budget_study.py`` does; the best design at the budget, the optimal design of
``specgpu plan optimal --frames 9 --sequence-ms 60`` (the best row of the equal-time table at 60 ms), is captured
``--draws`` times with fresh noise and recovered on the device; per-pixel RMSE and dE2000 (D65) are averaged over
the patches' pixels, mean +- std over the draws. Beside them: the number of primaries, the plan's exposure, the
RMSE it expects on its prior and the limit of any 9-frame design in 60 ms on the prior (``specgpu bound``).

Lumosaic's own accuracy figure is not known here, so no figure of it is printed beside the table.

    PYTHONPATH=. python tools/studies/led_study.py [--draws N] [--charts ces,tcs] [--lights dmd,led6,led12,led16] \
        [--size 320x240]
                              [--sequence-ms 60] [--frames 9]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from measured_chart import measured_chart_with_white  # noqa: E402

import specgpu.planning as E  # noqa: E402
from specgpu.apps.demo_measure import mean_std  # noqa: E402
from specgpu.calibration import calibrate  # noqa: E402
from specgpu.pipeline.evaluate import evaluate_pixels  # noqa: E402
from specgpu.pipeline.recovery import SequenceFolder, capture_plan, recover  # noqa: E402
from specgpu.planning.basis import (  # noqa: E402
    DEFAULT_WAVELENGTHS,
    evaluation_exclusions,  # noqa: E402
    load_reflectances,
)
from specgpu.planning.bound import design_bound  # noqa: E402
from specgpu.planning.design import plan_optimal  # noqa: E402
from specgpu.planning.priors import held_out_spectra  # noqa: E402
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import RigDescription  # noqa: E402
from specgpu.rig.led import LEDParameters  # noqa: E402
from specgpu.rig.scene import patch_scene  # noqa: E402

CHARTS = {"ces": "CIE 2017 CES", "tcs": "CIE 1995 TCS"}
LIGHTS = ("dmd", "led6", "led12", "led16")


def rig(light: str, width: int, height: int) -> RigDescription:
    """The paper's rig at ``width`` x ``height``, with its DMD light or an LED preset."""
    d = RigDescription(camera=CameraParameters(roi_width=width, roi_height=height))
    return d if light == "dmd" else replace(d, light=LEDParameters(preset=light))


def chart(description, key):
    """(scene, prior) of a held-out chart: the scene at the camera's size, the prior without the chart's set and
    without any spectrum within 0.01 RMS of one of its patches."""
    cam = description.camera
    name = CHARTS[key]
    if key == "ces":
        scene, _ = measured_chart_with_white(description, cam.roi_height, cam.roi_width)
    else:
        names, wl, spectra = held_out_spectra(name)
        scene = patch_scene(names, wl, spectra, cam.roi_height, cam.roi_width, name=name)
    test = np.stack([np.interp(DEFAULT_WAVELENGTHS, scene.wavelengths, scene.reflectance[m].mean(axis=0))
                     for m in scene.masks.values()])
    db = load_reflectances(exclude=evaluation_exclusions(name), exclude_similar_to=test)
    return scene, E.prior_from_spectra(db.reflectance, DEFAULT_WAVELENGTHS, f"colour-science sets without {name}")


def measure(description, bundle, plan, scene, seed) -> tuple[float, float]:
    """One capture and recovery: (per-pixel RMSE, per-pixel dE2000 under D65), means over the patches' pixels."""
    res = capture_plan(description, plan, scene, noise_seed=seed, calibration=bundle)
    folder = SequenceFolder(Path("<memory>"), np.stack([s.frames for s in res.sequences]), plan, bundle, [], {})
    y = recover(folder)
    mask = np.any(list(scene.masks.values()), axis=0)
    px = evaluate_pixels(y, scene, wavelengths=plan.output_wavelengths, illuminant="D65")
    return float(np.nanmean(px.rmse[mask])), float(np.nanmean(px.delta_E_2000[mask]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=3, help="noise draws per light and chart (default 3)")
    ap.add_argument("--charts", default="ces,tcs", help="held-out charts: ces, tcs (default both)")
    ap.add_argument("--lights", default=",".join(LIGHTS), help=f"lights (default {','.join(LIGHTS)})")
    ap.add_argument("--size", default="320x240", help="camera region of interest WxH (default 320x240)")
    ap.add_argument("--sequence-ms", type=float, default=60.0, help="time per sequence, ms (default 60)")
    ap.add_argument("--frames", type=int, default=9, help="frames of the design (default 9)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    charts = [c for c in a.charts.split(",") if c]
    lights = [x for x in a.lights.split(",") if x]
    for bad in [c for c in charts if c not in CHARTS] + [x for x in lights if x not in LIGHTS]:
        ap.error(f"unknown chart or light {bad!r}; charts: {', '.join(CHARTS)}; lights: {', '.join(LIGHTS)}")
    width, height = (int(v) for v in a.size.lower().split("x"))
    budget = a.sequence_ms / 1e3
    t0 = time.perf_counter()
    results = {}
    for light in lights:
        d = rig(light, width, height)
        print(f"[{time.perf_counter() - t0:6.0f} s] calibrating {light}", file=sys.stderr)
        bundle = calibrate(d, repeats=2, seed=a.seed)
        noise = lambda t, d=d: E.NoiseModel.from_rig(d, t)  # noqa: E731
        for key in charts:
            scene, prior = chart(d, key)
            plan = plan_optimal(bundle, prior, noise, frames=a.frames, sequence_s=budget,
                                min_frame_period_s=d.camera.min_frame_period_s, starts=4, seed=a.seed)
            bound = design_bound(bundle, prior, noise, frames=a.frames, sequence_s=budget,
                                 min_frame_period_s=d.camera.min_frame_period_s, starts=1)
            runs = [measure(d, bundle, plan, scene, 1000 * a.seed + 31 * k + 7) for k in range(a.draws)]
            results[light, key] = (bundle.columns, plan, bound, runs)
            print(f"[{time.perf_counter() - t0:6.0f} s] {light} on {CHARTS[key]} done", file=sys.stderr)
    print(f"\nOptimal {a.frames}-frame design within {a.sequence_ms:g} ms per sequence, {width} x {height} twin (the "
          f"paper's camera and noise), per-pixel means over the patches' pixels, mean +- std over {a.draws} draws; "
          "charts held out of the prior")
    print(f"{'chart':<14}{'light':<7}{'primaries':>10}{'exposure ms':>12}{'RMSE':>18}{'dE2000':>14}"
          f"{'expected':>10}{'any design >=':>15}")
    for key in charts:
        for light in lights:
            n, plan, bound, runs = results[light, key]
            (r, rs), (e, es) = mean_std([x[0] for x in runs]), mean_std([x[1] for x in runs])
            exp = plan.params.get("expected", {}).get("rmse")
            print(f"{CHARTS[key]:<14}{light:<7}{n:>10}{plan.exposure_s * 1e3:>12.3f}{f'{r:.4f}+-{rs:.4f}':>18}"
                  f"{f'{e:.2f}+-{es:.2f}':>14}{(f'{exp:.4f}' if exp else '-'):>10}{bound.lower_rmse:>15.4f}")
    print("Lumosaic (12 narrowband LEDs, 31 bands at 30 fps VGA): its reported accuracy figure is not known here.")
    print(f"[{time.perf_counter() - t0:.0f} s in all]", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
