"""Does ``specgpu recover --sigma`` predict the spread of the recoveries? For each plan, the same scene is captured
on the twin with ``--draws`` fresh noise seeds, each draw recovered and its sigma computed as ``recover --sigma``
does (:func:`specgpu.pipeline.recovery.recover` and :func:`specgpu.pipeline.recovery.uncertainty` on a one-sequence
folder); per
pixel and output, the spread of the recoveries over the draws (standard deviation, ddof 1) is compared with the
noise part of the predicted sigma (its mean variance less the prior's mismatch, which a Wiener plan's sigma holds
and which is the same in every draw). Pixels are split into quintiles of brightness (the mean recovered output)
and each quintile reports ``sqrt(mean spread^2 / mean sigma^2)``: 1 when the noise model holds, above 1 when
sigma understates the noise.

    PYTHONPATH=. python tools/studies/sigma_check.py [--size 320x240] [--draws 10] [--plans \
        hadamard,symmetric,narrowband,wiener]
                                [--bands 7] [--seed 0] [--white-roi] [--ambient] [--profile lab]
                                [--json out.json]

Plans: ``hadamard`` (``plan hadamard --bands N``), ``symmetric`` (m = 5), ``narrowband`` (10 nm steps),
``wiener`` (symmetric with the Wiener decoder on the default prior), ``optimal`` (a 6-frame design; slow). Every
plan gets the rig's noise model as ``specgpu plan`` records it. The rig is the default twin at ``--size`` (or
``--profile``'s, e.g. ``lab``), calibrated by :func:`specgpu.calibration.calibrate`. ``--white-roi`` puts a 0.99
white tile in the chart and recovers with the white's drift correction (the light's fluctuation is then divided
out per sequence); ``--ambient`` gives every plan an ambient frame (``plan --ambient``), subtracted instead of the
dark level.

The light's frame-to-frame fluctuation is common to every pixel of a frame, so the bright quintiles (where it
dominates) see only ``draws x K`` independent draws of it: with 10 draws their ratio scatters by about +-10 %.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu.apps.bench.sizes import parse_sizes  # noqa: E402

PLANS = ("hadamard", "symmetric", "narrowband", "wiener", "optimal")


def make_plans(description, bundle, names, bands: int) -> dict:
    """The named plans with the rig's noise model (as ``specgpu plan`` records it)."""
    from specgpu.pipeline.recovery import default_basis
    from specgpu.planning import NoiseModel, default_prior, make_plan, plan_hadamard, plan_optimal, with_estimator

    def noise_at(t):
        return NoiseModel.from_rig(description, t)

    prior = default_prior() if {"wiener", "optimal"} & set(names) else None
    plans = {}
    for name in names:
        if name == "hadamard":
            plan = plan_hadamard(bundle, bands=bands)
        elif name in ("symmetric", "wiener"):
            plan = make_plan("symmetric", bundle, default_basis(), m=5)
        elif name == "narrowband":
            plan = make_plan("narrowband", bundle, step_nm=10.0)
        elif name == "optimal":
            plans[name] = plan_optimal(bundle, prior, noise_at, frames=6, starts=1, iterations=100,
                                       max_exposure_s=0.1)
            continue
        else:
            raise ValueError(f"unknown plan {name!r}; valid: {', '.join(PLANS)}")
        estimator = "wiener" if name == "wiener" else "projection"
        plans[name] = with_estimator(plan, bundle, estimator, prior=prior if name == "wiener" else None,
                                     noise=noise_at(plan.exposure_s))
    return plans


