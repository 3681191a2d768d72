"""Where the time of the dense cube kernel goes: memory ceiling vs arithmetic, per layout and output dtype.

For 9 uint16 frames -> 61 bands at a given size, times (medians of wall and process CPU time, which counts
every OpenCL worker thread on a CPU device):

- copy      the device's buffer-to-buffer copy of a 256 MiB buffer (the yardstick of the bench),
- store     a kernel that only writes the cube with the production store path (layout, dtype), no arithmetic,
- compute   the production loads and matrix product, one output reduced per pixel, (almost) nothing stored,
- full      the production kernel (kernels/linear.cl),

and the bytes moved per second of each, so a shortfall against the copy bandwidth can be attributed.

    PYTHONPATH=. python tools/benchmarks/profile_cube.py [--size 640x480] [--repeats 15]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.engine import runtime

PROBES = r"""
#include "common.h"
#ifndef OUT_HALF
#define OUT_HALF 0
#endif
#if OUT_HALF
#define OUT_T half
#define STORE_ROW(v, p) STORE_HALF8(v, p)
#define STORE_PLANE(v, p) store_h(v, p, base, count)
#else
#define OUT_T float
#define STORE_ROW(v, p) STORE8(float, v, p)
#define STORE_PLANE(v, p) store_f(v, p, base, count)
#endif

/* the store path of linear_apply with constant data */
__kernel void store_only(__global OUT_T *restrict out, const ulong n)
{
    PIXEL_RANGE(n);
    const floatv v = (floatv)(1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f, 8.0f);
#if OUT_LAYOUT == 0
    for (uint b = 0; b < B; ++b) STORE_PLANE(v + (float)b, out + (ulong)b * n);
#else
    for (uint next = 0; next < B; next += 8) {
        const uint b0 = next + 8 <= B ? next : B - 8;
        for (uint j = 0; j < VW; ++j) STORE_ROW(v + (float)j, out + (base + j) * B + b0);
    }
#endif
}

/* the loads and the matrix product of linear_apply; one sum per pixel vector is kept alive by a store that
 * happens only when it is exactly zero (never, for these inputs) */
__kernel void compute_only(__global const IN_T *restrict frames, __constant const float *restrict A,
                           __global const float *restrict dark, __global float *restrict out, const ulong n)
{
    PIXEL_RANGE(n);
    LOAD_PIXELS();
    floatv sum = (floatv)(0.0f);
    for (uint b = 0; b < B; ++b) {
        floatv y;
        DOT_ROW(y, A, b);
        sum += y;
    }
    if (sum.s0 == 0.0f && sum.s7 == 0.0f) out[base] = sum.s1;
}
"""


def median_times(queue, fn, repeats):
    walls, cpus = [], []
    for _ in range(repeats):
        queue.finish()
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        queue.finish()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--device", default=None)
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    n, K, B = width * height, 9, 61
    queue = runtime.get_queue(args.device)
    rng = np.random.default_rng(0)
    frames = cla.to_device(queue, rng.integers(0, 1024, K * n, dtype=np.uint16))
    A = cla.to_device(queue, rng.normal(0, 1e-3, (B, K)).astype(np.float32))
    items = -(-n // 8)
    print(f"{queue.device.name.strip()}: {K} uint16 frames -> {B} bands, {width}x{height}; "
          f"medians of {args.repeats}; GB/s = (frames in + cube out) / wall time")

    big = cla.to_device(queue, np.ones(256 * 2**20, np.uint8))
    big2 = cla.empty_like(big)
    big2.fill(0)
    wall, cpu = median_times(queue, lambda: cl.enqueue_copy(queue, big2.data, big.data), 7)
    copy_gbps = 2 * big.nbytes / wall / 1e9
    print(f"{'copy 256 MiB':<34} wall {wall * 1e3:8.2f} ms  cpu {cpu * 1e3:8.2f} ms  {copy_gbps:6.2f} GB/s")

    for out_dtype in (np.float32, np.float16):
        for layout in (0, 1):
            out = cla.zeros(queue, (B * n,), out_dtype)
            moved = frames.nbytes + out.nbytes
            options = runtime.build_options(K=K, B=B, IN_T="ushort", OUT_LAYOUT=layout,
                                            OUT_HALF=out_dtype == np.float16)
            device_options = runtime._device_options(queue.device)
            program = cl.Program(queue.context, PROBES).build(
                options=[*options, *device_options, "-cl-mad-enable", f"-I{runtime.kernel_dir()}"])
            store_k = cl.Kernel(program, "store_only")
            compute_k = cl.Kernel(program, "compute_only")
            full_k = runtime.get_kernel(queue, "linear.cl", "linear_apply", K=K, B=B, IN_T="ushort", IN_LAYOUT=0,
                                        HAS_DARK=0, HAS_GAIN=0, IS_FLOAT_IN=0, OUT_HALF=out_dtype == np.float16,
                                        OUT_LAYOUT=layout, WRITE_MASK=0)
            runs = {
                "store": (lambda: store_k(queue, (items,), None, out.data, np.uint64(n)), out.nbytes),
                "compute": (lambda: compute_k(queue, (items,), None, frames.data, A.data, None, out.data,
                                              np.uint64(n)), frames.nbytes),
                "full": (lambda: full_k(queue, (items,), None, frames.data, A.data, None, None, out.data, None,
                                        np.uint64(n)), moved),
            }
            name = f"{np.dtype(out_dtype).name} {'interleaved' if layout else 'planar'}"
            for label, (fn, nbytes) in runs.items():
                fn()
                wall, cpu = median_times(queue, fn, args.repeats)
                print(f"{name + ' ' + label:<34} wall {wall * 1e3:8.2f} ms  cpu {cpu * 1e3:8.2f} ms  "
                      f"{nbytes / wall / 1e9:6.2f} GB/s  ({nbytes / wall / 1e9 / copy_gbps:4.0%} of copy)")


if __name__ == "__main__":
    main()
