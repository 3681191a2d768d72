"""specgpu bench --stream: its set-up (a minute at 640 x 480) says on stderr what it is doing."""

from __future__ import annotations

import pytest

import specgpu.pipeline.twin_replay
from specgpu.apps.bench.stream import STREAM_TARGETS, run_stream_bench, stream_targets


class Stop(Exception):
    """Raised in place of the twin's calibration: the set-up's first step, reached without waiting for it."""


def stop_at_calibration(*_args, **_kwargs):
    raise Stop


@pytest.mark.parametrize("progress", [True, False])
def test_the_setup_names_its_first_step_on_stderr_before_it_runs(monkeypatch, capsys, progress):
    monkeypatch.setattr(specgpu.pipeline.twin_replay, "calibrate", stop_at_calibration)
    printed = []
    with pytest.raises(Stop):
        run_stream_bench(width=320, height=240, cases=("equality",), echo=printed.append, progress=progress)
    err = capsys.readouterr().err
    line = "stream bench: calibrating the twin at 320 x 240, 200 frames/s (both feedback loops) ...\n"
    assert err == (line if progress else "")
    assert printed == []  # the report (stdout) holds figures only


def test_stream_rate_targets_are_judged_at_640_x_480_only():
    assert stream_targets(640, 480) == STREAM_TARGETS and stream_targets(640, 480) is not STREAM_TARGETS
    assert stream_targets(2048, 2048) == {} and stream_targets(480, 640) == {} and stream_targets(320, 240) == {}