def spread_over_sigma(description, bundle, plan, scene, *, draws: int = 10, seed: int = 0, white_roi=None,
                      quantiles: int = 5) -> dict:
    """Capture ``plan`` ``draws`` times, recover each draw with its sigma as ``recover --sigma`` does, and return
    ``{"ratio": [per brightness quantile, darkest first: sqrt(mean spread^2 / mean sigma^2)], "all": the same over
    every pixel, "brightness": [the quantiles' mean recovered output]}``."""
    from specgpu.pipeline.capture_folder import SequenceFolder
    from specgpu.pipeline.recovery import recover, uncertainty
    from specgpu.pipeline.twin_capture import capture_plan
    from specgpu.planning.uncertainty import constant_variance

    ys, sigmas = [], []
    for i in range(draws):
        res = capture_plan(description, plan, scene, noise_seed=seed * 1000 + i, calibration=bundle)
        folder = SequenceFolder(Path("<memory>"), res.sequences[0].frames[None], plan, bundle, [], {})
        ys.append(np.asarray(recover(folder, sequence=0, white_roi=white_roi), np.float64))
        sigmas.append(np.asarray(uncertainty(folder, sequence=0, white_roi=white_roi)[0], np.float64))
    y, sig = np.array(ys), np.array(sigmas)
    spread2 = y.var(axis=0, ddof=1)  # (H, W, P)
    # the noise part of the predicted variance: the prior's mismatch (a Wiener plan's) is the same in every draw
    sigma2 = (sig ** 2).mean(axis=0) - constant_variance(plan)
    brightness = y.mean(axis=0).mean(axis=-1)
    ok = np.isfinite(brightness) & np.all(np.isfinite(spread2) & np.isfinite(sigma2), axis=-1)
    if white_roi is not None:  # the white tile itself is the reference, not a measurement
        x, yy, w, h = white_roi
        ok[yy:yy + h, x:x + w] = False
    edges = np.quantile(brightness[ok], np.linspace(0, 1, quantiles + 1))
    ratio, level = [], []
    for q in range(quantiles):
        sel = ok & (brightness >= edges[q]) & (brightness <= edges[q + 1])
        ratio.append(float(np.sqrt(spread2[sel].mean() / sigma2[sel].mean())))
        level.append(float(brightness[sel].mean()))
    return {"ratio": ratio, "all": float(np.sqrt(spread2[ok].mean() / sigma2[ok].mean())), "brightness": level}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="320x240", help="camera ROI, WxH (default 320x240)")
    parser.add_argument("--draws", type=int, default=10, help="noise draws per plan (>= 2)")
    parser.add_argument("--plans", default="hadamard,symmetric,narrowband,wiener", help=f"of {', '.join(PLANS)}")
    parser.add_argument("--bands", type=int, default=7, help="Hadamard bands (default 7)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--white-roi", action="store_true", help="recover with a white tile's drift correction")
    parser.add_argument("--ambient", action="store_true",
                        help="plans with an ambient frame (plan --ambient), subtracted instead of the dark level")
    parser.add_argument("--profile", default=None, help="the twin's [twin] profile (e.g. lab: room light, drift)")
    parser.add_argument("--json", default=None, help="also write the figures as JSON")
    args = parser.parse_args(argv)
    if args.draws < 2:
        parser.error("--draws must be >= 2")
    names = [p.strip() for p in args.plans.split(",") if p.strip()]
    for name in names:
        if name not in PLANS:
            parser.error(f"unknown plan {name!r}; valid: {', '.join(PLANS)}")

    from specgpu.calibration import calibrate
    from specgpu.rig.config import rig_from_dict
    from specgpu.rig.scene import colorchecker_scene, white_tile_roi

    (width, height), = parse_sizes(args.size)
    table = {"camera": {"roi_width": width, "roi_height": height}}
    if args.profile:
        table["twin"] = {"profile": args.profile}
    description = rig_from_dict(table, source="<sigma_check>")
    bundle = calibrate(description, seed=args.seed)
    scene = colorchecker_scene(height, width, white_tile=0.99 if args.white_roi else None)
    roi = white_tile_roi(height, width) if args.white_roi else None
    plans = make_plans(description, bundle, names, args.bands)
    if args.ambient:
        from specgpu.planning.correction import with_ambient_frame

        plans = {name: with_ambient_frame(plan) for name, plan in plans.items()}
    print(f"{width} x {height}{f', {args.profile} profile' if args.profile else ''}, {args.draws} draws per plan, "
          f"spread / sigma by brightness quintile (darkest first){', white ROI' if roi else ''}"
          f"{', ambient frame' if args.ambient else ''}")
    print(f"{'plan':<12} {'K':>3} {'ms':>7} {'q1':>6} {'q2':>6} {'q3':>6} {'q4':>6} {'q5':>6} {'all':>6} {'s':>5}")
    out = {}
    for name, plan in plans.items():
        t = time.perf_counter()
        r = spread_over_sigma(description, bundle, plan, scene, draws=args.draws, seed=args.seed, white_roi=roi)
        out[name] = {"K": plan.K, "exposure_ms": plan.exposure_s * 1e3,
                     "light_rms": plan.params["noise"]["light_rms"], **r}
        print(f"{name:<12} {plan.K:>3} {plan.exposure_s * 1e3:>7.2f} "
              + " ".join(f"{v:>6.3f}" for v in r["ratio"]) + f" {r['all']:>6.3f} {time.perf_counter() - t:>5.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"size": [width, height], "draws": args.draws, "seed": args.seed,
                                               "white_roi": bool(roi), "ambient": args.ambient,
                                               "profile": args.profile, "plans": out},
                                              indent=2) + "\n")


if __name__ == "__main__":
    main()
