"""Drift study: calibrate without drift, capture with a drifted lamp, recover with and without correction.

    PYTHONPATH=. python tools/studies/drift_study.py [--profile lab] [--draws 3] [--small]
        [--cct -200] [--output -0.03] [--cut-on 5] [--methods narrowband,symmetric,tristimulus-D65]
        [--probes 430,650]

Prints, per method, per-patch RMSE / dE2000 and per-pixel dE2000 (mean +- std over noise draws) for: no drift
with the calibration's dark level (no ambient frame); then, every sequence with an ambient frame: no drift; no
drift with the white-ROI correction; drift uncorrected; drift with the white-ROI correction. With ``--probes``
every sequence also carries those drift probes (narrow bands, nm, read by the white only).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu.apps.demo import DEMO_METHODS, make_demo_plans  # noqa: E402
from specgpu.apps.demo_measure import chart_with_white, mean_std, measure_methods  # noqa: E402
from specgpu.calibration import calibrate  # noqa: E402
from specgpu.pipeline.recovery import EVALUATION_CHART, default_basis  # noqa: E402
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import rig_from_dict  # noqa: E402
from specgpu.rig.realism import Drift  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="lab", choices=("ideal", "lab"))
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--small", action="store_true", help="320 x 240")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cct", type=float, default=-200.0)
    ap.add_argument("--output", type=float, default=-0.03)
    ap.add_argument("--cut-on", type=float, default=5.0)
    ap.add_argument("--methods", default="narrowband,symmetric,tristimulus-D65")
    ap.add_argument("--probes", default="", help="drift probe centres, nm, comma-separated (e.g. 430,650)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    desc = rig_from_dict({"twin": {"profile": args.profile, "seed": args.seed}})
    if args.small:
        desc = replace(desc, camera=CameraParameters(roi_width=320, roi_height=240))
    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in names if m not in DEMO_METHODS]
    if unknown:
        raise SystemExit(f"--methods: unknown {unknown[0]!r}; valid: {', '.join(DEMO_METHODS)}")
    try:
        probes = [float(p) for p in args.probes.split(",") if p.strip()]
    except ValueError:
        raise SystemExit(f"--probes must be wavelengths in nm separated by commas, got {args.probes!r}") from None
    bundle = calibrate(desc, seed=args.seed)
    plans = make_demo_plans(bundle, default_basis(EVALUATION_CHART), names)
    scene, roi = chart_with_white(desc, EVALUATION_CHART)
    drifted = replace(desc, drift=Drift(lamp_cct_K=args.cct, lamp_output=args.output, cut_on_nm=args.cut_on))
    runs = {  # every run but the first subtracts an ambient frame per sequence (the lab's off-state and room light)
        "no drift, calibration dark": (desc, {}),
        "no drift": (desc, {"ambient": True}),
        "no drift, white ROI": (desc, {"white_roi": roi, "ambient": True}),
        "drift, uncorrected": (drifted, {"ambient": True}),
        "drift, white ROI": (drifted, {"white_roi": roi, "ambient": True}),
    }
    print(f"profile {args.profile}, {desc.camera.roi_width} x {desc.camera.roi_height}, drift: lamp "
          f"{args.cct:+g} K, output {args.output:+g}, cut-on {args.cut_on:+g} nm; white ROI {roi}; "
          f"drift probes {probes or 'none'}; "
          f"{args.draws} noise draws (mean +- std)")
    print(f"{'method':<17}{'run':<31}{'RMSE patch':>18}{'dE00 patch':>16}{'dE00 pixel':>16}")
    results = {}
    for label, (d, kw) in runs.items():
        results[label] = measure_methods(d, bundle, plans, scene, draws=args.draws, seed=args.seed, probes=probes,
                                         **kw)
    for name in names:
        for label in runs:
            r = results[label][name]
            rm = mean_std(r.get("rmse", []))
            de = mean_std(r["dE00"])
            px = mean_std(r["px_dE00"])
            rms = f"{rm[0]:.4f} +- {rm[1]:.4f}" if r.get("rmse") else "-"
            print(f"{name:<17}{label:<31}{rms:>18}{de[0]:>9.2f} +- {de[1]:.2f}{px[0]:>9.2f} +- {px[1]:.2f}")
    print(f"({time.perf_counter() - t0:.0f} s)")
    return results


if __name__ == "__main__":
    main()
