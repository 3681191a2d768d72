"""A moving chart under room light with a plan that has an ambient frame: ``recover --motion global`` (the ambient
frame placed on the other frames' steady motion and subtracted in the warped pass) against the same plan on the
still chart, and against what a user got before (the plan refused with ``--motion``; decoded still instead, the
ambient frame subtracted from fixed pixels the chart moves across). One more row isolates the ambient frame's part:
the motion compensated but the ambient frame subtracted from the fixed pixels first, as the still decoding does.

The twin's room light (``[realism] ambient_lux``: CIE FL2 on the object, not shaped by the light's spot) lights the
ColorChecker, which moves ``--speed`` px per frame in x; a 7-band narrowband plan (50 nm steps, its projection
estimator's noise model) with an ambient frame (``plan --ambient``) and its oracle calibration. One sequence per
case and noise draw rendered on the twin (the paper's noise; ``--draws`` seeds), recovered as ``specgpu recover``
does, scored per pixel over the patches' interiors (4 px or more inside their edges at the sequence's reference
time) against the scene there: the RMSE over the bands (mean and 95th percentile), dE2000 under D65 (mean and 95th
percentile) and the share of the interiors decoded (not flagged); each the mean and standard deviation over the
draws. The calibration is the twin's oracle (its own model): the rows are to be read against each other, not as
absolute accuracy.

    PYTHONPATH=. python tools/studies/ambient_motion.py                   # 3, 300 and 1000 lux at 320 x 240, 3 draws
    PYTHONPATH=. python tools/studies/ambient_motion.py --lux 300 --size 640x480

Writes ``results/ambient_motion.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from specgpu.calibration.bundle import oracle_calibration
from specgpu.engine.colorimetry import delta_E
from specgpu.engine.runtime import get_queue
from specgpu.motion.residual import residual_check
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.moving_decode import check_motion_options
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.recovery import recover, to_Lab, to_XYZ
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.correction import with_ambient_frame
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription
from specgpu.rig.motion import MotionParameters
from specgpu.rig.realism import Realism
from specgpu.rig.scene import colorchecker_scene, interpolation_matrix
from specgpu.rig.twin import TwinRig

EXPOSURE_S = 0.0049
#: What ``check_motion_options`` said of such a plan before the ambient frame was warped.
REFUSED = ("--motion global with a plan with an ambient frame: the ambient frame is subtracted from fixed pixels, "
           "which the scene moves across")


def setup(lux: float, size: tuple[int, int]):
    """(rig description, oracle calibration, the plan with its ambient frame, the chart)."""
    w, h = size
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0,
                                                  exposure_s=EXPOSURE_S),
                          realism=Realism(ambient_lux=lux))
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=50.0, max_exposure_s=EXPOSURE_S)
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
    return desc, bundle, with_ambient_frame(plan), colorchecker_scene(h, w)


def capture(desc, bundle, plan, scene, motion, seed: int):
    """One sequence's frames, rendered frame by frame on the twin (frame k exposed at k frame periods), and the scene
    at its reference time on the plan's output wavelengths."""
    rig = TwinRig(plan.rig_description(replace(desc, motion=motion)), scene=scene, seed=seed)
    rig.load_sequence(plan.patterns)
    times = np.arange(plan.K) * rig.frame_period_s
    frames = np.stack([rig.render(k, k, times[k])[0] for k in range(plan.K)])
    truth = rig.motion_truth(times)["reflectance"]
    return frames, truth @ interpolation_matrix(plan.output_wavelengths, scene.wavelengths).T


def interiors(truth, surround: float = 0.03) -> np.ndarray:
    """The patches' pixels 4 px or more inside their edges (the truth flat over 9 x 9 about them)."""
    level = truth.sum(axis=-1)
    flat = ndimage.maximum_filter(level, 9) - ndimage.minimum_filter(level, 9) < 1e-6
    return flat & (np.abs(truth - surround).max(axis=-1) > 1e-3)


def score(cube, truth, plan) -> dict:
    inside = interiors(truth)
    ok = inside & np.isfinite(cube).all(axis=-1)
    rmse = np.sqrt(np.mean((cube[ok] - truth[ok]) ** 2, axis=-1))
    lab, lab_true = to_Lab(to_XYZ(cube, plan), plan), to_Lab(to_XYZ(truth.astype(np.float32), plan), plan)
    dE = np.asarray(delta_E(lab_true, lab))[ok]
    return {"decoded_share": round(float(ok.sum() / inside.sum()), 4),
            "rmse_mean": round(float(rmse.mean()), 5), "rmse_p95": round(float(np.percentile(rmse, 95)), 5),
            "dE2000_mean": round(float(dE.mean()), 3), "dE2000_p95": round(float(np.percentile(dE, 95)), 3)}


