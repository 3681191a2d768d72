"""What the consistency check of a motion-compensated sequence costs: the gradient images on the host and on the
device, the check before and after kernels/consistency.cl became one pass of strips, and the whole check from
frames to flags, on frames of the moving twin.

Medians (and minima) over ``--repeats`` rounds after one warm-up, every step once a round in turn (on a shared
machine a slow spell then hits every step alike), at 640 x 480 with 9 frames of broad bands by default, on the
OpenCL device specgpu picks. "before" is the implementation at git revision ``--before`` (``specgpu/engine/
consistency.py`` and ``kernels/consistency.cl`` read with ``git show``, the kernels built from that text); left out
where this is no git checkout or the revision is unknown.

    PYTHONPATH=. python tools/benchmarks/consistency_cost.py
    PYTHONPATH=. python tools/benchmarks/consistency_cost.py --before main --repeats 30 --kernels
"""

from __future__ import annotations

import argparse
import subprocess
import time
import types
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.engine import kernels, runtime
from specgpu.engine.consistency import consistency_from_frames, consistency_maps
from specgpu.engine.gradients import gradient_images
from specgpu.motion.images import gradient_image
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters
from specgpu.rig.twin import TwinRig

ROOT = Path(__file__).resolve().parents[2]


def twin_frames(h: int, w: int, K: int):
    """K frames of K broad, overlapping bands of the moving twin's natural scene, and their true motion."""
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0, exposure_s=0.0049),
                          motion=MotionParameters(velocity_px_per_frame=(2.4, 1.8)))
    rig = TwinRig(desc, scene=natural_scene(h, w))
    cols = rig.light.params.columns
    patterns = np.zeros((K, cols), np.int32)
    for k in range(K):
        patterns[k, k * cols // (K + 1):(k + 2) * cols // (K + 1)] = rig.light.params.rows
    rig.load_sequence(patterns)
    times = np.arange(K) * rig.frame_period_s
    frames = np.stack([rig.render(k, k, t)[0] for k, t in enumerate(times)])
    return frames, rig.motion_truth(times)["displacement"]


def before(revision: str):
    """The consistency module at ``revision`` with its own kernels, or None (no git, no such revision)."""
    def show(path):
        return subprocess.run(["git", "-C", str(ROOT), "show", f"{revision}:{path}"], capture_output=True, text=True,
                              check=True).stdout

    try:
        source, kernel_text = show("specgpu/engine/consistency.py"), show("kernels/consistency.cl")
    except (OSError, subprocess.CalledProcessError):
        return None
    module = types.ModuleType(f"consistency_at_{revision}")
    exec(compile(source, f"{revision}:specgpu/engine/consistency.py", "exec"), module.__dict__)
    built: dict = {}

    def get_kernel(queue, _name, kernel_name, **macros):  # that revision's kernels/consistency.cl, built once
        options = runtime.build_options(**macros)
        if options not in built:
            program = cl.Program(queue.context, kernel_text).build(options=[
                *options, *runtime.mask_options(), *runtime._device_options(queue.device), "-cl-mad-enable",
                "-cl-denorms-are-zero", f"-I{runtime.kernel_dir()}"])
            built[options] = (program, {})
        program, entries = built[options]
        if kernel_name not in entries:
            entries[kernel_name] = cl.Kernel(program, kernel_name)
        return entries[kernel_name]

    module.get_kernel = get_kernel
    return module


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--before", default="main", help="git revision of the check timed as before (default: main)")
    ap.add_argument("--kernels", action="store_true",
                    help="also each kernel's device time in the check from frames (profiling events)")
    args = ap.parse_args(argv)
    h, w, K = args.height, args.width, args.frames
    frames, shifts = twin_frames(h, w, K)
    dark = np.full((h, w), 16.0, np.float32)
    gain = np.ones((h, w), np.float32)
    queue = runtime.get_queue()
    frames_dev, dark_dev, gain_dev = (cla.to_device(queue, a) for a in (frames, dark, gain))

    def host_images():
        return np.stack([gradient_image(f, dark, gain) for f in frames])

    g_host = host_images()
    g_dev = gradient_images(frames_dev, dark_dev, gain_dev)
    old = before(args.before)

    def device_images():
        gradient_images(frames_dev, dark_dev, gain_dev)
        queue.finish()

    steps = [
        ("gradient images: host (gradient_image per frame)", host_images),
        ("gradient images: device, frames in device memory", device_images),
        ("gradient images: device, read back as NumPy", lambda: gradient_images(frames_dev, dark_dev, gain_dev).get()),
        ("consistency_maps: after, host images", lambda: consistency_maps(g_host, shifts)),
        ("consistency_maps: after, images in device memory", lambda: consistency_maps(g_dev, shifts)),
        ("whole check after: frames in device memory -> maps",
         lambda: consistency_from_frames(frames_dev, shifts, dark_dev, gain_dev)),
        ("whole check after: host frames -> maps", lambda: consistency_from_frames(frames, shifts, dark, gain)),
    ]
    if old is not None:
        steps[3:3] = [("consistency_maps: before, host images", lambda: old.consistency_maps(g_host, shifts))]
        steps.append(("whole check before: host frames -> maps (host images)",
                      lambda: old.consistency_maps(host_images(), shifts)))
    times = {name: [] for name, _ in steps}
    for name, fn in steps:
        fn()
    for _ in range(args.repeats):
        for name, fn in steps:
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    print(f"{w} x {h}, K = {K}, uint16 frames, device {queue.device.name.strip()}; median (min) of {args.repeats} "
          "interleaved rounds")
    for name, _ in steps:
        print(f"  {name:<56} {np.median(times[name]) * 1e3:8.2f} ms  ({np.min(times[name]) * 1e3:7.2f})")
    textured, worst = consistency_from_frames(frames_dev, shifts, dark_dev, gain_dev)
    if old is not None:
        textured_old, worst_old = old.consistency_maps(g_host, shifts)
        print(f"  after vs before: textured differs at {int((textured != textured_old).sum())} pixels, worst by at "
              f"most {float(np.abs(worst - worst_old).max()):.2g}; flags (worst < 0.3) differ at "
              f"{int(((textured & (worst < 0.3)) != (textured_old & (worst_old < 0.3))).sum())} pixels")
    if args.kernels:
        events: dict = {}
        launch = kernels.launch_range

        def timed(queue_, kernel, *rest):
            event = launch(queue_, kernel, *rest)
            events.setdefault(kernel.function_name, []).append(event)
            return event

        kernels.launch_range = timed
        try:
            for _ in range(args.repeats):
                consistency_from_frames(frames_dev, shifts, dark_dev, gain_dev)
        finally:
            kernels.launch_range = launch
        print("  kernels of the whole check from device frames (device time, median):")
        for name, evs in events.items():
            ms = np.median([(e.profile.end - e.profile.start) * 1e-6 for e in evs])
            print(f"    {name:<24} {ms:7.2f} ms  ({len(evs) // args.repeats} a call)")


if __name__ == "__main__":
    main()
