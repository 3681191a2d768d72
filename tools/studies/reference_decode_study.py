"""Whether a plan's broadband reference frames are worth reading in the decode: the still scene decoded with the
reference frames' zero decoder columns (the plan's own decoder, what ``specgpu plan --reference-every`` makes) and
with a Wiener decoder re-fitted over every frame, reference frames included.

The twin at the paper's noise, 640 x 480 at 200 fps (exposure 4.9 ms), the natural scene, symmetric-9 with a
reference frame every ``--every`` frames, its decoder the Wiener estimator on the default prior (so both decoders are
made the same way); per-pixel RMSE (400-700 nm at 10 nm) and dE2000 (D65) over the field and within 3 px of edges,
mean +- std over ``--draws`` noise draws, and each decoder's expected RMSE on the prior.

    PYTHONPATH=. python tools/studies/reference_decode_study.py --every 3 --draws 3
"""

from __future__ import annotations

import argparse

import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.engine.linear_map import apply_linear
from specgpu.pipeline.moving_scores import edge_band, motion_scores
from specgpu.pipeline.recovery import default_basis
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.estimators import NoiseModel, with_estimator
from specgpu.planning.priors import default_prior
from specgpu.planning.reference_frames import with_reference_frames
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription, natural_scene

EXPOSURE_S = 0.0049


def fmt(values, digits):
    v = np.asarray(values, float)
    return f"{v.mean():.{digits}f}" + (f"+-{v.std():.{digits}f}" if v.size > 1 else "")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=int, default=3, help="pattern frames between two reference frames")
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--small", action="store_true", help="320 x 240 instead of 640 x 480")
    args = ap.parse_args(argv)
    w, h = (320, 240) if args.small else (640, 480)
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0,
                                                  exposure_s=EXPOSURE_S))
    bundle = oracle_calibration(desc)
    prior = default_prior()
    plan = make_plan("symmetric", bundle, default_basis(), m=5, output_wavelengths=np.arange(400.0, 701.0, 10.0),
                     max_exposure_s=EXPOSURE_S)
    noise = NoiseModel.from_rig(desc, plan.exposure_s)
    own = with_reference_frames(with_estimator(plan, bundle, "wiener", prior=prior, noise=noise), bundle, args.every)
    every = with_estimator(own, bundle, "wiener", prior=prior, noise=noise)
    decoders = {"zero columns": own, "all frames": every}
    scene = natural_scene(h, w)
    band = edge_band(scene.reflectance, 0.08)
    valid = np.ones((h, w), bool)
    dark = bundle.dark_at(own.exposure_s)
    rows = {name: [] for name in decoders}
    for d in range(args.draws):
        frames = capture_plan(desc, own, scene, noise_seed=1000 + 31 * d).sequences[0].frames
        for name, p in decoders.items():
            y = apply_linear(frames, p.A, dark, bundle.flat_field)
            rows[name].append(motion_scores(y, scene, own.output_wavelengths, valid, band)[0])
    print(f"twin: paper's noise, {w} x {h}, 200 fps; symmetric-9 + a reference frame every {args.every} "
          f"(K = {own.K}); Wiener decoders; {args.draws} draws")
    print(f"  {'decoder':<14} {'expected':>9} {'RMSE field':>15} {'RMSE edge':>15} {'dE00 field':>12} "
          f"{'dE00 edge':>12}")
    for name, p in decoders.items():
        r = rows[name]
        print(f"  {name:<14} {p.params['expected']['rmse']:9.4f} {fmt([x['rmse_field'] for x in r], 4):>15} "
              f"{fmt([x['rmse_edge'] for x in r], 4):>15} {fmt([x['dE_field'] for x in r], 2):>12} "
              f"{fmt([x['dE_edge'] for x in r], 2):>12}")


if __name__ == "__main__":
    main()
