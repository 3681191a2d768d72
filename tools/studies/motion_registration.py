"""Accuracy and cost of the global motion estimate's settings: each frame's estimated displacement against the moving
twin's truth, and the estimate's time, per setting of ``estimate_global_motion``.

The twin at the paper's noise (its own, oracle, calibration), the natural scene, two narrowband plans (50 and 40 nm
steps: 7 and 8 frames), six motions (drifts of 3.2, 1.3, 3.0 and 0.7 px per frame; vibrations of 0.5 px RMS at 20 Hz
and 1 px RMS at 35 Hz), two noise draws each: 24 sequences. Per setting: the largest and the median of each
sequence's largest per-frame error |estimate - truth| (px), how many sequences exceed 0.1 px, and the median time
of the estimate (the settings run in turn on each sequence, so a change of the machine's load falls on every
setting alike).

    PYTHONPATH=. python tools/studies/motion_registration.py                         # 320 x 240, the settings below
    PYTHONPATH=. python tools/studies/motion_registration.py --size 640x480 --settings "peak='dft',pairs='all';"

With ``--reference-every M`` the plans get a broadband reference frame before their first frame and after every M
(``specgpu plan --reference-every M``), and a setting that starts with ``reference`` runs
``estimate_reference_motion`` (the reference frames registered to each other, every frame interpolated in time)
instead, its other keys passed on to it:

    PYTHONPATH=. python tools/studies/motion_registration.py --size 640x480 --reference-every 3 \
        --settings ";reference;reference,interpolation='linear'"
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.motion.reference import estimate_reference_motion
from specgpu.planning.reference_frames import reference_indices, with_reference_frames
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters
from specgpu.rig.twin import TwinRig

MOTIONS = (MotionParameters(velocity_px_per_frame=(3.0, 1.0)), MotionParameters(velocity_px_per_frame=(-0.37, 1.21)),
           MotionParameters(vibration_rms_px=0.5, vibration_hz=20.0, seed=2),
           MotionParameters(velocity_px_per_frame=(2.4, 1.8)), MotionParameters(velocity_px_per_frame=(0.13, -0.71)),
           MotionParameters(vibration_rms_px=1.0, vibration_hz=35.0, seed=4))

SETTINGS = ("peak='dft',pairs='all';peak='dft',pairs='all',upsample=50;;pairs='all';peak='dft';binning=2;"
            "binning=2,cutoff=0.24")


def frames_of(desc, plan, scene, motion, seed):
    """One sequence of ``plan`` on the moving twin, rendered frame by frame, and each frame's true displacement."""
    rig = TwinRig(plan.rig_description(replace(desc, motion=motion)), scene=scene, seed=seed)
    rig.load_sequence(plan.patterns)
    ts = np.arange(plan.K) * rig.frame_period_s
    return np.stack([rig.render(k, k, ts[k])[0] for k in range(plan.K)]), rig.motion_truth(ts)["displacement"]


def parse_setting(text: str) -> dict:
    """``"a=1,b='x'"`` as keyword arguments of ``estimate_global_motion`` (empty: its defaults)."""
    kw = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, _, value = item.partition("=")
        kw[key.strip()] = value.strip().strip("'\"") if value.strip()[:1] in "'\"" else float(value) \
            if "." in value else int(value)
    return kw


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="320x240", help="WxH of the frames")
    ap.add_argument("--settings", default=SETTINGS, help="';'-separated settings, each 'key=value,...' ('' for the "
                                                          "defaults)")
    ap.add_argument("--reference-every", type=int, default=None,
                    help="plans with a broadband reference frame every M frames (settings 'reference...' use them)")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0, exposure_s=0.0049))
    bundle = oracle_calibration(desc)
    scene = natural_scene(h, w)
    cases = []
    for step in (50.0, 40.0):
        plan = make_plan("narrowband", bundle, step_nm=step, max_exposure_s=0.0049)
        if args.reference_every:
            plan = with_reference_frames(plan, bundle, args.reference_every)
        refs = reference_indices(plan)
        dark, gain = bundle.dark_at(plan.exposure_s), bundle.flat_field
        for motion in MOTIONS:
            for seed in (5, 6):
                frames, truth = frames_of(desc, plan, scene, motion, seed)
                cases.append((frames, truth, dark, gain, refs))
    settings = args.settings.split(";")
    errors = {s: [] for s in settings}
    times = {s: [] for s in settings}
    for frames, truth, dark, gain, refs in cases:
        for s in settings:
            t = time.perf_counter()
            if s.startswith("reference"):
                if not refs:
                    raise SystemExit(f"setting {s!r} needs --reference-every")
                est = estimate_reference_motion(frames, refs, dark, gain, **parse_setting(s[len("reference"):]))
            else:
                est = estimate_global_motion(frames, dark, gain, **parse_setting(s))
            times[s].append(time.perf_counter() - t)
            errors[s].append(float(np.abs(est.shifts - truth).max()))
    print(f"{w} x {h}, {len(cases)} sequences of the moving twin; per sequence its largest per-frame error, px")
    print(f"  {'setting':<28} {'max':>7} {'median':>7} {'> 0.1 px':>9} {'time':>9}")
    for s in settings:
        e = np.array(errors[s])
        print(f"  {s or '(defaults)':<28} {e.max():7.3f} {np.median(e):7.3f} {int((e > 0.1).sum()):>5}/{len(e):<3} "
              f"{np.median(times[s]) * 1e3:7.1f} ms")


if __name__ == "__main__":
    main()
