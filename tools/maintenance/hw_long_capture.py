"""A long simulated hardware capture: the DLPC900 simulated at report level, a GigE Vision camera on the bench
(``tests/hw_fakes.py``: 16-bit block ids that wrap from 65535 to 1, strobe-master wiring), the GenICam driver, the
ring buffer and the assembler, for N frames; every completed sequence is compared with the frames its patterns give.

    PYTHONPATH=. python tools/maintenance/hw_long_capture.py --frames 100000 --patterns 30

prints frames, sequences, wraps, drops and the wall time, and exits non-zero if any sequence does not match its
patterns or any frame was lost.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from hw_fakes import FakeCamera  # noqa: E402

from specgpu.capture import capture_sequences  # noqa: E402
from specgpu.hardware.dlpc900 import DLPC900, DLPC900Light, DMDGeometry, DMDLayout, SimulatedDLPC900  # noqa: E402
from specgpu.hardware.genicam import GenICamCamera  # noqa: E402

DMD = DMDGeometry("bench-dmd", 160, 48)
COLUMNS, ROWS = 16, 40


def render(layout, light) -> np.ndarray:
    c0 = layout.column_offset
    counts = np.asarray(light, np.float64)[:, c0:c0 + layout.columns * layout.column_step].sum(axis=0)
    counts = counts.reshape(layout.columns, layout.column_step).sum(axis=1)
    return np.rint(counts[None, :] * 10 + np.arange(4)[:, None] + 1).astype(np.uint16)


def long_capture(frames: int, k: int, *, first_id: int = 1, mode: str = "strobe-master", check_light: bool = True,
                 seed: int = 0) -> dict:
    """Run the capture; returns counts and whether every sequence matched its patterns."""
    sim = SimulatedDLPC900(DMD)
    layout = DMDLayout(DMD, COLUMNS, ROWS)
    light = DLPC900Light(DLPC900(sim, dmd=DMD), layout=layout, exposure_s=0.001,
                         wait_for_trigger=mode == "strobe-master")
    patterns = np.random.default_rng(seed).integers(0, ROWS + 1, (k, COLUMNS))
    light.load_sequence(patterns)
    want = np.stack([render(layout, layout.pattern_to_mask(p)) for p in patterns])
    acquirer = FakeCamera(sim, lambda m: render(layout, m), frames, shape=(4, COLUMNS), first_id=first_id,
                          id_bits=16, lines={"Line0": ("Input", False), "Line1": ("Output", False)})
    camera = GenICamCamera(light, acquirer=acquirer, mode=mode, exposure_s=0.001, n_frames=frames,
                           check_light=check_light, first_frame_id=first_id)
    bad = []
    n_seq = 0

    def check(seq):
        nonlocal n_seq
        n_seq += 1
        if not np.array_equal(seq.frames, want) or not np.array_equal(seq.frame_ids % k, np.arange(k)):
            bad.append(int(seq.cycle))

    t0 = time.perf_counter()
    result = capture_sequences(camera, k, on_sequence=check)
    wall = time.perf_counter() - t0
    a = result.assembly
    return {"frames": frames, "patterns": k, "sequences": n_seq, "mismatched": bad, "dropped": a.dropped,
            "discarded": a.sequences_discarded, "last_frame_id": result.end.last_frame_id,
            "id_wraps": camera._wraps, "wall_s": wall, "mode": mode}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--patterns", type=int, default=30)
    ap.add_argument("--first-id", type=int, default=1)
    ap.add_argument("--mode", choices=("strobe-master", "hardware-trigger"), default="strobe-master")
    ap.add_argument("--no-check-light", action="store_true", help="skip the per-frame Main Status read")
    args = ap.parse_args(argv)
    r = long_capture(args.frames, args.patterns, first_id=args.first_id, mode=args.mode,
                     check_light=not args.no_check_light)
    print(f"{r['frames']} frames ({r['mode']}), {r['patterns']} patterns: {r['sequences']} sequences, "
          f"{len(r['mismatched'])} mismatched, dropped {r['dropped']}, discarded {r['discarded']}, "
          f"block id wraps {r['id_wraps']}, last frame {r['last_frame_id']}; {r['wall_s']:.1f} s "
          f"({r['frames'] / r['wall_s']:.0f} frames/s)")
    ok = (not r["mismatched"] and r["dropped"] == 0 and r["sequences"] == r["frames"] // r["patterns"]
          and r["last_frame_id"] == r["frames"] - 1)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
