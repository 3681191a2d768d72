"""Is the sigma of ``--denoise`` calibrated, still and with ``--motion``? A 7-band narrowband plan (with the rig's
noise model) captures a scene on the 320 x 240 twin ``--draws`` times with fresh noise, still or moving
``--velocity`` px per frame (the light's frame-to-frame fluctuation off: it is one number per frame, common to every
pixel, so a few draws hold a few samples of it and no pixel statistic could check it). Each draw is decoded by the
one decoder (``SequenceDecoder``: what ``recover``, ``stream`` and ``batch`` run) with and without the guided
filter, with its ``sigma`` and ``dE_sigma`` maps, and the RMS z-score of each band is reported:

- ``noise``: (estimate - the draws' mean estimate) * sqrt(N / (N - 1)) / sigma: the noise the sigma states;
- ``truth``: (estimate - the scene's truth at the sequence's reference time, at the band centres) / sigma: with the
  estimator's own error besides the noise (the bands' width, the filter's smoothing across the guide's edges);

and the same for dE2000 against ``dE_sigma`` (RMS dE over RMS dE_sigma), over every decoded pixel (``all``) and over
the interiors of flat patches (``flat``: pixels whose true reflectance varies less than 0.01 in every band within
the filter's reach and the motion's). 1 is calibrated.

    PYTHONPATH=. python tools/studies/sigma_composed.py [--draws 4] [--velocity 3,0.5] [--scenes natural,chart]
                                                        [--json results/sigma_composed.json]

Prints the table; writes the figures as JSON (default ``results/sigma_composed.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

DENOISE = (2, 1e-4)
SCENES = ("natural", "chart")


def setup(width: int = 320, height: int = 240):
    """The twin (light fluctuation off), its oracle calibration and the 7-band plan with the rig's noise model."""
    from specgpu.calibration.bundle import oracle_calibration
    from specgpu.planning import NoiseModel, make_plan, with_estimator
    from specgpu.rig import CameraParameters, RigDescription

    desc = RigDescription(camera=CameraParameters(roi_width=width, roi_height=height, frame_rate_hz=200.0,
                                                  exposure_s=0.0049))
    desc = replace(desc, light=replace(desc.light, fluctuation_rms=0.0))
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=50.0, max_exposure_s=0.0049)
    return desc, bundle, with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))


def flat_interiors(truth: np.ndarray, reach: int, tolerance: float = 0.01) -> np.ndarray:
    """(H, W) bool: pixels whose true reflectance varies less than ``tolerance`` in every band within ``reach``."""
    from scipy.ndimage import maximum_filter, minimum_filter

    size = (2 * reach + 1, 2 * reach + 1, 1)
    return np.all(maximum_filter(truth, size=size) - minimum_filter(truth, size=size) < tolerance, axis=-1)


def rms(values) -> float | None:
    """The RMS of ``values``, None when there are none (a scene with no flat interior)."""
    v = np.asarray(values, np.float64)
    return float(np.sqrt(np.mean(v ** 2))) if v.size else None


def ratio(a, b) -> float | None:
    return None if a is None or b is None else a / b


