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
