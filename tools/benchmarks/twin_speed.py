"""How fast the digital twin renders frames (frames/s) through its driver, at 640 x 480 and at 320 x 240.

Usage: PYTHONPATH=. python tools/benchmarks/twin_speed.py [--frames N] [--patterns K]

Renders N frames of a K-pattern sequence on the ColorChecker scene through ``TwinDriver.fill`` into one
preallocated slot (the streaming path's cost), with fresh noise and with the noise pool, and prints frames/s.
The noise-free frame of every pattern is rendered once at ``start()``; that one-off cost is printed separately.
Also prints the rate of ``ReplayDriver`` replaying a recording of the twin (for work that must outrun 780 fps).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from specgpu.capture.twin_driver import TwinDriver
from specgpu.rig.config import RigDescription
from specgpu.rig.twin import TwinRig


def measure(roi, frames, k, noise):
    desc = RigDescription()
    cam = dataclasses.replace(desc.camera, roi_width=roi[0], roi_height=roi[1])
    rig = TwinRig(dataclasses.replace(desc, camera=cam), scene="colorchecker")
    rng = np.random.default_rng(1)
    rig.load_sequence(rng.integers(0, rig.light.params.rows + 1, (k, rig.light.params.columns)))
    rig.set_noise(noise)
    driver = TwinDriver(rig, n_frames=frames + 20)
    slot = np.empty(driver.frame_shape, np.uint16)
    t0 = time.perf_counter()
    driver.start()
    setup = time.perf_counter() - t0
    for _ in range(20):  # warm-up: first touches of the pool and scratch memory
        driver.fill(slot)
    t0 = time.perf_counter()
    n = 0
    while driver.fill(slot) is not None:
        n += 1
    dt = time.perf_counter() - t0
    driver.stop()
    return n / dt, setup


def measure_replay(roi, frames, k):
    """Frames/s of replaying a recording of the twin (memory copies into the slot)."""
    from specgpu.capture.replay import ReplayDriver, record

    desc = RigDescription()
    cam = dataclasses.replace(desc.camera, roi_width=roi[0], roi_height=roi[1])
    rig = TwinRig(dataclasses.replace(desc, camera=cam), scene="colorchecker")
    rig.load_sequence(np.random.default_rng(1).integers(0, rig.light.params.rows + 1, (k, rig.light.params.columns)))
    recorded = record(TwinDriver(rig), 8 * k)
    driver = ReplayDriver(*recorded, loops=None)
    slot = np.empty(driver.frame_shape, np.uint16)
    driver.start()
    t0 = time.perf_counter()
    for _ in range(frames):
        driver.fill(slot)
    return frames / (time.perf_counter() - t0)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--patterns", type=int, default=9)
    args = ap.parse_args()
    for roi in ((640, 480), (320, 240)):
        for noise in ("fresh", "pool"):
            fps, setup = measure(roi, args.frames, args.patterns, noise)
            print(f"{roi[0]}x{roi[1]}  noise={noise:5s}  {fps:8.0f} frames/s   "
                  f"(noise-free frames of {args.patterns} patterns: {setup * 1e3:.0f} ms once)")
        print(f"{roi[0]}x{roi[1]}  replay      {measure_replay(roi, args.frames, args.patterns):8.0f} frames/s   "
              f"(a recording of {8 * args.patterns} twin frames, looped)")


if __name__ == "__main__":
    main()
