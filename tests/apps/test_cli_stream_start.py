"""specgpu stream: a duration that cannot be honoured is refused up front, and a recording whose stream failed says
so (never "complete")."""

from __future__ import annotations

import pytest
from cli_helpers import one_line_error, run, stream_cli_files
from stream_helpers import shared_stream_setup

from specgpu.io.recording import open_recording


@pytest.fixture(scope="module")
def setup():
    return shared_stream_setup(320, 240, sequences=1, output_step_nm=10.0)


@pytest.mark.parametrize("seconds", ["1e308", "1e30", "31622401"])
def test_a_stream_longer_than_a_year_is_refused_before_any_work(setup, tmp_path, seconds):
    args = stream_cli_files(setup, tmp_path)
    result = run(*args, "--seconds", seconds, "--out", tmp_path / "rec.zarr", ok=False)
    one_line_error(result, "--seconds", "0<x<=31622400")
    assert not (tmp_path / "rec.zarr").exists()


def test_a_stream_that_fails_at_its_start_leaves_a_recording_marked_failed(setup, tmp_path, monkeypatch):
    """The camera fails before the first sequence: the command fails and its recording says ``failed`` with the
    reason and 0 sequences, never ``complete``."""
    import specgpu.pipeline.stream

    def camera_lost(driver, ring):
        raise OSError("camera lost at start")

    monkeypatch.setattr(specgpu.pipeline.stream, "run_producer", camera_lost)
    args = stream_cli_files(setup, tmp_path)
    result = run(*args, "--seconds", "2", "--out", tmp_path / "rec.zarr", "--frames", ok=False)
    one_line_error(result, "camera lost at start")
    rec = open_recording(tmp_path / "rec.zarr")
    assert rec.attrs["status"] == "failed" and rec.sequences == 0
    assert "camera lost at start" in rec.attrs["error"]
