"""The guided filter's variance on the device: the package's kernels
(:func:`specgpu.engine.guided_variance.filtered_variance_device`) against the previous ones, which summed each of a
pixel's (4r + 1)^2 weights window by window, O(r^4) per pixel (their copy: ``tools/benchmarks/
guided_variance_previous.cl``), on one textured image with ``--channels`` channels and ``--slopes`` slope images,
for each radius of ``--radii``.

Per radius, the two are run in interleaved rounds (each round: ``--calls`` calls of each, inputs and output on the
device); each kernel's own time is its OpenCL event profile, the median over every call; a ratio is previous / new
of those medians. Also the largest difference between the two outputs, relative to the output's scale.

    PYTHONPATH=. python tools/benchmarks/guided_variance_speed.py [--size 640x480] [--channels 1] [--slopes 9] \
        [--radii 1,2,3,4] [--rounds 5] [--calls 3]
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.engine.guided_variance import filtered_variance_device, pass_terms
from specgpu.engine.runtime import build_options, get_queue, mask_options
from specgpu.pipeline.denoise import DENOISE_EPS
from tools.benchmarks.guided_speed import KernelTimes  # every kernel enqueued, with its event

PREVIOUS = Path(__file__).resolve().with_name("guided_variance_previous.cl")


class PreviousVariance:
    """The previous kernels, launched as :func:`filtered_variance_device` launches the package's (no mask)."""

    def __init__(self, queue, r: int, C: int, D: int):
        options = [*build_options(R=r, C=C, D=D, SQRT=False, SKIPPED_BITS=0), *mask_options(), "-cl-mad-enable",
                   "-cl-denorms-are-zero"]
        program = cl.Program(queue.context, PREVIOUS.read_text(encoding="utf-8")).build(options=options)
        self.queue, self.C, self.D = queue, C, D
        self.first, self.second = cl.Kernel(program, "gv_stats"), cl.Kernel(program, "gv_apply")

    def __call__(self, own, total, guide, eps, slopes, guide_var, terms, out):
        q = self.queue
        H, W, C = own.shape
        flat, starts = pass_terms(terms)
        tables = [cla.to_device(q, a) for a in (flat, starts, np.zeros(C, np.float32))]
        stats = cla.empty(q, (H * W * (3 + self.D),), np.float32)
        glob = (-(-H * W // 64) * 64,)
        self.first.set_args(guide.data, slopes.data, stats.data, np.int32(H), np.int32(W), np.float32(eps))
        events = [cl.enqueue_nd_range_kernel(q, self.first, glob, (64,))]
        self.second.set_args(guide.data, stats.data, own.data, total.data, own.data, tables[0].data,
                             tables[1].data, guide_var.data, tables[2].data, out.data, np.int32(H), np.int32(W))
        events.append(cl.enqueue_nd_range_kernel(q, self.second, glob, (16,), wait_for=events[:1]))
        q.finish()
        return events


def inputs(queue, h: int, w: int, C: int, D: int):
    """A textured guide (a ramp, an edge and noise), own and total variances, slopes following the guide."""
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:h, 0:w]
    g = (0.4 + 0.3 * (xx > w // 2) + 0.2 * np.sin(xx / 7.0) * np.cos(yy / 5.0)
         + rng.normal(0, 0.01, (h, w))).astype(np.float32)
    own = rng.uniform(1e-4, 2e-4, (h, w, C)).astype(np.float32)
    total = (own * 1.5).astype(np.float32)
    slopes = (g[..., None] * rng.uniform(0.2, 1.0, D) + rng.normal(0, 0.01, (h, w, D))).astype(np.float32)
    gvar = np.full((h, w), 1e-6, np.float32)
    terms = [[(d, d, 1.0 / D) for d in range(D)] for _ in range(C)]
    return [cla.to_device(queue, a) for a in (own, total, g, slopes, gvar)], terms


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480", help="WxH of the image")
    ap.add_argument("--channels", type=int, default=1, help="channels carried (1: sigma_rms)")
    ap.add_argument("--slopes", type=int, default=9, help="slope images (the decoder's rank)")
    ap.add_argument("--radii", default="1,2,3,4")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    ap.add_argument("--calls", type=int, default=3, help="calls of each per round")
    ap.add_argument("--device", default=None, help="OpenCL device selector")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    C, D = args.channels, args.slopes
    queue = get_queue(args.device)
    (own, total, g, slopes, gvar), terms = inputs(queue, h, w, C, D)
    new_out, old_out = (cla.empty(queue, own.shape, np.float32) for _ in range(2))
    print(f"{w} x {h}, {C} channel(s), {D} slopes: ms per call (kernel profiles, medians)")
    print(f"  {'r':>2} {'prev stats':>11} {'prev apply':>11} {'new stats':>10} {'new apply':>10} {'ratio':>7} "
          f"{'max diff':>9}")
    for r in (int(v) for v in args.radii.split(",")):
        previous = PreviousVariance(queue, r, C, D)
        times: dict[str, list[float]] = defaultdict(list)
        for _ in range(args.rounds):
            for _ in range(args.calls):
                for name, ev in zip(("prev stats", "prev apply"),
                                    previous(own, total, g, DENOISE_EPS, slopes, gvar, terms, old_out)):
                    times[name].append(1e-6 * (ev.profile.end - ev.profile.start))
            for _ in range(args.calls):
                with KernelTimes() as rec:
                    filtered_variance_device(queue, own, total, g, r, DENOISE_EPS, slopes=slopes, guide_var=gvar,
                                             terms=terms, out=new_out)
                    queue.finish()
                for kernel, ev in rec.events:
                    times["new stats" if kernel == "gv_stats" else "new apply"].append(
                        1e-6 * (ev.profile.end - ev.profile.start))
        med = {k: statistics.median(v) for k, v in times.items()}
        a, b = old_out.get().astype(np.float64), new_out.get().astype(np.float64)
        diff = float(np.max(np.abs(a - b)) / np.max(np.abs(a)))
        ratio = (med["prev stats"] + med["prev apply"]) / (med["new stats"] + med["new apply"])
        print(f"  {r:>2} {med['prev stats']:>11.2f} {med['prev apply']:>11.2f} {med['new stats']:>10.2f} "
              f"{med['new apply']:>10.2f} {ratio:>7.2f} {diff:>9.2e}")


if __name__ == "__main__":
    main()
