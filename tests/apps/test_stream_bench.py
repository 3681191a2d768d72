"""specgpu bench --stream: its set-up (a minute at 640 x 480) says on stderr what it is doing."""

from __future__ import annotations

import pytest

import specgpu.testing
from specgpu.apps.stream_bench import run_stream_bench


class Stop(Exception):
    """Raised in place of the twin's calibration: the set-up's first step, reached without waiting for it."""


def stop_at_calibration(*_args, **_kwargs):
    raise Stop


@pytest.mark.parametrize("progress", [True, False])
def test_the_setup_names_its_first_step_on_stderr_before_it_runs(monkeypatch, capsys, progress):
    monkeypatch.setattr(specgpu.testing, "calibrate", stop_at_calibration)
    printed = []
    with pytest.raises(Stop):
        run_stream_bench(width=320, height=240, cases=("equality",), echo=printed.append, progress=progress)
    err = capsys.readouterr().err
    line = "stream bench: calibrating the twin at 320 x 240, 200 frames/s (both feedback loops) ...\n"
    assert err == (line if progress else "")
    assert printed == []  # the report (stdout) holds figures only
