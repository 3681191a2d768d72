"""Error budget: what each imperfection of a real bench costs each method, alone, with and without corrections.

    PYTHONPATH=. python tools/studies/error_budget.py [--full] [--draws 1] [--methods \
        narrowband,symmetric,tristimulus-D65]
        [--effects stray_light_fraction,blur_px,...] [--json OUT.json]

For the ideal twin and then for every ``[realism]`` effect switched on alone at its lab magnitude
(:mod:`specgpu.rig.realism`), plus a typical ``[drift]`` (lamp -200 K, output -3 %, cut-on +5 nm since
calibration): calibrate the rig (the procedure sees the effect, as a bench's calibration would), plan, capture the
chart with a white tile above it, and recover twice:

- ``raw``: the calibration's dark level, the plan's decoder as made;
- ``corrected``: an ambient frame per sequence (subtracted) and the white-ROI rescaling of each sequence's decoder
  (:mod:`specgpu.planning.correction`).

Prints per-patch RMSE (reflectance methods) and dE2000 (patch means) per method, and the calibration's error
against the twin's truth (RMS relative band response). Runs at 320 x 240 unless ``--full``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu.apps.demo import DEMO_METHODS, make_demo_plans  # noqa: E402
from specgpu.apps.demo_measure import chart_with_white, mean_std, measure_methods  # noqa: E402
from specgpu.calibration import calibrate, calibration_error  # noqa: E402
from specgpu.pipeline.recovery import EVALUATION_CHART, default_basis  # noqa: E402
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import RigDescription  # noqa: E402
from specgpu.rig.realism import LAB, Drift, Realism  # noqa: E402

#: Effects whose lab value is a setting of another effect, not an effect of its own.
_PERIODS = ("grating_ripple_period_nm", "sensor_ripple_period_nm")
TYPICAL_DRIFT = Drift(lamp_cct_K=-200.0, lamp_output=-0.03, cut_on_nm=5.0)


def effects(names=None) -> dict:
    """label -> (Realism, Drift): the ideal rig, each lab effect alone, the typical drift, and everything."""
    keys = [k for k in Realism.keys() if k not in _PERIODS]
    if names:
        unknown = [n for n in names if n not in keys and n not in ("drift", "ideal", "lab")]
        if unknown:
            raise SystemExit(f"--effects: unknown {unknown[0]!r}; valid: ideal, drift, lab, {', '.join(keys)}")
        keys = [k for k in keys if k in names]
    out = {"ideal": (Realism(), Drift())}
    for k in keys:
        out[f"{k} = {getattr(LAB, k):g}"] = (LAB.only(k), Drift())
    if not names or "drift" in names:
        out["drift (-200 K, -3 %, +5 nm)"] = (Realism(), TYPICAL_DRIFT)
    if not names or "lab" in names:
        out["lab (all) + drift"] = (LAB, TYPICAL_DRIFT)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="640 x 480 (default 320 x 240)")
    ap.add_argument("--draws", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="narrowband,symmetric,tristimulus-D65")
    ap.add_argument("--effects", default="", help="comma-separated subset (realism keys, drift, lab, ideal)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)
    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in names if m not in DEMO_METHODS]
    if bad:
        raise SystemExit(f"--methods: unknown {bad[0]!r}; valid: {', '.join(DEMO_METHODS)}")
    chosen = [e.strip() for e in args.effects.split(",") if e.strip()]
    cam = CameraParameters() if args.full else CameraParameters(roi_width=320, roi_height=240)
    basis = default_basis(EVALUATION_CHART)
    t0 = time.perf_counter()
    print(f"error budget: {cam.roi_width} x {cam.roi_height}, {args.draws} draw(s); per method: patch RMSE / "
          f"dE2000, raw -> corrected (ambient frame + white ROI); calibration error: RMS band response vs truth")
    head = f"{'effect':<36}{'cal. err':>9}" + "".join(f"{n:>34}" for n in names)
    print(head)
    table = {}
    for label, (realism, drift) in effects(chosen).items():
        # capture half an hour after calibration, as on a bench (the per-hour drifts act on the clock)
        desc = RigDescription(camera=cam, seed=args.seed, realism=realism, capture_delay_s=1800.0)
        bundle = calibrate(desc, seed=args.seed)
        cal = calibration_error(bundle, desc)["rms_relative"]
        at_capture = replace(desc, drift=drift)
        plans = make_demo_plans(bundle, basis, names)
        scene, roi = chart_with_white(desc, EVALUATION_CHART)
        raw = measure_methods(at_capture, bundle, plans, scene, draws=args.draws, seed=args.seed, pixels=False)
        fixed = measure_methods(at_capture, bundle, plans, scene, draws=args.draws, seed=args.seed, pixels=False,
                                white_roi=roi, ambient=True)
        cells = []
        row = {"calibration_rms_relative": cal}
        for n in names:
            r0, r1 = raw[n], fixed[n]
            if "rmse" in r0:
                cells.append(f"{mean_std(r0['rmse'])[0]:.4f}/{mean_std(r0['dE00'])[0]:.2f} -> "
                             f"{mean_std(r1['rmse'])[0]:.4f}/{mean_std(r1['dE00'])[0]:.2f}")
            else:
                cells.append(f"{mean_std(r0['dE00'])[0]:.2f} -> {mean_std(r1['dE00'])[0]:.2f}")
            row[n] = {"raw": {k: v for k, v in r0.items() if k != "reports"},
                      "corrected": {k: v for k, v in r1.items() if k != "reports"}}
        table[label] = row
        print(f"{label:<36}{cal * 100:8.2f}%" + "".join(f"{c:>34}" for c in cells), flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.json:
        Path(args.json).write_text(json.dumps(table, indent=1, default=float))
    return table


if __name__ == "__main__":
    main()
