"""Reflectance recovery of moving scenes on the twin: still, moving uncompensated, and motion-compensated.

The twin at the paper's noise (the default camera and light, ideal profile), 640 x 480 at 200 fps (exposure 4.9 ms),
the natural scene (a photograph given measured spectra); the calibration is the twin's own (oracle), so the table
isolates motion. For every motion case and plan, one sequence is captured through the capture path with the
scene still and with the scene moving (same noise seed), and recovered three ways:

- still: the still sequence, decoded as it is, against the scene;
- moving: the moving sequence decoded as it is (what specgpu did before motion compensation), against the scene
  as it was at the sequence's reference time (the mean of its frames' mid-exposure times);
- compensated: ``recover_moving`` (:func:`specgpu.pipeline.moving_scores.compare_motion`; a translation per frame
estimated from the frames themselves by phase
  correlation, then frame k sampled at x + d_k in the decoding pass), against the same truth.

Per-pixel RMSE (reflectance, 400-700 nm at 10 nm) and dE2000 (D65) are averaged over the field and over the pixels
within 3 px of an edge of the scene (a step of the true reflectance of more than ``--edge`` RMS between neighbours),
each over the pixels every recovery has (the compensated one leaves NaN where some frame saw outside the field:
and where its frames disagree after compensation, an object moving on its own: that share is the ``flagged``
column); with a moving object the scores leave out a 3 px band about its edges. Mean +- std over ``--draws``
noise draws. ``ratio`` is compensated over still. The ``-affine`` cases compensate an affine map per frame, the
``-flow`` ones the dense flow (``--motion flow``: the global decoding, then the tiles' flow where it agrees better).

    PYTHONPATH=. python tools/studies/motion_study.py --cases t1,t3,t10,vib,rot,rot-affine,object  # ~6 min
    PYTHONPATH=. python tools/studies/motion_study.py --draws 3 --cases t3-flow,rot-flow,object-flow \
        --plans symmetric-9,optimal-9
    PYTHONPATH=. python tools/studies/motion_study.py --small --draws 1 --cases t3

A plan named ``NAME+refM`` is NAME with a broadband reference frame before its first frame and after every M
(``specgpu plan --reference-every M``); its motion is estimated from those frames alone:

    PYTHONPATH=. python tools/studies/motion_study.py --draws 3 --cases t1,t3,t10,vib \
        --plans symmetric-9,symmetric-9+ref3,symmetric-9+ref9   # ~2.5 min
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.moving_scores import compare_motion
from specgpu.pipeline.recovery import default_basis
from specgpu.planning.design import plan_optimal
from specgpu.planning.estimators import NoiseModel
from specgpu.planning.priors import default_prior
from specgpu.planning.reference_frames import with_reference_frames
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters

EXPOSURE_S = 0.0049  # 200 fps less the light's 80 us switch time (and a margin)

CASES = {
    "t1": ("translation 1 px/frame", MotionParameters(velocity_px_per_frame=(0.8, 0.6))),
    "t3": ("translation 3 px/frame", MotionParameters(velocity_px_per_frame=(2.4, 1.8))),
    "t3-flow": ("translation 3 px/frame, flow", MotionParameters(velocity_px_per_frame=(2.4, 1.8))),
    "t10": ("translation 10 px/frame", MotionParameters(velocity_px_per_frame=(8.0, 6.0))),
    "vib": ("vibration 0.5 px RMS, 20 Hz", MotionParameters(vibration_rms_px=0.5, vibration_hz=20.0, seed=1)),
    "rot": ("rotation 0.2 deg/frame", MotionParameters(rotation_deg_per_frame=0.2)),
    "rot-affine": ("rotation 0.2 deg/frame, affine", MotionParameters(rotation_deg_per_frame=0.2)),
    "rot-flow": ("rotation 0.2 deg/frame, flow", MotionParameters(rotation_deg_per_frame=0.2)),
    "object": ("chart 3 px/frame over the scene", MotionParameters(object="colorchecker",
                                                                   object_velocity_px_per_frame=(3.0, 0.0))),
    "object-affine": ("chart 3 px/frame over the scene, affine",
                      MotionParameters(object="colorchecker", object_velocity_px_per_frame=(3.0, 0.0))),
    "object-flow": ("chart 3 px/frame over the scene, flow",
                    MotionParameters(object="colorchecker", object_velocity_px_per_frame=(3.0, 0.0))),
}
#: narrowband-31 (155 ms a sequence) only on the case it is measured for (a slow plan: one case keeps the study short)
NARROWBAND_CASES = ("t3",)


def make_plans(desc, bundle, names):
    """The plans by name; ``NAME+refM`` is NAME with a broadband reference frame before its first frame and after
    every M (``specgpu plan ... --reference-every M``): the motion is then estimated from those alone."""
    ow = np.arange(400.0, 701.0, 10.0)
    plans = {}
    for full in names:
        name, _, ref = full.partition("+ref")
        if ref:
            plans[full] = with_reference_frames(make_plans(desc, bundle, [name])[name], bundle, int(ref))
            continue
        if name == "symmetric-9":
            plans[name] = make_plan("symmetric", bundle, default_basis(), m=5, output_wavelengths=ow,
                                    max_exposure_s=EXPOSURE_S)
        elif name == "optimal-9":
            plans[name] = plan_optimal(bundle, default_prior(), lambda t: NoiseModel.from_rig(desc, t), frames=9,
                                       output_wavelengths=ow, max_exposure_s=EXPOSURE_S, starts=2, iterations=150)
        elif name == "narrowband-31":
            plans[name] = make_plan("narrowband", bundle, step_nm=10.0, max_exposure_s=EXPOSURE_S)
        else:
            raise SystemExit(f"unknown plan {name}")
    return plans


def twin_setup(small: bool, plan_names: str):
    """(description, oracle calibration, plans by name, natural scene) of the study: 640 x 480 (320 x 240 if
    ``small``) at 200 fps; ``plan_names`` comma-separated (:func:`make_plans`)."""
    w, h = (320, 240) if small else (640, 480)
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0,
                                                  exposure_s=EXPOSURE_S))
    bundle = oracle_calibration(desc)
    return desc, bundle, make_plans(desc, bundle, plan_names.split(",")), natural_scene(h, w)


def fmt(values, digits):
    v = np.asarray(values, float)
    return f"{v.mean():.{digits}f}" + (f"+-{v.std():.{digits}f}" if v.size > 1 else "")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="320 x 240 instead of 640 x 480")
    ap.add_argument("--draws", type=int, default=3, help="noise draws per row (default 3)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--plans", default="symmetric-9,optimal-9,narrowband-31")
    ap.add_argument("--edge", type=float, default=0.08, help="RMS reflectance step that counts as an edge")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    desc, bundle, plans, scene = twin_setup(args.small, args.plans)
    w, h = desc.camera.roi_width, desc.camera.roi_height
    print(f"twin: paper's noise, {w} x {h}, 200 fps; scene {scene.name}; oracle calibration; "
          f"{args.draws} draws; edge band: within 3 px of an RMS step > {args.edge}")
    for name, plan in plans.items():
        print(f"  {name}: K = {plan.K}, exposure {plan.exposure_s * 1e3:.2f} ms, sequence "
              f"{plan.K / plan.rig_description(desc).camera.frame_rate_hz * 1e3:.0f} ms")
    rows = []
    head = (f"{'motion':<32} {'plan':<14} {'':<12} {'RMSE field':>14} {'RMSE edge':>14} {'dE00 field':>12} "
            f"{'dE00 edge':>12}")
    print("\n" + head)
    for case in args.cases.split(","):
        label, motion = CASES[case]
        for pname, plan in plans.items():
            if pname == "narrowband-31" and case not in NARROWBAND_CASES:
                continue
            model = case.rpartition("-")[2] if case.endswith(("-affine", "-flow")) else "translation"
            runs = [compare_motion(desc, bundle, plan, scene, motion, 1000 + 31 * d, edge=args.edge, model=model)
                    for d in range(args.draws)]
            for run in runs:
                run.pop("maps")  # the error maps: for the demo's figures, not the table
            row = {"case": case, "motion": label, "plan": pname, "runs": runs}
            rows.append(row)
            for kind in ("still", "moving", "compensated"):
                r = [run[kind] for run in runs]
                print(f"{label if kind == 'still' else '':<32} {pname if kind == 'still' else '':<14} {kind:<12} "
                      f"{fmt([x['rmse_field'] for x in r], 4):>14} {fmt([x['rmse_edge'] for x in r], 4):>14} "
                      f"{fmt([x['dE_field'] for x in r], 2):>12} {fmt([x['dE_edge'] for x in r], 2):>12}")
            ratio = lambda key: [run["compensated"][key] / run["still"][key] for run in runs]  # noqa: E731
            print(f"{'':<32} {'':<14} {'ratio':<12} {fmt(ratio('rmse_field'), 2):>14} {fmt(ratio('rmse_edge'), 2):>14} "
                  f"{fmt(ratio('dE_field'), 2):>12} {fmt(ratio('dE_edge'), 2):>12}   flagged "
                  f"{fmt([100 * run['flagged'] for run in runs], 1)} %, shift error "
                  f"{'99th percentile' if model == 'flow' else '<='} "
                  f"{max(run['shift_error_px'] for run in runs):.3f} px, edge band "
                  f"{100 * np.mean([run['edge_share'] for run in runs]):.0f} % of the field, compensation "
                  f"{np.median([run['seconds'] for run in runs]):.2f} s")
            if runs[0]["object_flagged"] is not None:
                print(f"{'':<32} {'':<14} {'':<12} flagged: {100 * runs[0]['object_flagged'][0]:.1f} % of the object, "
                      f"{100 * runs[0]['object_flagged'][1]:.1f} % of the rest of the field (first draw)")
    print(f"\n({time.perf_counter() - t_start:.0f} s)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
