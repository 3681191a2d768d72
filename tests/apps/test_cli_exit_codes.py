"""One exit rule for every command: 0 done, 2 a usage error (a typo in a choice value included), 1 any other
failure, 130 interrupted, with one line saying what was kept ("specgpu: interrupted; kept ..." or "...; nothing
written"). Ctrl-C is simulated by the function each command does its work with raising KeyboardInterrupt, and by
a real SIGINT to a streaming process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_helpers import RIG, one_line_error, python_path, run

ROOT = Path(__file__).resolve().parents[2]
NOTHING = "specgpu: interrupted; nothing written"


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A small twin, its calibration, a Hadamard plan, a capture of one sequence and the cube recovered from it."""
    from specgpu.calibration.bundle import oracle_calibration, save_calibration
    from specgpu.rig.config import load_rig

    d = tmp_path_factory.mktemp("exits")
    (d / "rig.toml").write_text(RIG)
    save_calibration(d / "calib.npz", oracle_calibration(load_rig(d / "rig.toml")))
    run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out",
        d / "plan.npz", "--no-ambient")
    run("capture", "--rig", d / "rig.toml", "--plan", d / "plan.npz", "--calib", d / "calib.npz", "--out",
        d / "seq", "--sequences", "1", "--seed", "2")
    run("recover", d / "seq", "--out", d / "cube.npz")
    (d / "bad.toml").write_text("[camera\n")
    (d / "junk.npz").write_bytes(b"not a table")
    (d / "empty").mkdir()
    return d


def rig_plan(d):
    return ["--rig", d / "rig.toml", "--plan", d / "plan.npz", "--calib", d / "calib.npz"]


# ---- usage errors: 2 ------------------------------------------------------------------------------------
USAGE = {
    "plan-method-typo": lambda d, o: ["plan", "symetric", "--calib", d / "calib.npz", "--out", o],
    "plan-illuminant-typo": lambda d, o: ["plan", "tristimulus", "--illuminant", "D56", "--calib", d / "calib.npz",
                                          "--out", o],
    "plan-camera-typo": lambda d, o: ["plan", "camera", "--camera", "Nikon", "--calib", d / "calib.npz", "--out",
                                      o],
    "recover-method-typo": lambda d, o: ["recover", d / "seq", "--out", o, "--method", "CIE 200"],
    "recover-observer-typo": lambda d, o: ["recover", d / "seq", "--out", o, "--observer", "CIE 2 deg"],
    "evaluate-illuminant-typo": lambda d, o: ["evaluate", d / "cube.npz", "--truth", "colorchecker",
                                              "--illuminant", "D56", "--json", o],
    "evaluate-scene-typo": lambda d, o: ["evaluate", d / "cube.npz", "--truth", "colorchekcer", "--json", o],
    "capture-scene-typo": lambda d, o: ["capture", *rig_plan(d), "--scene", "colorchekcer", "--out", o],
    "stream-method-typo": lambda d, o: ["stream", *rig_plan(d), "--seconds", "0.2", "--method", "CIE 200",
                                        "--out", o],
    "stream-output-typo": lambda d, o: ["stream", *rig_plan(d), "--seconds", "0.2", "--outputs", "cub", "--out", o],
    "batch-output-typo": lambda d, o: ["batch", d / "seq", "--plan", d / "plan.npz", "--outputs", "cub", "--out",
                                       o],
    "calibrate-line-shape-typo": lambda d, o: ["calibrate", "--rig", d / "rig.toml", "--line-shape", "gausian",
                                               "--out", o],
    "bench-case-typo": lambda d, o: ["bench", "--stream", "--stream-cases", "fusd", "--json", o],
    "bench-size": lambda d, o: ["bench", "--sizes", "64y48", "--json", o],
    "bound-frames": lambda d, o: ["bound", "--frames", "0", "--sequence-ms", "50"],
    "demo-draws": lambda d, o: ["demo", "--draws", "0", "--out", o],
    "report-no-folder": lambda d, o: ["report", d / "nowhere", "--out", o],
    "salvage-no-folder": lambda d, o: ["salvage", d / "nowhere"],
    "view-no-path": lambda d, o: ["view", d / "nowhere"],
    "info-bad-option": lambda d, o: ["info", "--bogus"],
    "selftest-bad-option": lambda d, o: ["selftest", "--bogus"],
}


