"""Crash drills: ``kill -9`` of calibrate, capture, recover and stream at a
hypothesis-chosen moment of their work, as real subprocesses (``python -m specgpu``).

Afterwards nothing at a final path looks complete unless it is (it reads back whole), a second writer meanwhile is
refused in one line naming the killed process, and the next run into the same output either completes or refuses
in one line; it clears the stale lock and the killed run's temporary files. A SIGTERM makes a stream drain.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import one_line_error, python_path, run, tristimulus_rig
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.core.locks import lock_path
from specgpu.io.recording import open_recording

ROOT = Path(__file__).resolve().parents[2]
# no shrinking: each example is a subprocess killed at a time, and a failure is reported as found
DRILL = settings(max_examples=2, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
DELAY = st.floats(min_value=0.0, max_value=1.5)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tristimulus_rig(tmp_path_factory.mktemp("drill"))
    run("capture", "--rig", d / "rig.toml", "--plan", d / "tri.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", d / "seq", "--sequences", "4", "--seed", "1")
    return d


def start(*args) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=python_path(ROOT))
    return subprocess.Popen([sys.executable, "-m", "specgpu", *map(str, args)], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def kill_during(proc: subprocess.Popen, target: Path, delay: float, second_writer=None) -> bool:
    """Wait until ``proc`` holds the lock of ``target`` (its work has begun), try ``second_writer`` (it must be
    refused naming the pid), wait ``delay`` s more and kill -9 it. Returns whether it was still running."""
    lock = lock_path(target)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if lock.read_text().strip() == str(proc.pid):
                break
        except OSError:
            pass
        time.sleep(0.02)
    assert proc.poll() is None or proc.returncode == 0, proc.stderr.read()
    if proc.poll() is None and second_writer is not None:
        error = one_line_error(second_writer())
        assert f"pid {proc.pid}" in error, error
    time.sleep(delay)
    alive = proc.poll() is None
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    return alive


def leftovers(folder: Path) -> list[str]:
    """Hidden temporaries and locks specgpu writes (``.<name>.<pid>.<random>.tmp*``, ``.<name>.lock``)."""
    return sorted(p.name for p in folder.rglob(".*") if ".tmp" in p.name or p.name.endswith(".lock"))


@DRILL
@given(delay=DELAY)
def test_kill_calibrate(base, delay):
    d = Path(tempfile.mkdtemp(dir=base))
    out = d / "c.npz"
    kill_during(start("calibrate", "--rig", base / "rig.toml", "--out", out), out, delay,
                lambda: run("calibrate", "--rig", base / "rig.toml", "--out", out, ok=False))
    if out.exists():  # only ever a whole bundle
        from specgpu.calibration.bundle import load_calibration

        load_calibration(out)
    run("calibrate", "--rig", base / "rig.toml", "--out", out)  # the next run completes
    assert leftovers(d) == []
    shutil.rmtree(d)


@DRILL
@given(delay=DELAY)
def test_kill_capture(base, delay):
    d = Path(tempfile.mkdtemp(dir=base))
    out = d / "seq"
    args = ("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
            "--scene", "colorchecker", "--out", out, "--sequences", "12")
    kill_during(start(*args), out, delay, lambda: run(*args, ok=False))
    result = run("recover", out, "--out", d / "r.exr", ok=False)
    if (out / io.SEQUENCE_FILE).exists():  # it finished: complete and recoverable
        assert result.exit_code == 0, result.output
        again = one_line_error(run(*args, ok=False))
        assert "already holds" in again
    else:  # interrupted: refused in one line; its journaled sequences are salvaged, else the next capture replaces it
        assert "interrupted" in one_line_error(result) or not out.exists()
        salvaged = run("salvage", out, ok=False) if out.exists() else None
        if salvaged is not None and salvaged.exit_code == 0:
            meta = io.read_sequence_header(out)[1]["metadata"]
            assert 1 <= meta["salvaged"]["sequences"] <= 12
            frames, _, _ = io.read_sequence(out)  # every salvaged frame matches its checksum
            assert frames.shape[0] == meta["salvaged"]["sequences"] * meta["K"]
            run("recover", out, "--out", d / "r.exr")
        else:  # killed before a sequence was complete: nothing to keep, refused in one line
            assert salvaged is None or "salvage" in one_line_error(salvaged) or "missing" in salvaged.output
            run(*args)
            run("recover", out, "--out", d / "r.exr")
    assert leftovers(d) == []
    shutil.rmtree(d)


@DRILL
@given(delay=DELAY)
def test_kill_recover(base, delay):
    d = Path(tempfile.mkdtemp(dir=base))
    outs = [d / "r.exr", d / "x.exr", d / "l.exr"]
    args = ("recover", base / "seq", "--out", outs[0], "--xyz", outs[1], "--lab", outs[2])
    kill_during(start(*args), outs[0], delay, lambda: run(*args, ok=False))
    for path in outs:  # whatever is there reads back whole
        if path.exists():
            io.read_map(path)
    run(*args)
    assert leftovers(d) == []
    shutil.rmtree(d)


@settings(max_examples=1, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(delay=st.floats(min_value=0.5, max_value=2.0))
def test_kill_stream(base, delay):
    d = Path(tempfile.mkdtemp(dir=base))
    out = d / "ss"
    args = ("stream", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
            "--scene", "colorchecker", "--seconds", "30", "--outputs", "XYZ", "--pacing", "free", "--out", out)
    kill_during(start(*args), out, delay, lambda: run(*args, ok=False))
    if (out / "zarr.json").exists():  # what the recording committed reads back whole
        rec = open_recording(out)
        for i in range(rec.sequences):
            assert np.isfinite(rec.read("XYZ", i)).any()
    # the next stream is not blocked by the dead one's lock: it records or refuses in one line
    result = run(*args[:-4], "--seconds", "0.5", "--outputs", "XYZ", "--pacing", "free", "--out", out, ok=False)
    if result.exit_code:
        assert "being written" not in one_line_error(result)
    assert not lock_path(out).exists()
    shutil.rmtree(d)


def test_sigterm_drains_a_stream(base, tmp_path):
    out = tmp_path / "ss"
    proc = start("stream", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
                 "--scene", "colorchecker", "--seconds", "60", "--outputs", "XYZ", "--pacing", "free", "--out", out)
    lock = lock_path(out)

    def committed():
        try:
            return open_recording(out).sequences
        except (OSError, ValueError):  # not created yet, or its group being written
            return 0

    # the signal comes once a sequence is committed (a fixed wait is too short on a loaded machine), so what the
    # drain must keep is known to exist
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and committed() == 0:
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    assert proc.returncode == 130, err  # interrupted, saying what it kept
    kept = open_recording(out).sequences
    assert kept > 0  # drained and closed: every sequence it took is committed
    assert err.strip().splitlines()[-1] == f"specgpu: interrupted; kept {kept} complete sequences in {out}", err
    assert not list(out.glob("*.tmp*")) and not lock.exists()


def test_a_second_interrupt_during_the_drain_is_reported_not_obeyed(capsys):
    from specgpu.apps.cli.options import one_interrupt

    with one_interrupt():
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        os.kill(os.getpid(), signal.SIGINT)  # the drain goes on
        time.sleep(0.1)
    assert "draining what was captured" in capsys.readouterr().err
