"""Default-path study: what a first-time user gets on a realistic (lab-profile) bench from the command line.

    PYTHONPATH=. python tools/studies/bench_default_study.py [--small] [--draws 3] [--methods narrowband,symmetric]
        [--sequences 1] [--seed 0] [--json OUT.json]

Every step is the ``specgpu`` command a user types, run in-process: a rig TOML with ``[twin] profile = "lab"``,
``specgpu calibrate``, ``specgpu plan METHOD --calib C --rig R`` with default options and again with ``--ambient``
and ``--no-ambient``, ``specgpu capture`` on a chart of measured spectra the project does not ship
(colour-science's 99 CIE 2017 colour evaluation samples, 10 x 10 patches on a dark surround, a white strip of
reflectance 0.95 above them), ``specgpu recover --white-roi`` on the strip with ``--white-reflectance 0.95`` (and
once without the white ROI). The symmetric plan's basis is trained without those 99 samples (and without anything
within 0.01 RMS of one). Per plan variant it prints, mean +- std over the noise draws (``capture --seed``):
per-pixel RMSE over the whole frame (``specgpu evaluate``'s figure), over the frame less the pixels within 3 of an
edge (where the lab's lens blur and lateral colour mix neighbours: a third of this chart's frame) and over the
patches' pixels; per-patch RMSE; the mean bias (recovered - true) per true-reflectance level over the patches'
pixels and bands, and at 400 nm.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from measured_chart import LEVEL_EDGES, chart_errors, measured_chart_with_white  # noqa: E402

from specgpu.apps.demo_measure import mean_std  # noqa: E402
from specgpu.calibration.bundle import load_calibration  # noqa: E402
from specgpu.io.npz import read_cube_npz  # noqa: E402
from specgpu.planning import load_plan  # noqa: E402
from specgpu.planning.basis import save_basis  # noqa: E402
from specgpu.rig.config import load_rig  # noqa: E402
from specgpu.rig.scene import write_scene  # noqa: E402

#: plan options per variant; None: recover without the white ROI
VARIANTS = {"default": [], "--ambient": ["--ambient"], "--no-ambient": ["--no-ambient"], "default, no ROI": None}

#: Reflectance of the chart's white strip, given to ``recover --white-reflectance`` (a white of known value).
STRIP = 0.95


def run(*args):
    """``specgpu ARGS`` in-process; raises with the command's output when it fails."""
    from click.testing import CliRunner

    from specgpu.apps.cli import main

    res = CliRunner().invoke(main, [str(a) for a in args])
    if res.exit_code != 0:
        raise SystemExit(f"specgpu {' '.join(map(str, args))} failed:\n{res.output}")
    return res.output


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="320 x 240 instead of 640 x 480")
    ap.add_argument("--draws", type=int, default=3, help="noise draws (capture seeds)")
    ap.add_argument("--methods", default="narrowband,symmetric")
    ap.add_argument("--sequences", type=int, default=1, help="sequences per capture")
    ap.add_argument("--seed", type=int, default=0, help="calibration and camera seed")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-default-") as tmp:
        d = Path(tmp)
        roi = "[camera]\nroi_width = 320\nroi_height = 240\n" if args.small else ""
        (d / "rig.toml").write_text(f'[twin]\nprofile = "lab"\nseed = {args.seed}\n{roi}')
        h, w = (240, 320) if args.small else (480, 640)
        desc = load_rig(d / "rig.toml")
        scene, white_roi, basis = measured_chart_with_white(desc, h, w, basis=True, white=STRIP)
        write_scene(d / "chart.npz", scene)
        save_basis(d / "basis.npz", basis)
        run("calibrate", "--rig", d / "rig.toml", "--out", d / "calib.npz", "--seed", args.seed)
        b = load_calibration(d / "calib.npz")
        r = b.reports
        print(f"lab bench {w} x {h}; calibration: all-off level on the white "
              f"{[round(v, 2) for v in r['dark_levels_dn']]} DN at "
              f"{[round(t * 1e3, 2) for t in r['dark_exposures_s']]} ms; camera dark (capped) "
              f"{[round(v, 2) for v in r.get('camera_dark_levels_dn', [])]} DN; light with every mirror off "
              f"{r.get('mirrors_off_dn_per_s', float('nan')):.1f} DN/s per unit reflectance "
              f"({r.get('mirrors_off_fraction', float('nan')):.1%} of the weakest band's signal)")
        print(f"chart: {len(scene.masks)} CIE 2017 CES patches, white strip ROI {white_roi}; {args.draws} noise "
              f"draws, {args.sequences} sequence(s) each (mean +- std)")
        results = {}
        for method in methods:
            for label, extra in VARIANTS.items():
                use_roi = extra is not None
                tag = label.replace(",", "").replace(" ", "-").strip("-")
                plan = d / f"{method}-{tag}.npz"
                more = ["--basis", d / "basis.npz"] if method in ("biased", "symmetric") else []
                run("plan", method, "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out", plan, *more,
                    *(extra or []))
                p = load_plan(plan)
                rows = []
                for draw in range(args.draws):
                    seq = d / f"seq-{method}-{tag}-{draw}"
                    run("capture", "--rig", d / "rig.toml", "--plan", plan, "--calib", d / "calib.npz", "--scene",
                        d / "chart.npz", "--out", seq, "--sequences", args.sequences, "--seed", 1000 + draw)
                    cube = seq.with_suffix(".npz")
                    roi = (["--white-roi", ",".join(map(str, white_roi)), "--white-reflectance", STRIP]
                           if use_roi else [])
                    said = run("recover", seq, "--out", cube, *roi)
                    y, wl, _ = read_cube_npz(cube)
                    rows.append(chart_errors(y, wl, scene) | {"warned": "dark level not trusted" in said})
                results[(method, label)] = {"K": p.K, "exposure_ms": p.exposure_s * 1e3, "draws": rows}
        print(f"{'plan':<12}{'options':<16}{'K':>3}{'ms':>6}{'px RMSE frame':>18}{'px off edges':>18}"
              f"{'px RMSE patches':>18}{'patch RMSE':>18}{'bias @400nm':>18}  recover warned")
        for (method, label), res in results.items():
            cells = []
            for key in ("px_rmse", "px_rmse_off_edges", "px_rmse_patches", "patch_rmse", "bias_400nm"):
                m, s = mean_std([r[key] for r in res["draws"]])
                cells.append(f"{m:9.4f} +- {s:.4f}")
            warned = sum(r["warned"] for r in res["draws"])
            print(f"{method:<12}{label:<16}{res['K']:>3}{res['exposure_ms']:6.1f}" + "".join(f"{c:>18}" for c in cells)
                  + f"  {warned}/{len(res['draws'])}")
        print("bias (recovered - true) per true-reflectance level, patches' pixels and bands:")
        bins = [f"{a:.2f}-{b:.2f}" for a, b in zip(LEVEL_EDGES[:-1], LEVEL_EDGES[1:])]
        print(f"{'plan':<12}{'options':<16}" + "".join(f"{x:>18}" for x in bins))
        for (method, label), res in results.items():
            per = np.array([r["bias_by_level"] for r in res["draws"]])
            cells = []
            for j in range(per.shape[1]):
                m, s = mean_std(per[:, j])
                cells.append("n/a" if not np.isfinite(m) else f"{m:+.4f} +- {s:.4f}")
            print(f"{method:<12}{label:<16}" + "".join(f"{c:>18}" for c in cells))
        print(f"({time.perf_counter() - t0:.0f} s)")
        if args.json:
            Path(args.json).write_text(json.dumps(
                {f"{m} {lab}": v for (m, lab), v in results.items()} | {"level_edges": list(LEVEL_EDGES)},
                indent=1))


if __name__ == "__main__":
    main()
