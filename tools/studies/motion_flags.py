"""Moving scenes against their truth: how many pixels a motion-compensated recovery leaves unflagged with a wrong
spectrum, and how much it flags.

One sequence per case is captured on the moving twin through the capture path (the paper's noise, 200 fps, the
natural scene, symmetric-9 with its oracle calibration), recovered as ``specgpu recover --motion MODE`` does
(:func:`specgpu.pipeline.moving_layers.recover_moving` with the plan's residual check) and scored per pixel
against the scene at the sequence's reference time, as ``specgpu evaluate --truth SEQ`` scores it. Columns: the
unflagged pixels whose RMSE exceeds ``--bound`` (a still recovery's worst pixel is about 0.07), the flagged share
of the field (NaN: outside the field, saturated or inconsistent), and the RMSE (mean, 99th percentile, largest)
and dE2000 95th percentile of the unflagged pixels. ``--sweep`` adds every speed of the scene and of a chart
(0-50 px per frame) in each mode.

    PYTHONPATH=. python tools/studies/motion_flags.py                      # the cases at 640 x 480 (~2 min)
    PYTHONPATH=. python tools/studies/motion_flags.py --size 320x240 --sweep
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.motion.residual import residual_check
from specgpu.pipeline.evaluate import evaluate_pixels
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.recovery import default_basis
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.basis_plans import plan_symmetric_basis
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import SpectralScene
from specgpu.rig.twin import TwinRig

EXPOSURE_S = 0.0049
MODES = {"global": "translation", "affine": "affine", "flow": "flow"}


def chart(speed: float) -> MotionParameters:
    return MotionParameters(object="colorchecker", object_velocity_px_per_frame=(float(speed), 0.0))


#: (label, motion, mode, size or None for ``--size``)
CASES = [
    ("still", MotionParameters(), "global", None),
    ("scene 3 px/frame", MotionParameters(velocity_px_per_frame=(2.4, 1.8)), "global", None),
    ("chart 14 px/frame over the scene", chart(14.0), "global", None),
    ("chart 14 px/frame over the scene", chart(14.0), "flow", None),
    ("chart 3 px/frame over the scene", chart(3.0), "affine", None),
    ("scene 20 px/frame", MotionParameters(velocity_px_per_frame=(20.0, 0.0)), "global", (320, 240)),
    ("rotation 0.5 deg/frame", MotionParameters(rotation_deg_per_frame=0.5), "flow", None),
]


def sweep_cases():
    out = []
    for mode in MODES:
        out += [(f"scene {v} px/frame", MotionParameters(velocity_px_per_frame=(float(v), 0.0)), mode, None)
                for v in (0, 3, 10, 20, 35, 50)]
        out += [(f"chart {v} px/frame over the scene", chart(v), mode, None) for v in (3, 14, 25, 50)]
        out.append(("rotation 0.5 deg/frame", MotionParameters(rotation_deg_per_frame=0.5), mode, None))
    return out


def setup(size):
    w, h = size
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0,
                                                  exposure_s=EXPOSURE_S))
    bundle = oracle_calibration(desc)
    plan = plan_symmetric_basis(bundle, default_basis(), m=5, output_wavelengths=np.arange(400.0, 701.0, 10.0),
                                max_exposure_s=EXPOSURE_S)
    return desc, bundle, plan, natural_scene(h, w), residual_check(plan, bundle)


def run_case(made, motion, mode, bound, seed):
    desc, bundle, plan, scene, check = made
    moving = replace(desc, motion=motion)
    seq = capture_plan(moving, plan, scene, noise_seed=seed).sequences[0]
    truth = TwinRig(plan.rig_description(moving), scene=scene).motion_truth(seq.timestamps_s)
    t0 = time.perf_counter()
    res = recover_moving(seq.frames, plan.A, dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field,
                         saturation=float(bundle.max_code), model=MODES[mode], residual=check)
    seconds = time.perf_counter() - t0
    rep = evaluate_pixels(res.y, SpectralScene(scene.wavelengths, truth["reflectance"], name="truth"),
                          wavelengths=plan.output_wavelengths)
    decoded = np.all(np.isfinite(res.y), axis=2)
    err, dE = np.asarray(rep.rmse)[decoded], np.asarray(rep.delta_E_2000)[decoded]
    return {"beyond": int(np.sum(err > bound)), "flagged": 1.0 - float(decoded.mean()),
            "rmse_mean": float(err.mean()) if err.size else float("nan"),
            "rmse_p99": float(np.percentile(err, 99)) if err.size else float("nan"),
            "rmse_max": float(err.max()) if err.size else float("nan"),
            "dE_p95": float(np.percentile(dE, 95)) if dE.size else float("nan"), "seconds": seconds}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480", help="W x H of the cases without a size of their own")
    ap.add_argument("--bound", type=float, default=0.1, help="per-pixel RMSE that counts as wrong (default 0.1)")
    ap.add_argument("--sweep", action="store_true", help="every speed of the scene and of a chart, each mode")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    made = {}
    print(f"| case | mode | size | unflagged RMSE > {args.bound:g} | flagged | RMSE unflagged mean / p99 / max "
          f"| dE2000 p95 | s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for label, motion, mode, own in CASES + (sweep_cases() if args.sweep else []):
        where = own or size
        if where not in made:
            made[where] = setup(where)
        r = run_case(made[where], motion, mode, args.bound, args.seed)
        print(f"| {label} | {mode} | {where[0]} x {where[1]} | {r['beyond']} | {100 * r['flagged']:.1f} % | "
              f"{r['rmse_mean']:.4f} / {r['rmse_p99']:.4f} / {r['rmse_max']:.3f} | {r['dE_p95']:.2f} | "
              f"{r['seconds']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
