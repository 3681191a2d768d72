"""The outputs the stream bench's full-quality comparison streams: coefficients + XYZ + dE2000, with sigma_rms as
soon as the stream's decoder takes it with ``--motion global --denoise --white-roi``."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

import specgpu.apps.bench.stream as bench_stream


def _setup():
    return SimpleNamespace(frames=np.zeros((9, 24, 32), np.uint16), plan="plan", bundle="bundle", reference=None)


def test_sigma_rms_joins_where_the_decoder_takes_it(monkeypatch):
    seen = []

    def takes(plan, bundle, outputs, **kw):
        seen.append((outputs, kw["motion"], kw["denoise"], kw["white_roi"], kw["frame_shape"]))

    monkeypatch.setattr(bench_stream, "SequenceDecoder", takes)
    assert bench_stream.quality_outputs(_setup()) == ("coefficients", "XYZ", "dE", "sigma_rms")
    (outputs, motion, denoise, roi, shape), = seen
    assert outputs[-1] == "sigma_rms" and motion == "global" and denoise is not None and roi is not None
    assert shape == (24, 32)


def test_without_it_static_and_full_compare_the_three(monkeypatch):
    def refuses(plan, bundle, outputs, **kw):
        raise ValueError("--denoise filters the stream's coefficients, cube, XYZ outputs; sigma_rms cannot be "
                         "denoised in the stream")

    monkeypatch.setattr(bench_stream, "SequenceDecoder", refuses)
    assert bench_stream.quality_outputs(_setup()) == ("coefficients", "XYZ", "dE")