def study(desc, bundle, plan, scene, *, draws: int, motion: str, velocity, seed: int = 0) -> dict:
    """The z-scores of one scene (see the module notes), raw and denoised."""
    from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E
    from specgpu.pipeline.recovery import to_XYZ
    from specgpu.pipeline.sequence_decoder import SequenceDecoder
    from specgpu.pipeline.twin_capture import capture_plan
    from specgpu.rig.motion import MotionParameters
    from specgpu.rig.twin import TwinRig

    rig_desc = desc if motion == "none" else replace(desc, motion=MotionParameters(velocity_px_per_frame=velocity))
    shots = [capture_plan(rig_desc, plan, scene, noise_seed=seed * 1000 + i, calibration=bundle).sequences[0]
             for i in range(draws)]
    rig = TwinRig(plan.rig_description(rig_desc), scene=scene)
    rig.load_sequence(plan.patterns)
    truth_full = rig.motion_truth(shots[0].timestamps_s)["reflectance"]
    wl = np.asarray(plan.output_wavelengths, np.float64)
    truth = np.stack([np.interp(wl, scene.wavelengths, px) for px in truth_full.reshape(-1, truth_full.shape[-1])]
                     ).reshape(truth_full.shape[:2] + (wl.size,))
    reach = 2 * DENOISE[0] + int(np.ceil(np.hypot(*velocity))) if motion != "none" else 2 * DENOISE[0]
    flat = flat_interiors(truth, reach)
    white = plan.white_XYZ("D65")
    lab_truth = XYZ_to_Lab(to_XYZ(truth.astype(np.float32), plan), illuminant=white)
    out = {"flat_share": float(flat.mean())}
    for name, denoise in (("raw", None), ("denoised", DENOISE)):
        dec = SequenceDecoder(plan, bundle, ("cube", "XYZ", "Lab", "sigma", "dE_sigma"), motion=motion,
                              denoise=denoise)
        maps = [dec.maps(shot.frames) for shot in shots]
        cube = np.stack([m["cube"] for m in maps]).astype(np.float64)
        sigma = np.stack([m["sigma"][..., :-1] for m in maps]).astype(np.float64)
        ok = np.all(np.isfinite(cube[..., 0]) & np.isfinite(sigma[..., 0]), axis=0)
        mean = cube.mean(axis=0)
        z_noise = (cube - mean) * np.sqrt(draws / (draws - 1)) / sigma
        z_truth = (cube - truth) / sigma
        lab_mean = XYZ_to_Lab(to_XYZ(mean.astype(np.float32), plan), illuminant=white)
        des = np.stack([m["dE_sigma"] for m in maps]).astype(np.float64)
        dE_noise = np.stack([delta_E(m["Lab"], lab_mean) for m in maps]).astype(np.float64) * np.sqrt(
            draws / (draws - 1))
        dE_truth = np.stack([delta_E(m["Lab"], lab_truth) for m in maps]).astype(np.float64)
        row = {}
        for where, sel in (("all", ok), ("flat", ok & flat)):
            row[where] = {"pixels": int(sel.sum()),
                          "noise": [rms(z_noise[:, sel, b]) for b in range(cube.shape[-1])],
                          "truth": [rms(z_truth[:, sel, b]) for b in range(cube.shape[-1])],
                          "dE_noise": ratio(rms(dE_noise[:, sel]), rms(des[:, sel])),
                          "dE_truth": ratio(rms(dE_truth[:, sel]), rms(des[:, sel]))}
        out[name] = row
    return out


def _f(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def table(results: dict) -> str:
    lines = [f"{'case':<30}{'pixels':>8}  {'z noise per band':<44}{'z truth per band':<44}{'dE n':>6}{'dE t':>6}"]
    for case, res in results.items():
        for name in ("raw", "denoised"):
            for where in ("all", "flat"):
                r = res[name][where]
                lines.append(f"{case + ' ' + name + ' ' + where:<30}{r['pixels']:>8}  "
                             f"{' '.join(_f(v) for v in r['noise']):<44}"
                             f"{' '.join(_f(v) for v in r['truth']):<44}"
                             f"{_f(r['dE_noise']):>6}{_f(r['dE_truth']):>6}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=4, help="noise draws per case (>= 2)")
    parser.add_argument("--velocity", default="3,0.5", help="the scene's motion, px per frame: x,y")
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"of {', '.join(SCENES)}")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default="results/sigma_composed.json", help="where the figures go")
    args = parser.parse_args(argv)
    if args.draws < 2:
        parser.error("--draws must be >= 2")
    try:
        velocity = tuple(float(v) for v in args.velocity.split(","))
        assert len(velocity) == 2
    except (ValueError, AssertionError):
        parser.error(f"--velocity must be x,y in px per frame, got {args.velocity!r}")
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    for s in scenes:
        if s not in SCENES:
            parser.error(f"unknown scene {s!r}; valid: {', '.join(SCENES)}")

    from specgpu.rig import natural_scene
    from specgpu.rig.scene import colorchecker_scene

    t0 = time.perf_counter()
    desc, bundle, plan = setup()
    h, w = desc.camera.roi_height, desc.camera.roi_width
    results = {}
    for name in scenes:
        scene = natural_scene(h, w) if name == "natural" else colorchecker_scene(h, w)
        for motion in ("none", "global"):
            case = f"{name} {'still' if motion == 'none' else 'moving'}"
            results[case] = study(desc, bundle, plan, scene, draws=args.draws, motion=motion, velocity=velocity,
                                  seed=args.seed)
            print(f"{case}: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    print(table(results))
    record = {"command": "PYTHONPATH=. python tools/studies/sigma_composed.py " + " ".join(argv or sys.argv[1:]),
              "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "wall_s": round(time.perf_counter() - t0, 1), "draws": args.draws, "velocity_px_per_frame": velocity,
              "plan": f"{plan.method}, {plan.K} frames", "denoise": {"radius": DENOISE[0], "eps": DENOISE[1]},
              "size": [w, h], "result": results}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
