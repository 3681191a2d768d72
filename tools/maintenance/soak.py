"""Soak test: stream the twin at 200 fps for minutes with injected faults and a sink that stalls now and then.

    PYTHONPATH=. python tools/maintenance/soak.py --minutes 10

The twin camera runs paced (each frame delivered no earlier than its exposure ends, at the rig's frame rate)
with random frame drops, duplicated frames and missed light triggers; a sink sleeps now and then as a slow
disk would. Every ``--sample-s`` seconds a line shows the resident memory and the counters. At the end the
tool checks

- the stream's own accounting (:meth:`specgpu.pipeline.StreamReport.accounting`): frames in = into the ring +
  refused; into the ring = delivered + discarded; delivered = K x sequences + duplicates + unused; sequences
  out = sequences complete;
- exposures: every exposure the camera made (the driver's last frame id + 1) is a frame the assembler saw once
  or a gap it counted as dropped;
- the injected faults, recomputed from the fault schedule: the assembler counted at least the injected drops
  and at most those plus the ring's, and at most the injected duplicates;
- the sinks: each saw every sequence out, exactly once, in order;
- memory: the resident set after the warm-up may grow by at most ``--max-growth-mb`` (median of the last fifth
  of the samples against the first sample after the warm-up);

and exits 1 when one fails (2 for a bad argument), 0 when all hold.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from specgpu.calibration.bundle import oracle_calibration  # noqa: E402
from specgpu.capture.twin_driver import TwinDriver  # noqa: E402
from specgpu.pipeline import Sink, Stream
from specgpu.pipeline.stream_report import current_rss_bytes
from specgpu.planning import plan_tristimulus  # noqa: E402
from specgpu.rig.camera import CameraParameters  # noqa: E402
from specgpu.rig.config import RigDescription  # noqa: E402
from specgpu.rig.twin import FaultRates, FaultSchedule, TwinRig  # noqa: E402

MB = 1024 * 1024


class StallingSink(Sink):
    """Counts every result and checks they arrive once, in order; sleeps ``stall_s`` with probability ``rate``."""

    def __init__(self, rate: float, stall_s: float, seed: int):
        self.rng = np.random.default_rng(seed)
        self.rate, self.stall_s = rate, stall_s
        self.count, self.stalls, self.out_of_order, self.non_finite = 0, 0, 0, 0
        self.last_index = -1
        self.lock = threading.Lock()

    def write(self, result):
        with self.lock:
            if result.index <= self.last_index:
                self.out_of_order += 1
            self.last_index = result.index
            self.count += 1
            xyz = result.arrays.get("XYZ")
            if xyz is not None:  # NaN only where a frame saturated
                bad = int(np.count_nonzero(~np.isfinite(xyz).all(axis=-1)))
                self.non_finite += bad > result.saturated_pixels
            stall = self.rng.random() < self.rate
        if stall:
            self.stalls += 1
            time.sleep(self.stall_s)


def injected(schedule: FaultSchedule, last_frame_id: int) -> dict:
    """The faults the schedule put on exposures 0..last_frame_id."""
    counts = {"dropped": 0, "duplicated": 0, "missed_triggers": 0}
    for k in range(last_frame_id + 1):
        drop, dup, miss, _ = schedule.faults(k)
        counts["dropped"] += drop
        counts["duplicated"] += dup
        counts["missed_triggers"] += miss
    return counts


def parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=10.0, help="how long to stream (default 10)")
    p.add_argument("--fps", type=float, default=200.0, help="camera frame rate, frames/s (default 200)")
    p.add_argument("--width", type=int, default=320, help="camera ROI width (default 320)")
    p.add_argument("--height", type=int, default=240, help="camera ROI height (default 240)")
    p.add_argument("--drop-rate", type=float, default=0.002, help="per-frame probability of a lost frame")
    p.add_argument("--duplicate-rate", type=float, default=0.002, help="per-frame probability of a duplicate")
    p.add_argument("--missed-trigger-rate", type=float, default=0.001, help="per-frame probability of a missed "
                   "light trigger")
    p.add_argument("--stall-rate", type=float, default=0.01, help="per-result probability that the sink stalls")
    p.add_argument("--stall-ms", type=float, default=150.0, help="length of one stall (default 150 ms)")
    p.add_argument("--sample-s", type=float, default=None, help="seconds between RSS lines (default: 1/20 of the "
                   "run, at least 2)")
    p.add_argument("--warm-up-s", type=float, default=None, help="seconds before the RSS baseline (default: 1/10 "
                   "of the run, at least 5)")
    p.add_argument("--max-growth-mb", type=float, default=32.0, help="allowed RSS growth after the warm-up")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = p.parse_args(argv)
    for name in ("minutes", "fps", "stall_ms", "max_growth_mb"):
        value = getattr(args, name)
        if not np.isfinite(value) or value <= 0:
            p.error(f"--{name.replace('_', '-')} must be a finite number > 0, got {value}")
    for name in ("drop_rate", "duplicate_rate", "missed_trigger_rate", "stall_rate"):
        value = getattr(args, name)
        if not 0 <= value < 1:
            p.error(f"--{name.replace('_', '-')} must lie in [0, 1), got {value}")
    return args


def main(argv=None) -> int:
    args = parse(argv)
    seconds = args.minutes * 60.0
    sample_s = args.sample_s or max(2.0, seconds / 20)
    warm_up_s = args.warm_up_s if args.warm_up_s is not None else max(5.0, seconds / 10)

    period = 1.0 / args.fps
    desc = RigDescription(camera=CameraParameters(roi_width=args.width, roi_height=args.height,
                                                  frame_rate_hz=args.fps, exposure_s=0.5 * period))
    bundle = oracle_calibration(desc)
    light_switch = desc.light.switch_time_s
    plan = plan_tristimulus(bundle, max_exposure_s=period - light_switch - 2e-6)
    rig_desc = plan.rig_description(desc)
    schedule = FaultSchedule.from_rates(FaultRates(drop_rate=args.drop_rate, duplicate_rate=args.duplicate_rate,
                                                   missed_trigger_rate=args.missed_trigger_rate), seed=args.seed)
    driver = TwinDriver(TwinRig(rig_desc, scene="colorchecker"), patterns=plan.patterns, faults=schedule,
                        pacing="paced")
    sink = StallingSink(args.stall_rate, args.stall_ms / 1e3, args.seed)
    stream = Stream(driver, plan, bundle, outputs=("XYZ",), sinks=[sink], policy="drop_newest")
    fps = rig_desc.camera.frame_rate_hz
    print(f"soak: {args.minutes:g} min, {args.width} x {args.height} at {fps:.1f} fps, plan {plan.method} "
          f"(K = {plan.K}, exposure {plan.exposure_s * 1e3:.2f} ms); faults: drop {args.drop_rate}, duplicate "
          f"{args.duplicate_rate}, missed trigger {args.missed_trigger_rate}; sink stalls {args.stall_ms:g} ms "
          f"with probability {args.stall_rate}", flush=True)

    samples = []  # (t, rss bytes, status)
    t0 = time.perf_counter()
    next_sample = [0.0]

    def on_status(status):
        t = time.perf_counter() - t0
        if t < next_sample[0]:
            return
        next_sample[0] = t + sample_s
        rss = current_rss_bytes()
        samples.append((t, rss, dict(status)))
        print(f"t {t:7.1f} s  RSS {rss / MB:7.1f} MB  frames in {status['frames_in']:7d}  sequences out "
              f"{status['sequences_out']:6d}  dropped {status['assembler_dropped']:4d} "
              f"(ring {status['ring_dropped']:4d})"
              f"  discarded {status['discarded']:4d}  stalls {sink.stalls:4d}  latency {status['latency_ms']:6.1f} ms",
              flush=True)

    report = stream.run(seconds, on_status=on_status, status_interval_s=min(1.0, sample_s))
    rss_end = current_rss_bytes()
    samples.append((time.perf_counter() - t0, rss_end, {}))

    acc = report.accounting()
    a, r, end = report.assembly, report.ring, report.end
    faults = injected(schedule, end.last_frame_id)
    exposures = end.last_frame_id + 1
    seen_once = a.frames_received - a.duplicates - a.out_of_order
    after = [rss for t, rss, _ in samples if t >= warm_up_s and rss is not None]
    base = after[0] if after else None
    tail = after[-max(1, len(after) // 5):] if after else []
    growth = (float(np.median(tail)) - base) / MB if base is not None else float("nan")
    checks = {
        "stream accounting balanced": acc["balanced"],
        "exposures = frames seen once + frames counted dropped": seen_once + a.dropped == exposures,
        "frames in = exposures - injected drops + injected duplicates":
            report.frames_in == exposures - faults["dropped"] + faults["duplicated"],
        "injected drops <= assembler dropped <= injected + ring dropped":
            faults["dropped"] <= a.dropped <= faults["dropped"] + r.dropped,
        "assembler duplicates <= injected duplicates": a.duplicates <= faults["duplicated"],
        "sink saw every sequence once, in order": sink.count == report.sequences_out and sink.out_of_order == 0,
        "XYZ finite wherever no frame saturated": sink.non_finite == 0,
        "no sink error": not report.sink_errors,
        f"RSS growth after warm-up <= {args.max_growth_mb:g} MB": bool(np.isfinite(growth))
            and growth <= args.max_growth_mb,
    }
    print()
    print(f"{report.frames_in} frames in over {report.seconds:.1f} s ({report.frames_per_s:.1f}/s) from {exposures} "
          f"exposures; {report.sequences_out} sequences out ({report.sequences_per_s:.1f}/s); latency median "
          f"{report.latency_ms(50):.1f} ms, p99 {report.latency_ms(99):.1f} ms; "
          f"CPU {report.cpu_s / report.seconds:.2f} cores")
    print(f"injected: dropped {faults['dropped']}, duplicated {faults['duplicated']}, missed triggers "
          f"{faults['missed_triggers']}; the sink stalled {sink.stalls} times ({args.stall_ms:g} ms)")
    print(f"assembler: received {a.frames_received}, dropped {a.dropped}, duplicates {a.duplicates}, missed triggers "
          f"{a.missed_triggers}, sequences complete {a.sequences_complete}, discarded {a.sequences_discarded}, "
          f"frames unused {a.frames_unused}; ring: delivered {r.delivered}, dropped newest {r.dropped_newest}, "
          f"oldest {r.dropped_oldest}, high water {r.high_water}")
    print(f"RSS: start {samples[0][1] / MB:.1f} MB, after warm-up ({warm_up_s:g} s) "
          f"{base / MB if base else float('nan'):.1f}"
          f" MB, end {rss_end / MB:.1f} MB, peak {(report.peak_rss_bytes or 0) / MB:.1f} MB; growth after warm-up "
          f"{growth:+.1f} MB")
    for error in report.sink_errors:
        print(f"sink error: {error}")
    for name, ok in checks.items():
        print(f"  {'ok  ' if ok else 'FAIL'} {name}")
    if args.json:
        args.json.write_text(json.dumps({"report": report.as_dict(), "injected": faults, "exposures": exposures,
                                         "sink": {"count": sink.count, "stalls": sink.stalls},
                                         "rss_samples": [(t, rss) for t, rss, _ in samples],
                                         "rss_growth_mb": growth, "checks": checks}, indent=1, default=str))
    ok = all(checks.values())
    print("soak passed" if ok else "soak FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