@pytest.mark.parametrize("case", sorted(USAGE))
def test_a_usage_error_exits_2_in_one_line_writing_nothing(made, tmp_path, case):
    out = tmp_path / "out"
    result = run(*USAGE[case](made, out), ok=False)
    one_line_error(result, code=2)
    assert not out.exists()


# ---- failures: 1 ----------------------------------------------------------------------------------------
FAILURE = {
    "calibrate-bad-rig": lambda d, o: ["calibrate", "--rig", d / "bad.toml", "--out", o],
    "plan-corrupt-calibration": lambda d, o: ["plan", "symmetric", "--calib", d / "junk.npz", "--out", o],
    "capture-corrupt-plan": lambda d, o: ["capture", "--rig", d / "rig.toml", "--plan", d / "junk.npz", "--calib",
                                          d / "calib.npz", "--out", o],
    "stream-corrupt-plan": lambda d, o: ["stream", "--rig", d / "rig.toml", "--plan", d / "junk.npz", "--calib",
                                         d / "calib.npz", "--seconds", "0.2", "--out", o],
    "recover-no-capture": lambda d, o: ["recover", d / "empty", "--out", o],
    "evaluate-corrupt-cube": lambda d, o: ["evaluate", d / "junk.npz", "--truth", "colorchecker", "--json", o],
    "report-no-capture": lambda d, o: ["report", d / "empty", "--out", o],
    "batch-no-capture": lambda d, o: ["batch", d / "empty", "--plan", d / "plan.npz", "--calib", d / "calib.npz",
                                      "--out", o],
    "salvage-no-journal": lambda d, o: ["salvage", d / "empty"],
    "demo-bad-rig": lambda d, o: ["demo", "--rig", d / "bad.toml", "--out", o],
}


@pytest.mark.parametrize("case", sorted(FAILURE))
def test_a_failure_exits_1_in_one_line_writing_nothing(made, tmp_path, case):
    out = tmp_path / "out"
    result = run(*FAILURE[case](made, out), ok=False)
    one_line_error(result, code=1)
    assert not out.exists()


# ---- interrupted: 130, saying what was kept ---------------------------------------------------------------
def interrupt(*args, **kwargs):
    raise KeyboardInterrupt


INTERRUPTED = {  # the command, and the function it does its work with (patched where the command looks it up)
    "calibrate": ("specgpu.apps.cli.calibrate.calibrate_on_rig",
                  lambda d, o: ["calibrate", "--rig", d / "rig.toml", "--out", o]),
    "plan": ("specgpu.apps.cli.plan.estimated_plan",
             lambda d, o: ["plan", "symmetric", "--calib", d / "calib.npz", "--out", o]),
    "capture": ("specgpu.pipeline.acquire.capture_into", lambda d, o: ["capture", *rig_plan(d), "--out", o]),
    "recover": ("specgpu.pipeline.recovery.recover", lambda d, o: ["recover", d / "seq", "--out", o]),
    "evaluate": ("specgpu.apps.cli.evaluate.evaluation_report",
                 lambda d, o: ["evaluate", d / "cube.npz", "--truth", "colorchecker", "--json", o]),
    "report": ("specgpu.apps.cli.report.report_folder", lambda d, o: ["report", d / "seq", "--out", o]),
    "stream": ("specgpu.apps.cli.stream.open_rig_driver",
               lambda d, o: ["stream", *rig_plan(d), "--seconds", "0.2", "--out", o]),
    "batch": ("specgpu.apps.cli.batch.run_batch",
              lambda d, o: ["batch", d / "seq", "--plan", d / "plan.npz", "--out", o]),
    "demo": ("specgpu.apps.cli.demo.run_demo", lambda d, o: ["demo", "--rig", d / "rig.toml", "--out", o]),
    "bench": ("specgpu.apps.cli.bench.run_bench", lambda d, o: ["bench", "--sizes", "320x240", "--json", o]),
    "bound": ("specgpu.apps.cli.bound.requested_bound", lambda d, o: ["bound", "--frames", "3", "--sequence-ms",
                                                                     "50"]),
    "salvage": ("specgpu.apps.cli.capture.salvage_capture", lambda d, o: ["salvage", d / "empty"]),
    "selftest": ("specgpu.apps.cli.info.run_selftest", lambda d, o: ["selftest"]),
    "info": ("specgpu.apps.cli.info.describe", lambda d, o: ["info"]),
}


