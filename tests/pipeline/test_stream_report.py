"""The stream's report pieces: the fixed-memory latency histogram's quantiles and the process memory probes."""

from __future__ import annotations

import math

import numpy as np

from specgpu.pipeline.stream_report import LatencyHistogram, current_rss_bytes, peak_rss_bytes


def test_latency_quantiles_are_within_one_bin_of_the_exact_ones():
    values = np.random.default_rng(0).lognormal(np.log(2e-3), 0.5, 5000)
    hist = LatencyHistogram()
    before = hist.nbytes
    for v in values:
        hist.add(v)
    assert hist.nbytes == before  # fixed memory, whatever the count
    assert hist.count == 5000 and math.isclose(hist.mean, values.mean(), rel_tol=1e-12)
    bound = 10 ** (0.5 / hist.per_decade) - 1
    for q in (0.5, 0.9, 0.99):
        exact = np.quantile(values, q)
        assert abs(hist.quantile(q) / exact - 1) <= bound + 2e-3  # the bin's half width, plus the rank's step
    assert hist.quantile(0) == values.min() and hist.quantile(1) == values.max()
    assert len(hist.recent) == 64 and hist.recent[-1] == values[-1]


def test_an_empty_histogram_says_nan():
    hist = LatencyHistogram()
    assert math.isnan(hist.mean) and math.isnan(hist.quantile(0.5))


def test_memory_probes_report_the_process():
    now, peak = current_rss_bytes(), peak_rss_bytes()
    assert peak is not None and peak > 0
    assert now is None or 0 < now <= peak


def test_a_source_below_the_plan_s_frame_rate_is_behind():
    """Measured by frame id between two arrivals (a frame lost on the way is a drop, not a slower source); behind
    below 95 % of the plan's rate, said with both rates in the summary."""
    from specgpu.capture.assemble import AssemblyStats
    from specgpu.capture.driver import StreamEnd
    from specgpu.capture.ringbuffer import RingStats
    from specgpu.pipeline.live import stream_summary
    from specgpu.pipeline.stream import frame_rate
    from specgpu.pipeline.stream_report import StreamReport

    assert frame_rate((0, 10.0), (90, 11.0)) == 90.0
    assert frame_rate((0, 10.0), (0, 11.0)) is None and frame_rate(None, (9, 1.0)) is None
    assert frame_rate((0, 10.0), (10, 11.0), least_frames=16) is None

    def report(rate):
        return StreamReport(frames_in=90, sequences_out=10, ring=RingStats(*[0] * 10), assembly=AssemblyStats(),
                            end=StreamEnd(89, 8), seconds=1.0, latency=LatencyHistogram(), cpu_s=0.5,
                            peak_rss_bytes=None, interrupted=False, frame_rate_hz=rate, plan_frame_rate_hz=150.0)

    assert not report(149.0).behind and not report(143.0).behind and not report(None).behind
    slow = report(56.0)
    assert slow.behind and slow.as_dict()["behind"]
    assert "behind the plan: frames delivered at 56/s, the plan's rate is 150/s" in stream_summary(slow)
    assert "behind" not in stream_summary(report(149.0))
