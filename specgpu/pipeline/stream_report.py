"""What a finished stream reports: :class:`StreamReport` (counters, rates, latency and memory), the fixed-size
:class:`LatencyHistogram` it measures latency with, and the /proc probes of the process's memory.
"""

from __future__ import annotations

import resource
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from specgpu.capture.assemble import AssemblyStats
from specgpu.capture.driver import StreamEnd
from specgpu.capture.ringbuffer import RingStats

__all__ = ["BEHIND", "LatencyHistogram", "StreamReport", "current_rss_bytes", "peak_rss_bytes", "peak_rss_reset"]

#: A source delivering below this fraction of the plan's frame rate is behind it (a paced source keeps within a
#: percent of it; a twin that cannot render at the plan's rate falls far below).
BEHIND = 0.95


# ------------------------------------------------------------------------------------------------------ report


@dataclass
class StreamReport:
    """Counters and timings of a finished stream.

    Attributes
    ----------
    frames_in : int
        Frames the driver delivered (into the ring or refused by it).
    sequences_out : int
        Results handed to the sinks.
    ring, assembly : RingStats, AssemblyStats
        The frame ring's and the assembler's exact counters.
    end : StreamEnd
        The driver's last exposure.
    seconds : float
        Wall time from the first frame requested to the last result written.
    latency : LatencyHistogram
        Per result, arrival of the last frame -> result ready (see :class:`StreamResult`): exact count, mean,
        min and max, quantiles to 0.6 % (a bounded histogram: a day's stream holds no list of latencies).
    cpu_s : float
        Process CPU time (user + system) over the run, s.
    peak_rss_bytes : int or None
        Peak resident memory during the run (``VmHWM`` after a reset, else the process's lifetime peak).
    interrupted : bool
        The run ended by :meth:`Stream.stop` or Ctrl-C rather than by time or the end of the driver's stream.
    sink_errors : list of str
        One line per failed sink that is not optional, naming it (the capture stops at the first one).
    rss_start_bytes : int or None
        Resident memory when the stream started (what the process held before: the peak minus this is the
        stream's own).
    sinks_stopped : list of str
        One line per optional sink (EXR snapshots, preview, view) that failed and was stopped while the stream
        went on, naming it and the reason.
    frame_rate_hz : float or None
        The rate the source delivered frames at, frames/s, by frame id from the first frame to the last.
    plan_frame_rate_hz : float or None
        The rate the plan's frames are meant to come at (see :attr:`behind`).
    """

    frames_in: int
    sequences_out: int
    ring: RingStats
    assembly: AssemblyStats
    end: StreamEnd
    seconds: float
    latency: "LatencyHistogram"
    cpu_s: float
    peak_rss_bytes: int | None
    interrupted: bool
    sink_errors: list = field(default_factory=list)
    rss_start_bytes: int | None = None
    sinks_stopped: list = field(default_factory=list)
    frame_rate_hz: float | None = None
    plan_frame_rate_hz: float | None = None

    @property
    def behind(self) -> bool:
        """The source delivered below :data:`BEHIND` of the plan's frame rate: the stream ran slower than the
        plan, whatever the drop counters say (a twin that renders late drops nothing, it is only late)."""
        return (self.frame_rate_hz is not None and self.plan_frame_rate_hz is not None
                and self.frame_rate_hz < BEHIND * self.plan_frame_rate_hz)

    @property
    def frames_per_s(self) -> float:
        return self.frames_in / self.seconds if self.seconds > 0 else 0.0

    @property
    def sequences_per_s(self) -> float:
        return self.sequences_out / self.seconds if self.seconds > 0 else 0.0

    def latency_ms(self, q: float) -> float:
        return self.latency.quantile(q / 100.0) * 1e3

    def accounting(self) -> dict:
        """Where every frame went; ``balanced`` is True when the identities hold exactly:

        - frames in = into the ring + refused by a full ring;
        - into the ring = handed to the assembler + discarded unread by the ring (drop_oldest);
        - handed to the assembler = K x sequences + duplicates + out of order + unused (incomplete sequences);
        - sequences out = sequences complete.
        """
        r, a = self.ring, self.assembly
        k = None
        if a.sequences_complete:
            k = (a.frames_received - a.duplicates - a.out_of_order - a.frames_unused) / a.sequences_complete
        checks = [
            self.frames_in == r.finalized + r.dropped_newest,
            r.finalized == r.delivered + r.dropped_oldest + r.pending,
            r.pending == 0,
            a.frames_received == r.delivered,
            self.sequences_out == a.sequences_complete,
        ]
        return {"frames_in": self.frames_in, "ring_dropped": r.dropped, "assembler_dropped": a.dropped,
                "frames_in_sequences": a.frames_received - a.duplicates - a.out_of_order - a.frames_unused,
                "frames_per_sequence": k, "frames_unused": a.frames_unused, "duplicates": a.duplicates,
                "missed_triggers": a.missed_triggers, "sequences_discarded": a.sequences_discarded,
                "sequences_out": self.sequences_out, "balanced": all(checks)}

    def as_dict(self) -> dict:
        return {"frames_in": self.frames_in, "sequences_out": self.sequences_out, "seconds": self.seconds,
                "frames_per_s": self.frames_per_s, "sequences_per_s": self.sequences_per_s,
                "latency_ms_median": self.latency_ms(50), "latency_ms_p99": self.latency_ms(99),
                "latency_ms_max": self.latency.max * 1e3 if self.latency.count else float("nan"),
                "latencies_counted": self.latency.count,
                "cpu_s": self.cpu_s, "cpu_cores": self.cpu_s / self.seconds if self.seconds else 0.0,
                "peak_rss_bytes": self.peak_rss_bytes, "rss_start_bytes": self.rss_start_bytes,
                "interrupted": self.interrupted,
                "ring": {**{k: getattr(self.ring, k) for k in self.ring.__dataclass_fields__},
                         "dropped": self.ring.dropped},
                "assembly": self.assembly.as_dict(), "accounting": self.accounting(),
                "sink_errors": list(self.sink_errors), "sinks_stopped": list(self.sinks_stopped),
                "frame_rate_hz": self.frame_rate_hz, "plan_frame_rate_hz": self.plan_frame_rate_hz,
                "behind": self.behind}


