"""The guided filter's speed: the package's filter (:func:`specgpu.engine.guided.guided_filter_device`) against the
previous device filter (box means by direct sums, five passes and four full-size intermediates per call; its
kernels are the copy in ``tools/benchmarks/guided_previous.cl``) and against the same filter in NumPy / SciPy
(``specgpu bench``'s baseline), on one image of ``--channels`` channels, radius and eps those of ``recover
--denoise``.

The three are timed in interleaved rounds (each round: ``--calls`` calls of each device filter, data and output
on the device, enqueue + finish, and one NumPy call), so that all see the same load of the machine; a ratio is
the median over the rounds of each round's ratio of medians. Then each kernel's own time, from OpenCL event
profiling (median over ``--calls`` profiled calls), and the largest difference between the outputs.

    PYTHONPATH=. python tools/benchmarks/guided_speed.py [--size 640x480] [--channels 9] [--rounds 9]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

import specgpu.engine.guided as guided
from specgpu.apps.bench.denoise import guided_numpy
from specgpu.engine.runtime import get_allocator, get_queue
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS

PREVIOUS = Path(__file__).resolve().with_name("guided_previous.cl")
_GROUP = 128  # the previous filter's work-group: every channel of up to 128 / channels pixels


class PreviousFilter:
    """The previous device filter: products, box means along x then y (direct sums over the clipped window), the
    linear models, box means again, the output; each intermediate a fresh buffer from the context's pool."""

    def __init__(self, queue):
        self.queue = queue
        program = cl.Program(queue.context, PREVIOUS.read_text(encoding="utf-8")).build(
            options=["-cl-mad-enable", "-cl-denorms-are-zero"])
        self.kernels = {name: cl.Kernel(program, name) for name in ("box_h", "box_v", "gf_products", "gf_coeffs",
                                                                     "gf_apply")}

    def _run(self, name, shape, *args):
        c = min(_GROUP, shape[0])
        local = (c, max(1, _GROUP // c)) + (1,) * (len(shape) - 2)
        glob = tuple(-(-int(n) // int(g)) * int(g) for n, g in zip(shape, local))
        kernel = self.kernels[name]
        kernel.set_args(*args)
        return cl.enqueue_nd_range_kernel(self.queue, kernel, glob, local)

    def _empty(self, size):
        return cla.empty(self.queue, (size,), np.float32, allocator=get_allocator(self.queue))

    def _box(self, src, H, W, C, r, keep):
        tmp, out = self._empty(H * W * C), self._empty(H * W * C)
        args = (np.int32(H), np.int32(W), np.int32(C), np.int32(r))
        self._run("box_h", (C, W, H), src.data, tmp.data, *args)
        self._run("box_v", (C, W, H), tmp.data, out.data, *args)
        keep += [tmp, out]
        return out

    def __call__(self, p, g, r, eps, out):
        H, W, B = p.shape
        n, keep = H * W, []
        x = self._empty(n * (2 * B + 2))
        self._run("gf_products", (B, n), p.data, g.data, x.data, np.int32(B), np.uint64(n))
        m = self._box(x, H, W, 2 * B + 2, r, keep)
        ab = self._empty(n * 2 * B)
        self._run("gf_coeffs", (B, n), m.data, ab.data, np.int32(B), np.float32(eps), np.uint64(n))
        mab = self._box(ab, H, W, 2 * B, r, keep)
        self._run("gf_apply", (B, n), mab.data, g.data, out.data, np.int32(B), np.uint64(n))
        self.queue.finish()  # the pooled intermediates go back only once every pass has run
        return out


class KernelTimes:
    """Records every kernel enqueued while active (pyopencl's enqueue wrapped) and sums each kernel's profiled
    time per call."""

    def __init__(self):
        self.events: list[tuple[str, cl.Event]] = []
        self.real = cl.enqueue_nd_range_kernel

    def __enter__(self):
        def recording(queue, kernel, *args, **kwargs):
            event = self.real(queue, kernel, *args, **kwargs)
            self.events.append((kernel.function_name, event))
            return event

        cl.enqueue_nd_range_kernel = recording
        return self

    def __exit__(self, *exc):
        cl.enqueue_nd_range_kernel = self.real

    def per_call(self, calls: int) -> dict[str, float]:
        """Milliseconds per call of each kernel (a kernel launched twice in a call counts both), median over the
        calls (events taken in call order)."""
        per_kernel: dict[str, list[float]] = defaultdict(list)
        for name, event in self.events:
            event.wait()
            per_kernel[name].append(1e-6 * (event.profile.end - event.profile.start))
        result = {}
        for name, times in per_kernel.items():
            k = len(times) // calls
            result[name] = statistics.median(sum(times[i * k:(i + 1) * k]) for i in range(calls))
        return result


def _ms(fn) -> float:
    start = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - start)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480", help="WxH of the image")
    ap.add_argument("--channels", type=int, default=9)
    ap.add_argument("--rounds", type=int, default=9, help="interleaved rounds")
    ap.add_argument("--calls", type=int, default=5, help="calls of each device filter per round")
    ap.add_argument("--device", default=None, help="OpenCL device selector")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    r, eps, C = DENOISE_RADIUS, DENOISE_EPS, args.channels
    queue = get_queue(args.device)
    rng = np.random.default_rng(3)
    g = rng.uniform(0.2, 1.0, (h, w)).astype(np.float32)
    p = (g[..., None] * rng.uniform(0.1, 0.9, C) + rng.normal(0, 0.01, (h, w, C))).astype(np.float32)
    p_dev, g_dev = cla.to_device(queue, p), cla.to_device(queue, g)
    out_new, out_old = cla.empty(queue, p.shape, np.float32), cla.empty(queue, p.shape, np.float32)
    previous = PreviousFilter(queue)

    def new():
        guided.guided_filter_device(queue, p_dev, g_dev, r, eps, out=out_new)
        queue.finish()

    def old():
        previous(p_dev, g_dev, r, eps, out_old)

    expected = guided_numpy(p, g, r, eps)
    new(), old()  # builds, intermediates made
    rows = defaultdict(list)
    vs_old, vs_numpy = [], []
    for _ in range(args.rounds):
        t_new = statistics.median(_ms(new) for _ in range(args.calls))
        t_old = statistics.median(_ms(old) for _ in range(args.calls))
        t_np = _ms(lambda: guided_numpy(p, g, r, eps))
        rows["new"].append(t_new), rows["old"].append(t_old), rows["numpy"].append(t_np)
        vs_old.append(t_old / t_new), vs_numpy.append(t_np / t_new)
    print(f"{queue.device.name.strip()}: {w} x {h} x {C}, radius {r}, eps {eps:g}; {args.rounds} interleaved rounds "
          f"of {args.calls} calls")
    for name in ("new", "old", "numpy"):
        print(f"  {name:6s} median {statistics.median(rows[name]):8.1f} ms  (rounds: "
              f"{', '.join(f'{t:.0f}' for t in rows[name])})")
    print(f"  new vs old:   {statistics.median(vs_old):5.2f}x  (median of the rounds' ratios; "
          f"min {min(vs_old):.2f}, max {max(vs_old):.2f})")
    print(f"  new vs NumPy: {statistics.median(vs_numpy):5.2f}x  (min {min(vs_numpy):.2f}, max {max(vs_numpy):.2f})")
    for label, fn in (("new", new), ("old", old)):
        with KernelTimes() as times:
            for _ in range(args.calls):
                fn()
        per = times.per_call(args.calls)
        print(f"  {label} per kernel (event profiling, ms per call): "
              + ", ".join(f"{k} {v:.1f}" for k, v in per.items()) + f"; sum {sum(per.values()):.1f}")
    scale = max(float(np.max(np.abs(expected))), 1e-30)
    for label, got in (("new", out_new.get()), ("old", out_old.get())):
        print(f"  {label} max |diff| vs NumPy float32: {float(np.max(np.abs(got - expected))) / scale:.2e} "
              "(relative to the largest output)")


if __name__ == "__main__":
    main()
