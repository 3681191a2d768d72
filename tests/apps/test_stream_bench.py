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


def test_full_quality_is_run_beside_static_and_judged_by_their_ratio_and_paced_at_the_camera_rate(monkeypatch):
    """static and full run interleaved with the same outputs, full with --motion global --denoise --white-roi;
    their ratio is the median of the rounds' ratios against the 0.40 target; paced_full streams the full options
    at the camera's rate and passes only without a drop."""
    from stream_helpers import shared_stream_setup

    import specgpu.apps.bench.stream as bench_stream

    def shared(width, height, *, white_tile, progress):  # the session's recording with the white tile
        return shared_stream_setup(width, height, sequences=2, white_tile=white_tile)

    monkeypatch.setattr(bench_stream, "stream_setup", shared)
    report = run_stream_bench(seconds=0.25, paced_seconds=0.5, width=320, height=240, rounds=2, echo=None,
                              cases=("static", "full", "paced_full"), progress=False)
    rows = {row["case"].split(":")[0]: row for row in report["cases"]}
    assert set(rows) == {"static", "full", "full / static", "paced_full 5 ms period"}
    ratio = rows["full / static"]
    assert ratio["static_frames_per_s"] == rows["static"]["frames_per_s"] > 0
    assert ratio["full_frames_per_s"] == rows["full"]["frames_per_s"] > 0
    rounds = [f / s for f, s in zip(rows["full"]["frames_per_s_rounds"], rows["static"]["frames_per_s_rounds"])]
    assert sorted(ratio["ratio_rounds"]) == pytest.approx(sorted(rounds))
    assert ratio["ratio"] == pytest.approx(sum(rounds) / 2) and ratio["passed"] == (ratio["ratio"] >= 0.40)
    paced = rows["paced_full 5 ms period"]
    assert paced["sequences_out"] > 0
    assert paced["passed"] == (paced["ring"]["dropped"] == 0 and paced["assembly"]["dropped"] == 0)