class LatencyHistogram:
    """Latencies of a stream of any length in fixed memory: exact count, sum, min and max, a histogram on
    logarithmic bins (``bins_per_decade`` from ``low_s`` to ``high_s``; values beyond go to the end bins) for
    quantiles, and the latest ``recent`` values for a live status. A quantile is the geometric centre of its
    bin, clamped to [min, max]: within ``10 ** (0.5 / bins_per_decade) - 1`` (0.6 % at 200) of the exact one.
    """

    def __init__(self, low_s: float = 1e-6, high_s: float = 1e3, bins_per_decade: int = 200, recent: int = 64):
        self.low, self.per_decade = float(low_s), int(bins_per_decade)
        self.bins = int(np.ceil(np.log10(high_s / low_s) * self.per_decade))
        self.counts = np.zeros(self.bins, np.int64)
        self.count = 0
        self.total = 0.0
        self.min = float("inf")
        self.max = float("-inf")
        self.recent: deque = deque(maxlen=int(recent))

    def add(self, value_s: float) -> None:
        v = float(value_s)
        i = int(np.floor(np.log10(max(v, self.low) / self.low) * self.per_decade))
        self.counts[min(max(i, 0), self.bins - 1)] += 1
        self.count += 1
        self.total += v
        self.min = min(self.min, v)
        self.max = max(self.max, v)
        self.recent.append(v)

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else float("nan")

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0 <= q <= 1) in seconds (NaN when empty)."""
        if not self.count:
            return float("nan")
        if q <= 0:
            return self.min
        if q >= 1:
            return self.max
        i = int(np.searchsorted(np.cumsum(self.counts), q * self.count, side="left"))
        centre = self.low * 10 ** ((i + 0.5) / self.per_decade)
        return float(min(max(centre, self.min), self.max))

    @property
    def nbytes(self) -> int:
        """Memory the structure holds, bytes (fixed: independent of the count)."""
        return int(self.counts.nbytes + 8 * self.recent.maxlen)


def peak_rss_reset() -> bool:
    """Reset the kernel's peak-RSS mark of this process (Linux ``clear_refs`` 5); False where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _status_kib(field_name: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field_name + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def current_rss_bytes() -> int | None:
    """Resident set size of this process now, bytes (None where /proc is absent)."""
    return _status_kib("VmRSS")


def peak_rss_bytes() -> int | None:
    """Peak resident set size of this process since start or the last :func:`peak_rss_reset`, bytes."""
    peak = _status_kib("VmHWM")
    return peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


