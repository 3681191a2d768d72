"""The CLI test helpers shared by the command-line test files: a small twin rig, running a command in-process, and
the one-line error check every refusal must pass."""

from __future__ import annotations

import atexit
import functools
import os
import shutil
import tempfile
from pathlib import Path

from click.testing import CliRunner

from specgpu.apps.cli import main

#: a 320 x 240 twin: the paper's rig, small enough for quick CLI round trips
RIG = "[camera]\nroi_width = 320\nroi_height = 240\n"
#: a 320 x 240 rig at 200 fps whose natural scene drifts 2 px per frame in x and 1 in y
MOVING_RIG = ("[camera]\nroi_width = 320\nroi_height = 240\nframe_rate_hz = 200.0\nexposure_s = 0.0049\n"
              "[scene]\nsource = \"natural\"\n[motion]\nvelocity_px_per_frame = [2.0, 1.0]\n")


def python_path(*first) -> str:
    """A PYTHONPATH for a subprocess: ``first`` ahead of this process's own entries, which are kept (an
    interpreter whose packages come from PYTHONPATH still finds them; ``first`` still wins)."""
    return os.pathsep.join([*map(str, first), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])


def run(*args, ok=True):
    """``specgpu ARGS`` in-process; ``ok``: assert it exited 0."""
    result = CliRunner().invoke(main, [str(a) for a in args])
    if ok:
        assert result.exit_code == 0, result.output
    return result


def one_line_error(result, *fragments, code=None):
    """Assert a refusal: non-zero exit (``code`` when given) and exactly one ``Error:`` line holding every
    fragment; returns that line."""
    assert result.exit_code != 0, result.output
    if code is not None:
        assert result.exit_code == code, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, result.output
    assert not any(line.startswith(("Usage:", "Try ")) for line in result.output.splitlines()), result.output
    for fragment in fragments:
        assert str(fragment) in errors[0], errors[0]
    return errors[0]


def stream_cli_files(setup, tmp_path):
    """The rig TOML, calibration and plan of a :func:`specgpu.pipeline.twin_replay.stream_setup` written under
    ``tmp_path``;
    returns the ``specgpu stream`` arguments that use them."""
    from specgpu.calibration.bundle import save_calibration
    from specgpu.planning import save_plan

    cam = setup.description.camera
    (tmp_path / "rig.toml").write_text(f"[camera]\nroi_width = {cam.roi_width}\nroi_height = {cam.roi_height}\n"
                                       f"exposure_s = {cam.exposure_s!r}\nframe_rate_hz = {cam.frame_rate_hz!r}\n")
    save_calibration(tmp_path / "calib.npz", setup.bundle)
    save_plan(tmp_path / "plan.npz", setup.plan)
    return ["stream", "--rig", str(tmp_path / "rig.toml"), "--plan", str(tmp_path / "plan.npz"), "--calib",
            str(tmp_path / "calib.npz"), "--scene", "colorchecker"]


def hadamard_rig(d, bundle=None):
    """Write the small twin rig into folder ``d`` with a calibration (``bundle``, default the rig's exact model) and
    a Hadamard-7 plan without an ambient frame made through the CLI; returns the paths (rig, calibration, plan)."""
    from specgpu.calibration.bundle import oracle_calibration, save_calibration
    from specgpu.rig.config import load_rig

    rig, cal, plan = d / "rig.toml", d / "cal.npz", d / "p.npz"
    rig.write_text(RIG)
    save_calibration(cal, oracle_calibration(load_rig(rig)) if bundle is None else bundle)
    run("plan", "hadamard", "--bands", "7", "--calib", cal, "--rig", rig, "--out", plan, "--no-ambient")
    return rig, cal, plan


@functools.cache
def _calibrated(rig_text: str) -> Path:
    """The rig ``rig_text`` (``rig.toml``) calibrated through the CLI (``calib.npz``), once per test session and
    rig (calibrating the twin costs seconds; the calibration is seeded, so each would be the same), in a folder
    removed when the session ends."""
    d = Path(tempfile.mkdtemp(prefix="specgpu-calibrated-"))
    atexit.register(shutil.rmtree, d, True)
    (d / "rig.toml").write_text(rig_text)
    run("calibrate", "--rig", d / "rig.toml", "--out", d / "calib.npz")
    return d


@functools.cache
def _session_files() -> Path:
    """The small twin rig calibrated (:func:`_calibrated`) and a tristimulus plan made from it (``tri.npz``), once
    per test session."""
    d = _calibrated(RIG)
    run("plan", "tristimulus", "--calib", d / "calib.npz", "--out", d / "tri.npz")
    return d


def calibrated_rig(d, *names):
    """Write the small twin rig into folder ``d`` as ``rig.toml`` with ``calib.npz`` beside it, what ``specgpu
    calibrate --rig rig.toml --out calib.npz`` writes (made once per session; each folder gets its own copies),
    and the session's other ``names``; returns ``d``."""
    for name in ("rig.toml", "calib.npz", *names):
        shutil.copyfile(_session_files() / name, d / name)
    return d


def moving_rig(d):
    """Write the moving rig (:data:`MOVING_RIG`) into folder ``d`` as ``rig.toml`` with ``calib.npz`` beside it,
    what ``specgpu calibrate --rig rig.toml --out calib.npz`` writes (made once per session: the calibration is
    seeded, so each would be the same; each folder gets its own copies); returns ``d``."""
    for name in ("rig.toml", "calib.npz"):
        shutil.copyfile(_calibrated(MOVING_RIG) / name, d / name)
    return d


@functools.cache
def _other_calibration() -> Path:
    """A second calibration of the small twin rig (seed 1: a bundle other than ``calib.npz``'s), made through the
    CLI once per session."""
    d = _session_files()
    run("calibrate", "--rig", d / "rig.toml", "--out", d / "other.npz", "--seed", "1")
    return d / "other.npz"


def other_calibration(path):
    """Write at ``path`` what ``specgpu calibrate --seed 1`` writes for the small twin rig: a calibration of the
    rig of :func:`calibrated_rig` other than its ``calib.npz`` (made once per session); returns ``path``."""
    shutil.copyfile(_other_calibration(), path)
    return path


def tristimulus_rig(d):
    """:func:`calibrated_rig` with a tristimulus plan ``tri.npz`` made through the CLI beside the calibration;
    returns ``d``."""
    return calibrated_rig(d, "tri.npz")


def plan_and_capture(d, plan: str, method: str, *plan_args, scene: str = "colorchecker", seq: str, sequences=None):
    """In a folder made by :func:`tristimulus_rig`: ``specgpu plan METHOD *plan_args`` into ``d / plan``, then one
    capture of ``scene`` with it into ``d / seq`` (seed 1); returns ``d``."""
    run("plan", method, *plan_args, "--calib", d / "calib.npz", "--out", d / plan)
    run("capture", "--rig", d / "rig.toml", "--plan", d / plan, "--calib", d / "calib.npz", "--scene", scene,
        "--out", d / seq, "--seed", "1", *(("--sequences", str(sequences)) if sequences else ()))
    return d


HOLD = ("import sys, time; from specgpu.core.locks import output_lock\n"
        "with output_lock(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)\n")


def lock_holder(path):
    """Another process holding specgpu's output lock on ``path`` (for 60 s, or until killed); returns it once the
    lock is held."""
    import os
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(path)], stdout=subprocess.PIPE, text=True,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert proc.stdout.readline().strip() == "held"
    return proc
