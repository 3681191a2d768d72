"""Fixtures of the apps tests."""

import pytest
from estimator_helpers import bundle, prior, spectra  # noqa: F401 (the estimator tests' module-scoped fixtures)


@pytest.fixture(scope="session")
def default_zarr(tmp_path_factory):
    """(setup, recording, batch output): 3 sequences of the stream's default outputs (coefficients, XYZ, dE) with
    their raw frames, and a batch output of them (cube, XYZ, dE) with sequences 0 and 2 computed, 1 not."""
    from zarr_helpers import batch_output, default_recording

    root = tmp_path_factory.mktemp("default-zarr")
    setup, rec = default_recording(root, frames=True)
    return setup, rec, batch_output(setup, rec, root / "out.zarr", [0, 2])



@pytest.fixture
def bench_on_the_shared_recording(monkeypatch):
    """``specgpu bench --stream`` streams the session's shared twin recording (2 sequences of it, with the white
    tile the bench asks for) instead of calibrating the twin and recording the chart again for each test."""
    from stream_helpers import shared_stream_setup

    import specgpu.apps.bench.stream as bench_stream

    def shared(width, height, *, white_tile, progress):
        return shared_stream_setup(width, height, sequences=2, white_tile=white_tile)

    monkeypatch.setattr(bench_stream, "stream_setup", shared)
