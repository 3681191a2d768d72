"""What the motion-compensated decoding of a stream costs on the device against the static decoding: bare kernel
times, every buffer already on the device.

The twin's 9-frame basis plan at 640 x 480 (specgpu.pipeline.twin_replay.stream_setup), uint16 frames with the
calibration's
dark and flat field, and the cases:

* the static decoder as the stream launches it for the outputs ("coefficients", "XYZ")
  (specgpu.pipeline.sequence_decoder.SequenceDecoder.enqueue: a linear pass for the 5 coefficients, a fused pass
  for XYZ);
* the translation path (specgpu.engine.warp_map.PreparedWarp, kernels/warp.cl) writing the same 5 + 3 outputs
  interleaved, each frame displaced by its own translation, in one pass (the raw frames corrected as they are
  read), and as 8 planes; and in two passes, the corrected planes kept for a later step (the correction of the
  frames, then the warp of the corrected planes), each pass alone too;
* with ``--old REV``: the one-pass translation kernel of that revision (linear_warp_translate, which read the raw
  frames, dark and gain inside the warp), the same 8 outputs interleaved.

Each repetition runs every case once, in turn (the order rotated each time), and times from the enqueue to the
end of the queue; the table gives the median and the 25th percentile over ``--repeats`` repetitions, and each
median over the static decoder's.

    PYTHONPATH=. python tools/benchmarks/warp_cost.py
    PYTHONPATH=. python tools/benchmarks/warp_cost.py --old dc279a8     # and that commit's one-pass kernel
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.engine import runtime
from specgpu.engine.runtime import get_queue
from specgpu.engine.warp_map import PreparedWarp, check_shifts
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.pipeline.twin_replay import stream_setup

REPO = Path(__file__).resolve().parents[2]


def old_kernel(queue, rev: str, macros: dict) -> cl.Kernel:
    """linear_warp_translate of kernels/warp.cl at git revision ``rev``, built as specgpu.engine.runtime builds."""
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("warp.cl", "common.h"):
            text = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:kernels/{name}"], check=True,
                                  capture_output=True, text=True).stdout
            (Path(tmp) / name).write_text(text)
        options = [*runtime.build_options(**macros), *runtime.mask_options(), *runtime._device_options(queue.device),
                   "-cl-mad-enable", "-cl-denorms-are-zero", f"-I{tmp}"]
        program = cl.Program(queue.context, (Path(tmp) / "warp.cl").read_text()).build(options=options)
    return cl.Kernel(program, "linear_warp_translate")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--repeats", type=int, default=40)
    ap.add_argument("--old", metavar="REV", help="also time the one-pass translation kernel of this git revision")
    ap.add_argument("--device", help="OpenCL device selector (default: specgpu's choice)")
    args = ap.parse_args(argv)
    queue = get_queue(args.device)
    setup = stream_setup(args.width, args.height, sequences=1)
    plan, bundle = setup.plan, setup.bundle
    K = plan.K
    h, w = args.height, args.width
    n = h * w
    frames = cla.to_device(queue, np.ascontiguousarray(setup.frames[:K]).reshape(-1))
    decoder = SequenceDecoder(plan, bundle, ("coefficients", "XYZ"), frame_shape=(h, w), device=queue)
    if decoder.precorrect:
        raise SystemExit("this calibration corrects the frames on the host first; the comparison needs raw frames")
    decoder.warm_up(np.uint16)
    A = np.vstack([decoder.spec.A_coefficients, decoder.spec.M])  # what the static launches decode, 5 + 3 rows
    m = decoder.spec.A_coefficients.shape[0]
    B = A.shape[0]
    dark, gain = decoder.fused.dark.reshape(h, w), decoder.fused.gain.reshape(h, w)
    # each frame displaced by its own translation, the middle one (the reference) by none
    shifts = np.stack([np.linspace(-4.3, 4.3, K), np.linspace(-1.2, 1.2, K)], axis=1)
    shifts[K // 2] = 0.0
    groups = [("coefficients", m, "interleaved"), ("XYZ", B - m, "interleaved")]
    common = dict(saturation=decoder.fused.saturation)
    warp = PreparedWarp(queue, np.uint16, A, (h, w), dark, gain, outputs=groups, **common)
    planes = PreparedWarp(queue, np.uint16, A, (h, w), dark, gain, outputs=[("y", B, "planar")], **common)
    kept = PreparedWarp(queue, np.uint16, A, (h, w), dark, gain, outputs=groups, corrected_planes=True, **common)
    kept.enqueue(frames, shifts)  # the shifts on the device for the passes timed alone
    queue.finish()

    def enqueue(kernel, sizes):
        return lambda: cl.enqueue_nd_range_kernel(queue, kernel, *sizes)

    cases = {
        "static decoder: coefficients + XYZ (2 passes)": lambda: decoder.enqueue(frames),
        f"translations, one pass: {m} + {B - m} interleaved": lambda: warp.enqueue(frames, shifts),
        f"translations, one pass: {B} planes": lambda: planes.enqueue(frames, shifts),
        f"translations, corrected planes kept: {m} + {B - m} interleaved": lambda: kept.enqueue(frames, shifts),
        "  pass 1: the frames corrected": enqueue(kept.correct, kept._correct_size),
        "  pass 2: the warp of the corrected planes": enqueue(kept.warp, kept._warp_size),
    }
    if args.old:
        macros = dict(K=K, B=B, IN_T="ushort", HAS_DARK=1, HAS_GAIN=True, IS_FLOAT_IN=False, FLOW=None,
                      SAT_LEVEL=repr(float(decoder.fused.saturation)) + "f", OUT_INTERLEAVED=True, STRIP=8)
        kernel = old_kernel(queue, args.old, macros)
        A_dev = cla.to_device(queue, A.astype(np.float32).reshape(-1))
        motion = cla.to_device(queue, check_shifts(shifts, K).reshape(-1))
        out, mask = cla.empty(queue, n * B, np.float32), cla.empty(queue, n, np.uint8)
        kernel.set_args(frames.data, A_dev.data, motion.data, None, dark.data, gain.data, out.data, mask.data,
                        np.uint32(w), np.uint32(h))
        columns = -(-(-(-w // 8)) // 16) * 16
        cases[f"translations, one pass at {args.old}: {B} interleaved"] = enqueue(kernel, ((columns, -(-h // 8)),
                                                                                             (16, 1)))
    names = list(cases)
    for name in names:  # builds, first touches
        cases[name]()
    queue.finish()
    times = {name: [] for name in names}
    for r in range(args.repeats):
        for name in names[r % len(names):] + names[:r % len(names)]:
            t = time.perf_counter()
            cases[name]()
            queue.finish()
            times[name].append(time.perf_counter() - t)
    print(f"{w} x {h}, K = {K}, B = {B} ({m} coefficients + XYZ), uint16 frames with dark and gain, device "
          f"{queue.device.name.strip()}; {args.repeats} repetitions, cases interleaved")
    base = float(np.median(times[names[0]]))
    print(f"  {'':<64} {'median':>9} {'25th pct':>9} {'/ static':>9}")
    for name in names:
        t = np.asarray(times[name])
        print(f"  {name:<64} {np.median(t) * 1e3:6.2f} ms {np.percentile(t, 25) * 1e3:6.2f} ms "
              f"{np.median(t) / base:8.2f}x")


if __name__ == "__main__":
    main()