def fixed_pixels(folder) -> np.ndarray:
    """The moving sequence compensated with its ambient frame subtracted from the frames' fixed pixels first (the
    still decoding's correction, which the refusal kept from the motion mode): each frame above the ambient frame
    where it is, then the warped pass of the plan's decoder, its checks as recover's."""
    plan, bundle = folder.plan, folder.calibration
    params = {k: v for k, v in plan.params.items() if k != "ambient_frame"}  # the frame as one the decoder skips
    dec = SequenceDecoder(plan, bundle, motion="global")
    corr = dec.corrections
    raw = folder.frames[0]
    rec = recover_moving(corr.sensor(raw), plan.A, dark=corr.level(raw), gain=bundle.flat_field,
                         saturation=float(bundle.max_code), model="translation", device=get_queue(None),
                         residual=residual_check(replace(plan, params=params), bundle))
    return rec.y


def still_refused(plan) -> bool:
    """Whether this version still refuses the plan with ``--motion global`` (it does not: the study measures it)."""
    try:
        check_motion_options("global", plan)
    except ValueError:
        return True
    return False


def summary(draws: list[dict]) -> dict:
    """Each score's mean and standard deviation over the noise draws, beside the draws themselves."""
    keys = [k for k in draws[0] if k != "seconds"]
    out = {k: {"mean": round(float(np.mean([d[k] for d in draws])), 5),
               "std": round(float(np.std([d[k] for d in draws])), 5)} for k in keys}
    return {**out, "seconds": round(float(np.median([d["seconds"] for d in draws])), 1), "draws": draws}


def run(lux: float, size, speed: float, seed: int, draws: int = 3) -> dict:
    desc, bundle, plan, scene = setup(lux, size)
    moving = MotionParameters(velocity_px_per_frame=(speed, 0.0))
    rows = {}
    for label, motion, mode in (("still, --motion none", MotionParameters(), "none"),
                                ("moving, --motion global", moving, "global"),
                                ("moving, global, ambient subtracted on fixed pixels", moving, "fixed"),
                                ("moving, decoded still (--motion none)", moving, "none")):
        scores = []
        for draw in range(draws):
            t0 = time.perf_counter()
            frames, truth = capture(desc, bundle, plan, scene, motion, seed + draw)
            folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
            cube = fixed_pixels(folder) if mode == "fixed" else recover(folder, sequence=0, motion=mode)
            scores.append({**score(cube, truth.astype(np.float32), plan),
                           "seconds": round(time.perf_counter() - t0, 1)})
        rows[label] = summary(scores)
    amb = frames[plan.K - 1].astype(np.float64) - bundle.dark_at(plan.exposure_s)
    brightest = max(float(np.mean(frames[k], dtype=np.float64)) for k in range(plan.K - 1))
    return {"lux": lux, "ambient_frame_median_dn": round(float(np.median(amb)), 2),
            "brightest_frame_mean_dn": round(brightest, 1), "rows": rows,
            "before": {"moving, --motion global": REFUSED}, "refused_now": still_refused(plan)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lux", type=float, action="append", help="room light, lux (repeatable; default 3, 300, 1000)")
    ap.add_argument("--size", default="320x240", help="WxH (default 320x240)")
    ap.add_argument("--speed", type=float, default=3.0, help="the chart's speed, px per frame in x (default 3)")
    ap.add_argument("--seed", type=int, default=5, help="the first draw's seed (default 5)")
    ap.add_argument("--draws", type=int, default=3, help="noise draws per case (default 3)")
    ap.add_argument("--out", default="results/ambient_motion.json")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if args.draws < 1:
        ap.error(f"--draws must be at least 1, got {args.draws}")
    cases = [run(lux, size, args.speed, args.seed, args.draws) for lux in (args.lux or [3.0, 300.0, 1000.0])]
    result = {"size": list(size), "speed_px_per_frame": args.speed, "plan": "narrowband 50 nm + ambient frame",
              "draws": args.draws, "command": "PYTHONPATH=. python tools/studies/ambient_motion.py "
              + " ".join(argv if argv is not None else sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "cases": cases}
    for case in cases:
        print(f"{case['lux']:g} lux (ambient frame median {case['ambient_frame_median_dn']} DN)")
        for label, row in case["rows"].items():
            print(f"  {label:52s} RMSE {row['rmse_mean']['mean']:.4f} +- {row['rmse_mean']['std']:.4f}  dE00 "
                  f"{row['dE2000_mean']['mean']:.2f} +- {row['dE2000_mean']['std']:.2f}  decoded "
                  f"{row['decoded_share']['mean']:.3f}")
        print(f"  {'before: moving, --motion global':52s} refused")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
