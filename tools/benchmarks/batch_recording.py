"""Write a long raw-frame recording for `specgpu batch` measurements, from the twin's frames.

    PYTHONPATH=. python tools/benchmarks/batch_recording.py --sequences 2000 --size 640x480 --out /tmp/rec.zarr

The twin (stream_setup: calibrated 200 fps camera, symmetric plan, K = 9) records 8 sequences of the colorchecker;
they are replayed in turn, with running frame ids, into a ZarrRecorder with raw frames only (what `specgpu stream
--frames --outputs ...` writes, without the stream's own outputs). plan.npz and calibration.npz are stored beside
the frames, as `specgpu stream --out` does, so `specgpu batch REC --plan REC/plan.npz --out OUT` runs as is.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu.apps.bench.sizes import parse_sizes  # noqa: E402
from specgpu.calibration.bundle import save_calibration  # noqa: E402
from specgpu.io.recording import ZarrRecorder  # noqa: E402
from specgpu.pipeline import StreamResult  # noqa: E402
from specgpu.pipeline.twin_replay import stream_setup  # noqa: E402
from specgpu.planning import save_plan  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=2000)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    (width, height), = parse_sizes(args.size)
    setup = stream_setup(width, height, sequences=8, output_step_nm=10.0)
    K = setup.plan.K
    rec = ZarrRecorder(args.out, setup.plan, outputs=(), frames=True,
                       metadata={"source": "tools/benchmarks/batch_recording.py"})
    save_plan(Path(args.out) / "plan.npz", setup.plan)
    save_calibration(Path(args.out) / "calibration.npz", setup.bundle)
    t0 = time.perf_counter()
    for i in range(args.sequences):
        j = i % 8
        ids = [i * K + k for k in range(K)]
        rec.write(StreamResult(i, i, ids, [t * 0.005 for t in ids], {}, 0.0, frames=setup.frames[j * K:(j + 1) * K]))
    rec.close()
    print(f"wrote {args.out}: {rec.committed} sequences of {K} frames {width} x {height} in "
          f"{time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
