"""Calibration against the twin's truth: how far the bundle's model is from the bench it measured.

    PYTHONPATH=. python tools/studies/calibration_truth.py [--profile lab] [--step 10] [--small]
        [--line-shape gaussian,measured]

Calibrates the twin once per line-shape model and prints :func:`specgpu.calibration.bundle.calibration_error` over
bands of ``--step`` nm across 400-700 nm: each band's response (model / truth - 1, RMS and worst), its centroid
(nm) and its shape (RMS difference of the unit-area responses, relative to the true peak: the line shape's error).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu.calibration import calibrate, calibration_error  # noqa: E402
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import rig_from_dict  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="lab", choices=("ideal", "lab"))
    ap.add_argument("--step", type=float, default=10.0, help="band width and spacing, nm")
    ap.add_argument("--small", action="store_true", help="320 x 240")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--line-shape", default="gaussian,measured",
                    help="the bundle's slit models to compare: gaussian (design FWHM), measured (probe scans)")
    args = ap.parse_args(argv)
    models = [m.strip() for m in args.line_shape.split(",") if m.strip()]
    bad = [m for m in models if m not in ("gaussian", "measured")]
    if bad or not models:
        raise SystemExit(f"--line-shape: unknown {bad[0] if bad else args.line_shape!r}; valid: gaussian, measured")
    t0 = time.perf_counter()
    desc = rig_from_dict({"twin": {"profile": args.profile, "seed": args.seed}})
    if args.small:
        desc = replace(desc, camera=CameraParameters(roi_width=320, roi_height=240))
    print(f"profile {args.profile}: bundle vs twin, bands of {args.step:g} nm over 400-700 nm (RMS / worst)")
    print(f"{'line shape':<12}{'band response %':>22}{'centroid nm':>20}{'shape % of peak':>22}")
    out = {}
    for m in models:
        bundle = calibrate(desc, seed=args.seed, line_shape=m)
        e = out[m] = calibration_error(bundle, desc, band_step_nm=args.step)
        print(f"{m:<12}{100 * e['rms_relative']:>11.3f} / {100 * e['max_relative']:<8.3f}"
              f"{e['rms_centroid_nm']:>9.3f} / {e['max_centroid_nm']:<8.3f}"
              f"{100 * e['rms_shape']:>11.3f} / {100 * e['max_shape']:<8.3f}")
    print(f"({time.perf_counter() - t0:.0f} s)")
    return out


if __name__ == "__main__":
    main()
