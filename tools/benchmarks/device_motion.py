"""The global motion estimate on the device against the host's, per sequence, beside the plain decode, on the moving
twin: what each costs and how far each is from the twin's truth.

Each case renders one 9-frame sequence of the moving twin (the natural scene, 200 fps, K broad overlapping bands, as
``tools/benchmarks/motion_cost.py``) at 640 x 480 and times, in rounds that take each step in turn (the median over
``--rounds``, after a warm-up, all in one run, so the ratios share the machine's load):

* ``decode``: the plain decode, ``apply_linear`` of frames already on the device (K -> ``--outputs``), as the
  stream's decoder runs it;
* ``host``: the estimate as ``--motion global`` makes it without a device, ``estimate_motion(..., device=None)``:
  ``estimate_global_motion`` given the gradient images made on the default device (``frame_gradients``; phase
  correlation on the host);
* ``device``: the estimate as ``--motion global`` makes it with a device (the stream's and the batch's),
  ``estimate_motion(..., device=queue)`` (``motion.device_estimate``: the frames uploaded, their gradient images
  made, registered and read back for the consistency check, the rival-peak check and, where it finds a rival, the
  tiles' consensus); ``device_all_rows``: the same with every row summed at full resolution (``full_rows=1``;
  the estimate sums every n-th band of rows, n = H / ``FULL_ROWS_SUMMED``);
  and ``register_only``: ``register_gradients`` alone on gradient images already made.

Each estimate's error is the largest distance over the frames from the twin's truth (``TwinRig.motion_truth``), px.
The JSON holds every time, error and ratio, the device, the machine's load and the command line.

    PYTHONPATH=. python tools/benchmarks/device_motion.py
    PYTHONPATH=. python tools/benchmarks/device_motion.py --size 320x240 --rounds 3 --json /tmp/device_motion.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
import pyopencl.array as cla

from specgpu.engine.gradients import apply_scale, frames_on_device, launch_gradients
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.registration import register_gradients
from specgpu.engine.runtime import get_queue
from specgpu.motion import device_estimate
from specgpu.motion.methods import estimate_motion
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters
from specgpu.rig.twin import TwinRig

#: (name, motion of the twin)
CASES = [
    ("still", MotionParameters()),
    ("scene 0.6 px/frame", MotionParameters(velocity_px_per_frame=(0.5, -0.35))),
    ("scene 3 px/frame", MotionParameters(velocity_px_per_frame=(2.4, 1.8))),
    ("scene 8 px/frame", MotionParameters(velocity_px_per_frame=(-7.5, 2.5))),
]


def sequence(h: int, w: int, K: int, motion: MotionParameters, seed: int = 0):
    """One sequence of the moving twin: (frames (K, H, W) uint16, the truth's displacement (K, 2))."""
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0, exposure_s=0.0049),
                          motion=motion)
    rig = TwinRig(desc, scene=natural_scene(h, w), seed=seed)
    cols = rig.light.params.columns
    patterns = np.zeros((K, cols), np.int32)
    for k in range(K):  # K broad, overlapping bands
        patterns[k, k * cols // (K + 1):(k + 2) * cols // (K + 1)] = rig.light.params.rows
    rig.load_sequence(patterns)
    ts = np.arange(K) * rig.frame_period_s
    frames = np.stack([rig.render(k, k, ts[k])[0] for k in range(K)])
    return frames, rig.motion_truth(ts)["displacement"]


def reference_of(scale: np.ndarray) -> int:
    """The host estimate's reference frame from each frame's 1 / mean: the brightest of the middle three."""
    K = len(scale)
    middle = list(range(max(0, K // 2 - 1), min(K, K // 2 + 2)))
    return max(middle, key=lambda k: 1.0 / float(scale[k]))


def device_all_rows(frames, dark, gain, queue):
    """The wired-in device estimate with every row summed at full resolution."""
    rows = device_estimate.FULL_ROWS_SUMMED
    device_estimate.FULL_ROWS_SUMMED = 1 << 30
    try:
        return estimate_motion(frames, dark, gain, device=queue)
    finally:
        device_estimate.FULL_ROWS_SUMMED = rows


def timed_rounds(steps: dict, rounds: int, queue) -> dict:
    """Each step's median seconds over ``rounds`` rounds that run every step in turn (after one warm-up round)."""
    times = {name: [] for name in steps}
    for r in range(rounds + 1):
        for name, fn in steps.items():
            queue.finish()
            t = time.perf_counter()
            fn()
            queue.finish()
            if r:
                times[name].append(time.perf_counter() - t)
    return {name: float(np.median(v)) for name, v in times.items()}


def error_px(shifts: np.ndarray, truth: np.ndarray) -> float:
    d = np.asarray(shifts, np.float64) - truth
    return float(np.nanmax(np.hypot(d[:, 0], d[:, 1]))) if np.isfinite(d).any() else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480", help="W x H of the frames (default 640x480)")
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--outputs", type=int, default=31, help="outputs of the plain decode")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--json", default="device_motion.json", help="write the figures here (default: %(default)s)")
    args = ap.parse_args(argv)
    w, h = (int(n) for n in args.size.lower().split("x"))
    K = args.frames
    queue = get_queue()
    A = np.random.default_rng(0).normal(0, 1, (args.outputs, K))
    dark = np.full((h, w), 16.0, np.float32)
    gain = np.ones((h, w), np.float32)
    dark_dev, gain_dev = cla.to_device(queue, dark), cla.to_device(queue, gain)
    load_start = os.getloadavg()[0]
    print(f"{w} x {h}, K = {K}, device {queue.device.name.strip()}; median of {args.rounds} rounds, ms per sequence")
    rows = []
    for name, motion in CASES:
        frames, truth = sequence(h, w, K, motion)
        frames_dev = frames_on_device(queue, frames)
        grads_dev = apply_scale(queue, *launch_gradients(queue, frames_dev, dark_dev, gain_dev))
        ref = reference_of(launch_gradients(queue, frames_dev, dark_dev, gain_dev)[1].get(queue=queue))
        steps = {
            "decode": lambda: apply_linear(frames_dev, A, dark_dev, gain_dev, device=queue),
            "host": lambda: estimate_motion(frames, dark, gain),
            "device": lambda: estimate_motion(frames, dark, gain, device=queue),
            "device_all_rows": lambda: device_all_rows(frames, dark, gain, queue),
            "register_only": lambda: register_gradients(
                grads_dev, ref, full_rows=max(1, h // device_estimate.FULL_ROWS_SUMMED), device=queue),
        }
        times = timed_rounds(steps, args.rounds, queue)
        errors = {"host": error_px(estimate_motion(frames, dark, gain).shifts, truth),
                  "device": error_px(estimate_motion(frames, dark, gain, device=queue).shifts, truth),
                  "device_all_rows": error_px(device_all_rows(frames, dark, gain, queue).shifts, truth)}
        ratios = {k: times[k] / times["decode"] for k in times if k != "decode"}
        rows.append({"case": name, "ms": {k: v * 1e3 for k, v in times.items()}, "error_px": errors,
                     "x_decode": ratios, "host_over_device": times["host"] / times["device"]})
        print(f"  {name:<20} decode {times['decode'] * 1e3:7.1f}   host {times['host'] * 1e3:7.1f} "
              f"({ratios['host']:5.1f} x, err {errors['host']:.3f} px)   device {times['device'] * 1e3:7.1f} "
              f"({ratios['device']:5.1f} x, err {errors['device']:.3f} px)   all rows "
              f"{times['device_all_rows'] * 1e3:7.1f} ({ratios['device_all_rows']:5.1f} x, err "
              f"{errors['device_all_rows']:.3f} px)   registration alone "
              f"{times['register_only'] * 1e3:7.1f} ({ratios['register_only']:4.1f} x)", flush=True)
    out = {"command": " ".join(["python", "tools/benchmarks/device_motion.py", *(argv or sys.argv[1:])]),
           "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "size": [w, h], "frames": K,
           "outputs": args.outputs, "rounds": args.rounds, "device": queue.device.name.strip(),
           "machine": {"cores": os.cpu_count(), "system": platform.platform(terse=True)},
           "load_avg_1min": {"start": load_start, "end": os.getloadavg()[0]}, "cases": rows}
    with open(args.json, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
