"""The stream's host path alone: replayed frames -> ring buffer -> sequence assembler, with no decode.

What the frames' own path can carry on this machine, the ceiling below which a stream whose device work is
negligible (a GPU) is capped by something else: its per-sequence upload, launches, read-back and result handling.

    PYTHONPATH=. python tools/benchmarks/stream_host_path.py --size 640x480 --runs 3
"""

from __future__ import annotations

import argparse
import threading
import time

from specgpu.capture.assemble import SequenceAssembler, assemble_stream
from specgpu.capture.ringbuffer import RingBuffer, run_producer
from specgpu.pipeline.twin_replay import stream_setup


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480", help="WxH of the frames")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--loops", type=int, default=40, help="passes over the 8 recorded sequences per run")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    setup = stream_setup(w, h, sequences=8)
    K = setup.plan.K
    rates = []
    for _ in range(args.runs):
        driver = setup.driver(loops=args.loops)
        ring = RingBuffer(4 * K, (h, w), driver.dtype, "block")  # the stream's own ring depth
        producer = threading.Thread(target=run_producer, args=(driver, ring), daemon=True)
        driver.start()
        t0 = time.perf_counter()
        producer.start()
        n = sum(1 for _ in assemble_stream(ring, SequenceAssembler(K), timeout=1.0))
        rates.append(n * K / (time.perf_counter() - t0))
        producer.join()
    rates.sort()
    print(f"{w} x {h}, K = {K}: driver -> ring -> assembler, no decode: median {rates[len(rates) // 2]:.0f} raw "
          f"frames/s over {args.runs} runs ({', '.join(f'{r:.0f}' for r in rates)})")


if __name__ == "__main__":
    main()
