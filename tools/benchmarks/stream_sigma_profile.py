"""Where the stream's uncertainty outputs and white-reference correction spend their time, per 640 x 480 sequence
(K = 9, the bench's symmetric plan with 61 output bands):

    PYTHONPATH=. python tools/benchmarks/stream_sigma_profile.py [--size 640x480] [--repeats 15]

Prints the device time of each launch of a sequence alone (enqueue + finish on the warm decoder, median of
``--repeats``): coefficients, sigma (61 bands + RMS), sigma_rms, the XYZ covariance, the fused XYZ / dE2000 pass
and the dE_sigma kernel; then the host's per-sequence white-reference work (the ROI means and the corrected
decoder's matrices) beside the alternative of reducing the ROI on the device (one work-item per frame and a
blocking read of K means, which the decode of that sequence would have to wait for).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu.apps.bench.sizes import parse_sizes  # noqa: E402
from specgpu.engine.runtime import get_queue  # noqa: E402
from specgpu.pipeline import SequenceDecoder  # noqa: E402
from specgpu.pipeline.twin_replay import stream_setup  # noqa: E402
from specgpu.planning import NoiseModel, smooth_prior, with_estimator  # noqa: E402
from specgpu.rig.scene import white_tile_roi  # noqa: E402

_ROI_SUM = """
__kernel void roi_mean(__global const ushort *f, __global float *out, const int x, const int y, const int w,
                       const int h, const int H, const int W) {
    const int k = get_global_id(0);
    float s = 0.0f;
    for (int r = y; r < y + h; ++r) for (int c = x; c < x + w; ++c) s += f[(long)k * H * W + r * W + c];
    out[k] = s / (w * h);
}"""


def _median_ms(fn, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    (width, height), = parse_sizes(args.size)
    setup = stream_setup(width, height, sequences=2, white_tile=0.99)
    plan = with_estimator(setup.plan, setup.bundle, "projection",
                          noise=NoiseModel.from_rig(setup.description, setup.plan.exposure_s),
                          prior=smooth_prior(np.arange(400.0, 700.0 + 1e-9, 5.0)))
    q = get_queue(None)
    K, n = plan.K, width * height
    host_frames = np.ascontiguousarray(setup.frames[:K])
    frames = cla.to_device(q, host_frames.reshape(-1))
    roi = white_tile_roi(height, width)
    dec = SequenceDecoder(plan, setup.bundle, ("coefficients", "XYZ", "dE", "sigma", "sigma_rms", "dE_sigma"),
                          frame_shape=(height, width), device=q, reference=setup.reference, white_roi=roi)
    load = os.getloadavg()[0]
    print(f"{width} x {height}, K = {K}, {plan.A.shape[0]} bands, {q.device.name.strip()}, load {load:.2f}")
    kinds = [kind for _, kind in dec.fused._matrix_makers()] + ["dE_sigma"]
    launches = dec.fused._launches(np.dtype(frames.dtype))
    xyz = cla.zeros(q, 3 * n, np.float32) + 0.3
    cov = cla.zeros(q, 6 * n, np.float32) + 1e-6
    for (launch, names), kind in zip(launches, kinds):
        if kind == "dE_sigma":
            run = lambda: (launch.enqueue(xyz.data, inputs={1: cov.data}), q.finish())  # noqa: E731
        else:
            run = lambda: (launch.enqueue(frames.data), q.finish())  # noqa: E731
        run()
        print(f"  device {kind:13s} {_median_ms(run, args.repeats):7.2f} ms")
    print(f"  device all launches   {_median_ms(lambda: (dec.enqueue(frames), q.finish()), args.repeats):7.2f} ms")
    wr = dec.white_reference
    print(f"  host white gains      {_median_ms(lambda: wr.gains(host_frames), 10 * args.repeats):7.3f} ms")
    gains = wr.gains(host_frames)
    print(f"  host decoder+matrices {_median_ms(lambda: dec.matrices(wr.decoder(gains)), 10 * args.repeats):7.3f} ms"
          " (power change: per-pattern scaling)")
    tilted = gains * np.linspace(0.95, 1.05, K)
    print(f"  host decoder+matrices {_median_ms(lambda: dec.matrices(wr.decoder(tilted)), 10 * args.repeats):7.3f}"
          " ms (colour change: the smooth-ratio refit)")
    x, y, w, h = roi
    sl = (slice(None), slice(y, y + h), slice(x, x + w))
    print(f"  host ROI means alone  "
          f"{_median_ms(lambda: host_frames[sl].reshape(K, -1).mean(axis=1), 10 * args.repeats):7.3f} ms")
    kernel = cl.Program(q.context, _ROI_SUM).build().roi_mean
    buf = cl.Buffer(q.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=host_frames)
    means, dev = np.empty(K, np.float32), cl.Buffer(q.context, cl.mem_flags.WRITE_ONLY, 4 * K)

    def device_roi():
        kernel(q, (K,), None, buf, dev, *(np.int32(v) for v in (x, y, w, h, height, width)))
        cl.enqueue_copy(q, means, dev, is_blocking=True)

    print(f"  device ROI means + blocking read {_median_ms(device_roi, 10 * args.repeats):7.3f} ms")


if __name__ == "__main__":
    main()
