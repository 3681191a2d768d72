"""Measure the stream's transfer modes on this machine: upload (host_ptr, pinned ALLOC_HOST_PTR staging, copy)
x readback (map, copy), on the stream bench's fused case (coefficients + XYZ + dE2000, replayed frames, ``block``
ring policy so the rate is the pipeline's own).

    PYTHONPATH=. python tools/benchmarks/stream_transfers.py [--size 640x480] [--seconds 8] [--rounds 2]

Prints one line per combination and round (combinations interleaved, so a neighbour's load on a shared machine
hits them alike): frames/s in, sequences/s out, latency median / p99, CPU cores; then the device time of each
kernel of a sequence alone (enqueue + finish on the warm decoder, median of 30), the floor under the stream.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import pyopencl.array as cla

from specgpu.apps.bench.sizes import parse_sizes
from specgpu.pipeline import SequenceDecoder, Stream
from specgpu.pipeline.twin_replay import stream_setup


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--outputs", default="coefficients,XYZ,dE")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    (width, height), = parse_sizes(args.size)
    setup = stream_setup(width, height, sequences=4)
    outputs = tuple(args.outputs.split(","))
    print(f"{width} x {height}, outputs {','.join(outputs)}, {args.seconds:g} s each, load {os.getloadavg()[0]:.2f}")
    best = {}
    for round_ in range(args.rounds):
        for upload in ("host_ptr", "pinned", "copy"):
            for readback in ("map", "copy"):
                stream = Stream(setup.driver(), setup.plan, setup.bundle, outputs=outputs, reference=setup.reference,
                                cube_dtype=np.float16, policy="block", upload=upload, readback=readback,
                                sinks=[lambda r: None])
                rep = stream.run(args.seconds)
                key = (upload, readback)
                best[key] = max(best.get(key, 0.0), rep.frames_per_s)
                print(f"round {round_} upload {upload:<9} readback {readback:<5}: {rep.frames_per_s:6.0f} frames/s, "
                      f"{rep.sequences_per_s:6.1f} seq/s, latency {rep.latency_ms(50):6.1f} / "
                      f"{rep.latency_ms(99):6.1f} ms, CPU {rep.cpu_s / rep.seconds:.2f} cores, "
                      f"load {os.getloadavg()[0]:.2f}", flush=True)
    print("best of rounds: " + ", ".join(f"{u}+{r} {v:.0f}" for (u, r), v in best.items()))
    # device time per sequence, each kernel alone and all together
    queue = stream.queue
    frames = cla.to_device(queue, setup.frames[:setup.plan.K].reshape(-1))
    for subset in [(o,) for o in outputs] + [outputs]:
        dec = SequenceDecoder(setup.plan, setup.bundle, subset, frame_shape=(height, width), device=queue,
                              reference=setup.reference if "dE" in subset else None)
        dec.warm_up()
        times = []
        for _ in range(30):
            t = time.perf_counter()
            dec.enqueue(frames)
            queue.finish()
            times.append(time.perf_counter() - t)
        ms = statistics.median(times) * 1e3
        print(f"device {'+'.join(subset):<24}: {ms:6.2f} ms per sequence ({setup.plan.K / ms * 1e3:5.0f} frames/s "
              "if nothing else ran)")

if __name__ == "__main__":
    main()
