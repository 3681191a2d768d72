"""Estimator study: Wiener decoders and optimal illuminants beside the paper's methods, on a held-out chart.

On the twin with the paper's noise (default rig: 44.2 dB camera, 10-bit, the light's frame-to-frame fluctuation),
calibrate, hold out colour-science's "CIE 1995 TCS" (14 Munsell chips, in neither the training prior nor the
ColorChecker) as the evaluation chart, build the training prior and basis from every other set colour-science ships
(minus any spectrum within 0.01 RMS of a held-out chip), plan the paper's methods and wiener-6/9, optimal-9/6/3,
capture each ``--runs`` times with fresh noise, and print per-pixel and per-patch means (mean +- std over the runs),
the expected RMSE recorded with each plan beside the measured RMS error (and for Wiener decoders the expected RMSE
on an unseen chart, by leaving one training set out at a time: ``cv``), the standard deviation of the
standardised errors (error / the per-pixel sigma of ``specgpu recover --sigma``) and the RMS dE2000 over the RMS
predicted dE2000 sigma (``specgpu recover --delta-e-sigma``, first run).

``--profile lab`` runs the same on the twin's lab profile (``[twin] profile = "lab"``: every imperfection of a
real bench, the lamp drifting for 30 min between calibration and capture) with the corrections ``specgpu demo``
applies there: an ambient frame per sequence and a reference white tile above the chart rescaling each decoder.

    PYTHONPATH=. python tools/studies/estimator_study.py [--small] [--profile ideal|lab] [--runs N] [--seed N]
        [--methods a,b] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from estimator_rows import format_study, hadamard_gain, prior_size_rows, study_rows  # noqa: E402

import specgpu.planning as E  # noqa: E402
from specgpu.calibration import calibrate  # noqa: E402
from specgpu.planning.estimator_plans import STUDY_METHODS, study_plans, training_sets  # noqa: E402
from specgpu.planning.priors import HELD_OUT_CHART, held_out_basis, held_out_spectra, subspace_bound, training_spectra
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import RigDescription, rig_from_dict  # noqa: E402
from specgpu.rig.scene import patch_scene, white_tile_roi  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="320 x 240 instead of 640 x 480")
    ap.add_argument("--runs", type=int, default=3, help="captures per method with fresh noise (default 3)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", choices=("ideal", "lab"), default="ideal",
                    help="the twin's profile (default ideal: the paper's rig with no imperfection)")
    ap.add_argument("--methods", default=None, help=f"comma-separated subset of {', '.join(STUDY_METHODS)}")
    ap.add_argument("--prior-sizes", default=None,
                    help="also: how the held-out error of optimal-9 depends on the prior's size, e.g. 10,30,100,300")
    ap.add_argument("--hadamard", action="store_true",
                    help="also: Hadamard-31's measured SNR gain over narrowband-31 at equal exposure (2 ms), on the "
                         "paper's camera and on one with 300 e- read noise")
    ap.add_argument("--bound", action="store_true",
                    help="also: the noise-free linear bound with K = 3, 6, 9 measurements learnt from the prior, on "
                         "the held-out chart (projection onto the prior's top K, uncentred and centred)")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    methods = None if args.methods is None else [m.strip() for m in args.methods.split(",")]
    for m in methods or ():
        if m not in STUDY_METHODS:
            ap.error(f"unknown method {m!r}; valid: {', '.join(STUDY_METHODS)}")
    t0 = time.perf_counter()
    cam = CameraParameters(roi_width=320, roi_height=240) if args.small else CameraParameters()
    if args.profile == "lab":
        desc = rig_from_dict({"twin": {"profile": "lab"}, "camera": {"roi_width": cam.roi_width,
                                                                      "roi_height": cam.roi_height}},
                             source="<lab profile>")
        desc = replace(desc, seed=args.seed)
    else:
        desc = RigDescription(camera=cam, seed=args.seed)
    bundle = calibrate(desc, seed=args.seed)
    prior = E.default_prior(HELD_OUT_CHART)
    basis = held_out_basis(HELD_OUT_CHART)
    names, wl, spectra = held_out_spectra(HELD_OUT_CHART)
    roi = None
    if args.profile == "lab":  # the twin's white: its certificate's 0.99 off by the bench's white_error
        roi = white_tile_roi(cam.roi_height, cam.roi_width)
        scene = patch_scene(names, wl, spectra, cam.roi_height, cam.roi_width, name=HELD_OUT_CHART,
                              white_tile=0.99 * (1.0 + desc.realism.white_error))
    else:
        scene = patch_scene(names, wl, spectra, cam.roi_height, cam.roi_width, name=HELD_OUT_CHART)
    print(f"rig: paper defaults, {args.profile} profile"
          f"{' (corrections: ambient frame, white ROI ' + ','.join(map(str, roi)) + ')' if roi else ''}, "
          f"{cam.roi_width} x {cam.roi_height}, seed {args.seed}; held-out chart: "
          f"{HELD_OUT_CHART} ({len(names)} patches); prior: {prior.source}; {args.runs} runs per method")
    plans = study_plans(desc, bundle, prior, basis, methods=methods,
                          sets=training_sets(HELD_OUT_CHART, prior.wavelengths))
    rows = study_rows(desc, bundle, scene, plans, runs=args.runs, seed=args.seed, white_roi=roi)
    print(format_study(rows))
    sizes = []
    if args.prior_sizes:
        sizes = prior_size_rows(desc, bundle, [int(s) for s in args.prior_sizes.split(",")], seed=args.seed)
        print("\noptimal-9 against the prior's size (random subsets; expected on the prior, exact on the chart):")
        print(f"{'spectra':>8} {'expected RMSE':>14} {'chart RMSE':>11}")
        for r in sizes:
            print(f"{r['n']:>8} {r['expected_rmse']:>14.4f} {r['chart_rmse']:>11.4f}")
    bounds = []
    if args.bound:
        train = training_spectra(HELD_OUT_CHART, prior.wavelengths)
        _, _, test = held_out_spectra(HELD_OUT_CHART, prior.wavelengths)
        print(f"\nnoise-free linear bound on the held-out chart, K measurements learnt from the prior ({len(train)} "
              f"spectra; the chart's own top K beside it, for scale):")
        for K in (3, 6, 9):
            b = {"K": K, "uncentred": subspace_bound(train, test, K),
                 "centred": subspace_bound(train, test, K, centred=True), "own": subspace_bound(test, test, K)}
            bounds.append(b)
            print(f"  K {K}: RMSE {b['uncentred']:.4f} (affine {b['centred']:.4f}); the chart's own subspace "
                  f"{b['own']:.4f}")
    gains = []
    if args.hadamard:
        print("\nHadamard-31 against narrowband-31, equal exposure 2 ms, grey 0.5 (noise: pixel std, mean over bands):")
        for read in (desc.camera.read_noise_e, 300.0):
            d = replace(desc, camera=replace(desc.camera, read_noise_e=read))
            g = hadamard_gain(d, bands=31, exposure_s=0.002, seed=args.seed)
            gains.append(g)
            print(f"  read noise {read:5.0f} e-: narrowband {g['narrowband_noise']:.4f}, hadamard "
                  f"{g['hadamard_noise']:.4f}: gain {g['gain']:.2f} (read-noise-limited theory {g['theory']:.2f})")
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.json:
        Path(args.json).write_text(json.dumps({"chart": HELD_OUT_CHART, "profile": args.profile,
                                               "prior": prior.source, "size": [cam.roi_width, cam.roi_height],
                                               "rows": rows, "prior_sizes": sizes, "hadamard": gains,
                                               "bounds": bounds}, indent=1))


if __name__ == "__main__":
    main()
