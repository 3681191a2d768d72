"""Temporal accumulation along the motion on the twin: one sequence against the running estimate over up to N.

The twin and plans of ``tools/studies/motion_study.py`` (the paper's noise, 640 x 480 at 200 fps, the natural scene,
oracle calibration). For each motion case, ``--sequences`` consecutive sequences are rendered frame by frame, each
decoded motion-compensated (:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder`'s motion mode: cube and
sigma_rms) and fed to the running estimate that moves with the scene
(:class:`specgpu.pipeline.accumulate.AccumulateSink` with ``motion=True``, as ``specgpu stream --motion global
--accumulate N``). The last sequence is scored per pixel against the scene at its reference time: RMSE (reflectance,
400-700 nm at 10 nm) and dE2000 (D65) over the field and within 3 px of an edge of the scene, over the pixels both the
sequence and the estimate have (the scores leave out a 3 px band about a moving object's edges). ``noise`` is the part
of the error that changes between noise draws (the RMS of the difference of two draws over sqrt 2), which is what
accumulation can remove; the rest (the prior's mismatch, the compensation's interpolation) stays. Mean +- std over
``--draws`` draws.

    PYTHONPATH=. python tools/studies/motion_accumulate.py                      # ~4 min
    PYTHONPATH=. python tools/studies/motion_accumulate.py --small --draws 2 --cases t3 --plans symmetric-9
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from motion_study import CASES, fmt, twin_setup
from scipy import ndimage

from specgpu.pipeline.accumulate import AccumulateSink
from specgpu.pipeline.evaluate import evaluate_pixels
from specgpu.pipeline.moving_scores import edge_band
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.estimators import NoiseModel, with_estimator
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import SpectralScene
from specgpu.rig.twin import TwinRig

STILL = ("still", MotionParameters())


def run(desc, bundle, plan, scene, motion, sequences, N, seed):
    """The last sequence's cube and the running estimate after ``sequences``, the truth, the object mask, and the
    sink's seconds per sequence."""
    rig = TwinRig(plan.rig_description(replace(desc, motion=motion)), scene=scene)
    rig.seed = seed  # the frames' temporal noise and light (the camera's fixed pattern is the calibrated one)
    rig.load_sequence(plan.patterns)
    dec = SequenceDecoder(plan, bundle, ("cube", "sigma_rms"), motion="global")
    sink = AccumulateSink(N, ("cube", "sigma_rms"), motion=True)
    seconds = []
    for s in range(sequences):
        ts = (s * plan.K + np.arange(plan.K)) * rig.frame_period_s
        frames = np.stack([rig.render(k, s * plan.K + k, ts[k])[0] for k in range(plan.K)])
        maps = dec.maps(frames)
        single = maps["cube"].copy()
        t0 = time.perf_counter()
        sink.write(SimpleNamespace(arrays=maps))
        seconds.append(time.perf_counter() - t0)
    truth = rig.motion_truth(ts)
    return single, maps["cube"], truth, float(np.median(seconds[1:])), sink


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="320 x 240 instead of 640 x 480")
    ap.add_argument("--draws", type=int, default=3, help="noise draws per row (default 3; at least 2 for noise)")
    ap.add_argument("--cases", default="still,t1,t3,vib,object", help=f"comma-separated, of still, {', '.join(CASES)}")
    ap.add_argument("--plans", default="symmetric-9,optimal-9")
    ap.add_argument("--sequences", type=int, default=6, help="sequences streamed (the last one is scored)")
    ap.add_argument("--accumulate", type=int, default=4, help="N, the most sequences averaged")
    ap.add_argument("--edge", type=float, default=0.08, help="RMS reflectance step that counts as an edge")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    desc, bundle, plans, scene = twin_setup(args.small, args.plans)
    w, h = desc.camera.roi_width, desc.camera.roi_height
    print(f"twin: paper's noise, {w} x {h}, 200 fps; scene {scene.name}; oracle calibration; {args.draws} draws; "
          f"{args.sequences} sequences, the last scored; --accumulate {args.accumulate} along the motion")
    head = (f"{'motion':<32} {'plan':<12} {'':<12} {'RMSE field':>14} {'RMSE edge':>14} {'dE00 field':>12} "
            f"{'noise':>8}")
    print("\n" + head)
    for case in args.cases.split(","):
        label, motion = STILL if case == "still" else CASES[case]
        for pname, plan in plans.items():
            if "noise" not in plan.params:  # sigma_rms needs the plan's noise model
                plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
            runs = [run(desc, bundle, plan, scene, motion, args.sequences, args.accumulate, 2000 + 17 * d)
                    for d in range(args.draws)]
            truth = runs[0][2]
            t_scene = SpectralScene(scene.wavelengths, truth["reflectance"], name="truth at the reference time")
            valid = np.all([np.isfinite(r[k][..., 0]) for r in runs for k in (0, 1)], axis=0)
            if truth["object_mask"] is not None:
                inside = truth["object_mask"] > 0.5
                valid &= ~((ndimage.distance_transform_edt(~inside) <= 3)
                           & (ndimage.distance_transform_edt(inside) <= 3))
            band = edge_band(truth["reflectance"], args.edge)
            scores = {"one sequence": [], "accumulated": []}
            for r in runs:
                for kind, y in (("one sequence", r[0]), ("accumulated", r[1])):
                    rep = evaluate_pixels(y, t_scene, wavelengths=plan.output_wavelengths)
                    scores[kind].append((float(np.mean(rep.rmse[valid])), float(np.mean(rep.rmse[valid & band])),
                                         float(np.mean(rep.delta_E_2000[valid]))))
            for i, kind in enumerate(scores):
                k = 0 if kind == "one sequence" else 1
                noise = [np.sqrt(np.mean((runs[d][k] - runs[d + 1][k])[valid] ** 2) / 2)
                         for d in range(len(runs) - 1)]
                s = np.array(scores[kind])
                print(f"{label if i == 0 else '':<32} {pname if i == 0 else '':<12} {kind:<12} "
                      f"{fmt(s[:, 0], 4):>14} {fmt(s[:, 1], 4):>14} {fmt(s[:, 2], 2):>12} "
                      f"{fmt(noise, 4) if noise else '-':>8}")
            ratio = np.array(scores["accumulated"]) / np.array(scores["one sequence"])
            sink = runs[0][4]
            shifts = np.array(sink.shifts)
            print(f"{'':<32} {'':<12} {'ratio':<12} {fmt(ratio[:, 0], 2):>14} {fmt(ratio[:, 1], 2):>14} "
                  f"{fmt(ratio[:, 2], 2):>12}   averaged {100 * np.mean(sink.counts[valid] >= 2):.0f} % of the "
                  f"pixels (>= 2 sequences), restarts {100 * np.mean(sink.resets):.1f} %/sequence, step "
                  f"{np.round(np.median(shifts, axis=0), 2)} px, sink {1e3 * np.median([r[3] for r in runs]):.0f} ms")
    print(f"\n({time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