@pytest.mark.parametrize("case", sorted(INTERRUPTED))
def test_an_interrupt_exits_130_saying_nothing_was_written(made, tmp_path, monkeypatch, case):
    target, args = INTERRUPTED[case]
    monkeypatch.setattr(target, interrupt)
    out = tmp_path / "out"
    result = run(*args(made, out), ok=False)
    assert result.exit_code == 130, result.output
    assert result.output.strip().splitlines()[-1] == NOTHING, result.output
    assert not out.exists()


def test_recover_interrupted_once_its_outputs_are_written_says_it_kept_them(made, tmp_path, monkeypatch):
    import specgpu.apps.cli.recover as cli_recover

    class Late(cli_recover.Staged):
        def commit(self):
            super().commit()
            raise KeyboardInterrupt  # as a Ctrl-C held back during the renames lands once they are done

    monkeypatch.setattr(cli_recover, "Staged", Late)
    result = run("recover", made / "seq", "--out", tmp_path / "c.npz", "--xyz", tmp_path / "x.exr", ok=False)
    assert result.exit_code == 130, result.output
    assert result.output.strip().splitlines()[-1] == \
        f"specgpu: interrupted; kept {tmp_path / 'c.npz'}; {tmp_path / 'x.exr'}", result.output
    assert (tmp_path / "c.npz").is_file() and (tmp_path / "x.exr").is_file()


def test_salvage_interrupted_once_its_index_is_written_says_it_kept_it(tmp_path, monkeypatch):
    import specgpu.apps.cli.capture as cli_capture

    def indexed_then_interrupted(seq):
        (Path(seq) / "sequence.json").write_text("{}")  # the index in place, then Ctrl-C
        raise KeyboardInterrupt

    (tmp_path / "seq").mkdir()
    monkeypatch.setattr(cli_capture, "salvage_capture", indexed_then_interrupted)
    result = run("salvage", tmp_path / "seq", ok=False)
    assert result.exit_code == 130, result.output
    assert result.output.strip().splitlines()[-1] == \
        f"specgpu: interrupted; kept {tmp_path / 'seq' / 'sequence.json'}", result.output


def test_capture_interrupted_after_two_sequences_says_it_kept_them(made, tmp_path, monkeypatch):
    import specgpu.pipeline.twin_capture as pipeline

    real = pipeline.capture_plan

    def stopping(*args, on_sequence, **kwargs):
        seen = []

        def each(sequence):
            on_sequence(sequence)
            seen.append(sequence)
            if len(seen) == 2:
                raise KeyboardInterrupt
        return real(*args, on_sequence=each, **kwargs)

    monkeypatch.setattr(pipeline, "capture_plan", stopping)
    out = tmp_path / "s"
    result = run("capture", *rig_plan(made), "--out", out, "--sequences", "4", ok=False)
    assert result.exit_code == 130, result.output
    assert result.output.strip().splitlines()[-1] == f"specgpu: interrupted; kept 2 of 4 sequences in {out}"
    run("recover", out, "--sequence", "1", "--out", tmp_path / "c.npz")


def test_stream_interrupted_drains_then_exits_130_saying_what_it_recorded(made, tmp_path, monkeypatch):
    import specgpu.apps.cli.stream as cli_stream
    from specgpu.io import open_recording

    def status(s, tty):
        if s["sequences_out"] >= 2:
            raise KeyboardInterrupt  # Ctrl-C, on the thread that runs the stream

    monkeypatch.setattr(cli_stream, "status_line", status)
    out = tmp_path / "rec.zarr"
    result = run("stream", *rig_plan(made), "--seconds", "60", "--pacing", "free", "--out", out, ok=False)
    assert result.exit_code == 130, result.output
    kept = open_recording(out).sequences
    assert kept >= 2
    assert result.output.strip().splitlines()[-1] == \
        f"specgpu: interrupted; kept {kept} complete sequences in {out}", result.output


def test_a_sigint_to_a_streaming_process_exits_130_saying_what_it_recorded(made, tmp_path):
    out = tmp_path / "rec.zarr"
    env = {**os.environ, "PYTHONPATH": python_path(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "specgpu", "stream", *map(str, rig_plan(made)), "--seconds",
                             "120", "--pacing", "free", "--out", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # the status line counts sequences out
            line = proc.stderr.readline()
            if "sequences out" in line and "sequences out 0," not in line:
                break
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert "specgpu: interrupted; kept " in stderr.strip().splitlines()[-1] and str(out) in stderr, stderr
