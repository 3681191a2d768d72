"""What motion compensation costs per sequence: the decoding pass with and without the warp, and the host's motion
estimation and consistency check, on frames of the moving twin.

Medians over ``--repeats`` calls (after one warm-up), at 640 x 480 with a 9-frame plan decoded to 31 outputs by
default, on the OpenCL device specgpu picks; the rates are sequences per second of each step alone.

    PYTHONPATH=. python tools/benchmarks/motion_cost.py
    PYTHONPATH=. python tools/benchmarks/motion_cost.py --reference-every 3   # and the estimate from broadband \
        reference frames
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from specgpu.engine.linear_map import apply_linear
from specgpu.engine.runtime import get_queue
from specgpu.engine.warp_map import apply_linear_warped
from specgpu.motion.consistency import inconsistent_pixels
from specgpu.motion.flow import flow_field, tile_motion
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.motion.images import frame_gradients
from specgpu.motion.reference import estimate_reference_motion
from specgpu.planning.reference_frames import reference_positions
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters
from specgpu.rig.twin import TwinRig


def median_s(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--outputs", type=int, default=31)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--reference-every", type=int, default=None,
                    help="also time the estimate of the same frames with a broadband frame (every mirror on) before "
                         "the first and after every M (specgpu plan --reference-every M)")
    args = ap.parse_args(argv)
    h, w, K = args.height, args.width, args.frames
    desc = RigDescription(camera=CameraParameters(roi_width=w, roi_height=h, frame_rate_hz=200.0, exposure_s=0.0049),
                          motion=MotionParameters(velocity_px_per_frame=(2.4, 1.8)))
    rig = TwinRig(desc, scene=natural_scene(h, w))
    cols = rig.light.params.columns
    patterns = np.zeros((K, cols), np.int32)
    for k in range(K):  # K broad, overlapping bands
        patterns[k, k * cols // (K + 1):(k + 2) * cols // (K + 1)] = rig.light.params.rows
    rig.load_sequence(patterns)
    frames = np.stack([rig.render(k, k, k * rig.frame_period_s)[0] for k in range(K)])
    with_refs = None
    if args.reference_every:
        refs = reference_positions(K, args.reference_every)
        n = K + len(refs)
        interleaved = np.zeros((n, cols), np.int32)
        interleaved[refs] = rig.light.params.rows // 3  # broadband, about the bands' level on a white
        interleaved[[k for k in range(n) if k not in refs]] = patterns
        rig.load_sequence(interleaved)
        with_refs = (refs, np.stack([rig.render(k, k, k * rig.frame_period_s)[0] for k in range(n)]))
    A = np.random.default_rng(0).normal(0, 1, (args.outputs, K))
    dark = np.full((h, w), 16.0, np.float32)
    gain = np.ones((h, w), np.float32)
    queue = get_queue()
    est = estimate_global_motion(frames, dark, gain)
    gradients = frame_gradients(frames, dark, gain, est.gradients)

    def tile_flow():  # the flow mode's own estimate, from the global one and the gradient images
        motion = tile_motion(gradients, est.shifts, est.reference_frame, est.registered)
        return flow_field(motion, est.shifts, (h, w))

    flow = tile_flow()
    print(f"{w} x {h}, K = {K}, B = {args.outputs}, uint16 frames, device {queue.device.name.strip()}; "
          f"median of {args.repeats}")
    rows = [
        ("decode (linear.cl)", lambda: apply_linear(frames, A, dark, gain, device=queue)),
        ("decode with a shift per frame (warp.cl)",
         lambda: apply_linear_warped(frames, A, est.shifts, dark, gain, device=queue)),
        ("estimate: translation, every pair (36)",
         lambda: estimate_global_motion(frames, dark, gain, pairs="all", robust=False)),
        ("estimate: translation, every pair, upsampled DFT (before)",
         lambda: estimate_global_motion(frames, dark, gain, pairs="all", peak="dft")),
        ("estimate: translation, to the reference, 2x2 binned",
         lambda: estimate_global_motion(frames, dark, gain, robust=False, binning=2)),
        ("estimate: translation, to the reference, tiles always",
         lambda: estimate_global_motion(frames, dark, gain, ambiguous=-1.0)),
        ("estimate: translation, to the reference (8) (default)",
         lambda: estimate_global_motion(frames, dark, gain)),
        ("estimate: affine", lambda: estimate_global_motion(frames, dark, gain, model="affine")),
        ("consistency check", lambda: inconsistent_pixels(frames, est.shifts, dark, gain)),
        # the dense case (--motion flow): a displacement per pixel and frame, on top of the global estimate
        ("estimate: the flow's tiles and field (after the global)", tile_flow),
        ("decode with a flow field per frame (warp.cl, FLOW)",
         lambda: apply_linear_warped(frames, A, flow, dark, gain, device=queue)),
        ("consistency check of a flow (consistency.cl, FLOW)",
         lambda: inconsistent_pixels(frames, flow, dark, gain, gradients=gradients)),
    ]
    if with_refs is not None:
        refs, ref_frames = with_refs
        n = len(ref_frames)
        rows += [
            (f"estimate: every frame of {n} to the reference (cross-spectrum)",
             lambda: estimate_global_motion(ref_frames, dark, gain)),
            (f"estimate: from the {len(refs)} reference frames of {n} (every {args.reference_every})",
             lambda: estimate_reference_motion(ref_frames, refs, dark, gain)),
            (f"estimate: affine from the {len(refs)} reference frames",
             lambda: estimate_reference_motion(ref_frames, refs, dark, gain, model="affine")),
        ]
    base = None
    for name, fn in rows:
        s = median_s(fn, args.repeats)
        base = base or s
        print(f"  {name:<58} {s * 1e3:9.1f} ms  {1.0 / s:8.1f} seq/s  {s / base:6.2f} x decode")


if __name__ == "__main__":
    main()
