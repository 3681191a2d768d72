"""Reliability: no silent overwrite or deletion, one writer per output, clear one-line refusals.

Every test reads only the module fixture (calibration, a tristimulus plan, one captured sequence) and writes only
under its own ``tmp_path``.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
from cli_helpers import RIG, one_line_error, run, tristimulus_rig
from cli_helpers import lock_holder as _holder
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu import io
from specgpu.core import locks
from specgpu.io import sequence as io_sequence


def hidden(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tristimulus_rig(tmp_path_factory.mktemp("rel"))
    run("capture", "--rig", d / "rig.toml", "--plan", d / "tri.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", d / "seq", "--sequences", "1", "--seed", "3")
    return d


@pytest.fixture
def seq(base, tmp_path):
    """A private copy of the captured sequence folder."""
    shutil.copytree(base / "seq", tmp_path / "seq")
    return tmp_path / "seq"


# ---- two outputs naming one file ----------------------------------------------------------------------
def test_recover_refuses_two_outputs_on_one_file(seq, tmp_path):
    result = run("recover", seq, "--out", tmp_path / "same.exr", "--xyz", tmp_path / "same.exr", ok=False)
    one_line_error(result, "--out and --xyz", "same.exr", code=2)
    assert not (tmp_path / "same.exr").exists()


def test_recover_refuses_the_same_file_by_another_name(seq, tmp_path):
    (tmp_path / "sub").mkdir()
    result = run("recover", seq, "--out", tmp_path / "a.exr", "--lab", tmp_path / "sub" / ".." / "a.exr", ok=False)
    one_line_error(result, "--out and --lab", code=2)


# ---- a failed write never deletes the earlier file ----------------------------------------------------
def test_failed_recover_keeps_the_previous_output(seq, tmp_path):
    run("recover", seq, "--out", tmp_path / "prev.exr")
    before = (tmp_path / "prev.exr").read_bytes()
    result = run("recover", seq, "--out", tmp_path / "prev.exr", "--xyz", tmp_path / "nodir" / "x.exr", ok=False)
    one_line_error(result, "nodir")
    assert (tmp_path / "prev.exr").read_bytes() == before
    assert hidden(tmp_path) == []


def test_failed_later_write_keeps_every_previous_output(seq, tmp_path, monkeypatch):
    run("recover", seq, "--out", tmp_path / "a.exr", "--xyz", tmp_path / "x.exr")
    before = {p: (tmp_path / p).read_bytes() for p in ("a.exr", "x.exr")}
    calls = []
    real = io.write_map

    def failing(path, *args, **kwargs):  # the second map fails, as a full disk would
        calls.append(path)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, *args, **kwargs)

    monkeypatch.setattr(io, "write_map", failing)  # the package: where recover looks it up
    result = run("recover", seq, "--out", tmp_path / "a.exr", "--xyz", tmp_path / "x.exr", ok=False)
    assert result.exit_code == 1
    assert {p: (tmp_path / p).read_bytes() for p in before} == before
    assert hidden(tmp_path) == []


# ---- an output equal to an input -------------------------------------------------------------------
def test_calibrate_refuses_to_overwrite_its_rig(tmp_path):
    (tmp_path / "r.toml").write_text(RIG)
    one_line_error(run("calibrate", "--rig", tmp_path / "r.toml", "--out", tmp_path / "r.toml", ok=False),
                   "--out", "--rig", code=2)
    assert (tmp_path / "r.toml").read_text() == RIG


def test_plan_refuses_to_overwrite_its_calibration(base, tmp_path):
    shutil.copy(base / "calib.npz", tmp_path / "c.npz")
    before = (tmp_path / "c.npz").read_bytes()
    one_line_error(run("plan", "tristimulus", "--calib", tmp_path / "c.npz", "--out", tmp_path / "c.npz",
                       ok=False), "--calib", code=2)
    assert (tmp_path / "c.npz").read_bytes() == before


@pytest.mark.parametrize("name", ["plan.npz", "calibration.npz", "sequence.json", "frame_000000.tif"])
def test_recover_refuses_to_write_into_the_sequence_it_reads(seq, name):
    before = (seq / name).read_bytes()
    result = run("recover", seq, "--out", seq / name, ok=False)
    one_line_error(result, name, code=2)
    assert (seq / name).read_bytes() == before
    run("recover", seq, "--out", seq.parent / "ok.exr")  # still recoverable


def test_evaluate_refuses_to_write_its_report_over_the_cube(seq, tmp_path):
    run("recover", seq, "--out", tmp_path / "c.exr")
    before = (tmp_path / "c.exr").read_bytes()
    one_line_error(run("evaluate", tmp_path / "c.exr", "--truth", "colorchecker", "--json", tmp_path / "c.exr",
                       ok=False), "--json", "CUBE", code=2)
    assert (tmp_path / "c.exr").read_bytes() == before


# ---- capture never overwrites a user's files ----------------------------------------------------------
def test_capture_refuses_a_folder_with_the_users_files(base, tmp_path):
    shutil.copy(base / "tri.npz", tmp_path / "plan.npz")
    (tmp_path / "notes.txt").write_text("mine")
    before = (tmp_path / "plan.npz").read_bytes()
    result = run("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
                 "--scene", "colorchecker", "--out", tmp_path, ok=False)
    one_line_error(result, "notes.txt", "plan.npz")
    assert (tmp_path / "plan.npz").read_bytes() == before
    assert not (tmp_path / "sequence.json").exists()


def test_capture_replaces_an_interrupted_capture(base, tmp_path):
    out = tmp_path / "seq"
    out.mkdir()
    (out / ".specgpu-capture-incomplete").write_text("interrupted")
    (out / "frame_000000.tif").write_bytes(b"half a frame")
    (out / "plan.npz").write_bytes(b"half a plan")
    one_line_error(run("recover", out, "--out", tmp_path / "c.exr", ok=False), "interrupted capture")
    run("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
        "--scene", "colorchecker", "--out", out)
    assert not (out / ".specgpu-capture-incomplete").exists()
    run("recover", out, "--out", tmp_path / "c.exr")


# ---- an existing --out refused before capturing; frames written as they arrive ------------------------
def test_capture_refuses_an_existing_sequence_before_capturing(base, seq, monkeypatch):
    import specgpu.pipeline.twin_capture as pipeline

    def no_capture(*args, **kwargs):
        raise AssertionError("captured before refusing the folder")

    monkeypatch.setattr(pipeline, "capture_plan", no_capture)
    one_line_error(run("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib",
                       base / "calib.npz", "--scene", "colorchecker", "--out", seq, ok=False), "already holds")


def test_capture_writes_each_sequence_as_it_arrives(base, tmp_path, monkeypatch):
    import specgpu.pipeline.twin_capture as pipeline

    real = pipeline.capture_plan
    on_disk = []

    def watching(*args, on_sequence, **kwargs):
        def seen(sequence):
            on_sequence(sequence)
            on_disk.append(len(list((tmp_path / "s").glob("frame_*.tif"))))
        return real(*args, on_sequence=seen, **kwargs)

    monkeypatch.setattr(pipeline, "capture_plan", watching)
    run("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
        "--scene", "colorchecker", "--out", tmp_path / "s", "--sequences", "3")
    K = json.loads((tmp_path / "s" / "sequence.json").read_text())["metadata"]["K"]
    assert on_disk == [K, 2 * K, 3 * K]
    frames, _, _ = io.read_sequence(tmp_path / "s")
    assert frames.shape[0] == 3 * K


# ---- a reference colour that is not one -----------------------------------------------------------------
@pytest.mark.parametrize("ref", ["nan,0,0", "1e40,0,0", "50,inf,0", "-5,0,0", "50,0,1e6"])
def test_recover_refuses_a_non_finite_reference(seq, tmp_path, ref):
    result = run("recover", seq, "--out", tmp_path / "c.exr", "--delta-e-ref", ref, "--delta-e",
                 tmp_path / "dE.exr", ok=False)
    one_line_error(result, "--delta-e-ref", code=2)
    assert not (tmp_path / "c.exr").exists() and not (tmp_path / "dE.exr").exists()


def test_recover_accepts_a_sane_reference(seq, tmp_path):
    run("recover", seq, "--out", tmp_path / "c.exr", "--delta-e-ref", "50,0,0", "--delta-e", tmp_path / "dE.exr")
    dE, _, _ = io.read_map(tmp_path / "dE.exr")
    assert np.isfinite(dE).mean() > 0.9


def test_stream_refuses_a_non_finite_reference(base, tmp_path):
    result = run("stream", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
                 "--scene", "colorchecker", "--seconds", "0.5", "--delta-e-ref", "nan,0,0", ok=False)
    one_line_error(result, "--delta-e-ref", code=2)


# ---- option values that hang or exhaust memory ---------------------------------------------------------
@pytest.mark.parametrize("value", ["1e-6", "0", "nan", "-1", "inf"])
def test_plan_refuses_absurd_output_steps(base, tmp_path, value):
    result = run("plan", "symmetric", "--calib", base / "calib.npz", "--out", tmp_path / "p.npz",
                 "--output-step-nm", value, ok=False)
    one_line_error(result, "--output-step-nm", code=2)
    assert not (tmp_path / "p.npz").exists()


@pytest.mark.parametrize("value", ["nan", "inf", "0", "-1"])
def test_stream_refuses_a_duration_that_never_ends(base, value):
    result = run("stream", "--plan", base / "tri.npz", "--calib", base / "calib.npz", "--seconds", value, ok=False)
    one_line_error(result, "--seconds", code=2)


# ---- apply_linear's arguments ----------------------------------------------------------------------
def test_apply_linear_refuses_bad_arguments(monkeypatch):
    from specgpu.core import validate
    from specgpu.engine.linear_map import apply_linear

    frames = np.ones((2, 4, 4), np.uint16)
    with pytest.raises(TypeError, match="complex"):
        apply_linear(frames, np.ones((3, 2)) * (1 + 1j))
    with pytest.raises(ValueError, match="saturation must be finite"):
        apply_linear(frames, np.ones((3, 2)), saturation=float("nan"))
    with pytest.raises(TypeError, match="saturation must be a number"):
        apply_linear(frames, np.ones((3, 2)), saturation="x")
    with pytest.raises(ValueError, match="largest buffer"):
        apply_linear(np.ones((2, 20000, 1000), np.uint8), np.ones((40000, 2)))
    monkeypatch.setattr(validate, "available_memory_bytes", lambda: 100)
    with pytest.raises(ValueError, match="GB of memory"):
        apply_linear(frames, np.ones((3, 2)))
    monkeypatch.undo()
    y = apply_linear(frames, np.full((3, 2), 0.5), saturation=np.float32(60000))
    np.testing.assert_allclose(y, 1.0, rtol=1e-6)


@settings(max_examples=30, deadline=None)
@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=3), st.booleans(),
                 st.integers(-2**40, 2**40)))
def test_check_level_accepts_only_finite_numbers(value):
    from specgpu.core.validate import check_level

    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(float(value))
    if ok:
        assert check_level(value) == float(value)
    else:
        with pytest.raises((TypeError, ValueError)):
            check_level(value)


# ---- Ctrl-C / kill during recover -------------------------------------------------------------------
def test_ctrl_c_during_recover_leaves_no_output(seq, tmp_path, monkeypatch):
    real = io.write_map
    calls = []

    def interrupted(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(path, *args, **kwargs)

    monkeypatch.setattr(io, "write_map", interrupted)  # the package: where recover looks it up
    result = run("recover", seq, "--out", tmp_path / "a.exr", "--xyz", tmp_path / "x.exr", "--lab",
                 tmp_path / "l.exr", ok=False)
    assert result.exit_code == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_temporaries_of_a_killed_writer_are_cleaned(seq, tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".c.exr.{dead.pid}.abcd1234.tmp.exr"
    stale.write_bytes(b"half")
    alive = tmp_path / f".c.exr.{os.getpid()}.abcd1234.tmp.exr"  # a live writer's: left alone
    alive.write_bytes(b"busy")
    run("recover", seq, "--out", tmp_path / "c.exr")
    assert not stale.exists() and alive.exists()


# ---- one writer per output ----------------------------------------------------------------------
@pytest.mark.parametrize("command", ["calibrate", "recover", "capture", "plan", "evaluate", "stream", "demo"])
def test_a_second_writer_refuses_at_once_naming_the_holder(base, seq, tmp_path, command):
    out = {"calibrate": tmp_path / "c.npz", "recover": tmp_path / "c.exr", "capture": tmp_path / "s",
           "plan": tmp_path / "p.npz", "evaluate": tmp_path / "r.json", "stream": tmp_path / "ss",
           "demo": tmp_path / "d"}[command]
    args = {"calibrate": ["--rig", base / "rig.toml", "--out", out],
            "recover": [seq, "--out", out],
            "capture": ["--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
                        "--out", out],
            "plan": ["tristimulus", "--calib", base / "calib.npz", "--out", out],
            "evaluate": [base / "calib.npz", "--truth", "colorchecker", "--json", out],
            "stream": ["--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
                       "--seconds", "5", "--out", out],
            "demo": ["--out", out, "--rig", base / "rig.toml"]}[command]
    holder = _holder(out)
    try:
        t0 = time.perf_counter()
        result = run(command, *args, ok=False)
        seconds = time.perf_counter() - t0
    finally:
        holder.kill()
        holder.wait()
    one_line_error(result, f"pid {holder.pid}", out.name)
    assert seconds < 5, seconds
    assert not out.exists()


def test_a_lock_left_by_a_killed_process_is_cleared(tmp_path):
    holder = _holder(tmp_path / "out.npz")
    with pytest.raises(locks.OutputLocked, match=f"pid {holder.pid}"):
        with locks.output_lock(tmp_path / "out.npz"):
            pass
    holder.kill()  # kill -9: no clean-up ran, its lock file stays
    holder.wait()
    assert locks.lock_path(tmp_path / "out.npz").exists()
    with locks.output_lock(tmp_path / "out.npz") as lock:
        assert lock.stale_pid == holder.pid
    assert not locks.lock_path(tmp_path / "out.npz").exists()


def test_locks_are_released_after_a_failure(tmp_path):
    with pytest.raises(RuntimeError):
        with locks.output_locks([tmp_path / "a", tmp_path / "b"]):
            raise RuntimeError
    with locks.output_locks([tmp_path / "a", tmp_path / "b"]):
        pass
    assert hidden(tmp_path) == []


# ---- unclear messages -------------------------------------------------------------------------------------------
def test_binary_rig_toml_names_the_file(tmp_path):
    (tmp_path / "bin.toml").write_bytes(b"\x00\xff\xfe binary")
    one_line_error(run("calibrate", "--rig", tmp_path / "bin.toml", "--out", tmp_path / "c.npz", ok=False),
                   "bin.toml", "not a TOML text file")


def test_negative_seed_names_the_option(tmp_path):
    one_line_error(run("calibrate", "--out", tmp_path / "c.npz", "--seed", "-1", ok=False), "--seed", code=2)


def _disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_in_plan_names_the_file(base, tmp_path, monkeypatch):
    monkeypatch.setattr(np.lib.format, "write_array", _disk_full)  # mid-write: the archive is already open
    error = one_line_error(run("plan", "tristimulus", "--calib", base / "calib.npz", "--out", tmp_path / "p.npz",
                               ok=False), "p.npz", "No space left", "MB free")
    assert "Errno" not in error and ".tmp" not in error
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_disk_full_in_evaluate_names_the_file_and_leaves_nothing(seq, tmp_path, monkeypatch):
    run("recover", seq, "--out", tmp_path / "c.exr")
    import pathlib

    monkeypatch.setattr(pathlib.Path, "write_text", _disk_full)
    one_line_error(run("evaluate", tmp_path / "c.exr", "--truth", "colorchecker", "--json",
                       tmp_path / "report.json", ok=False), "report.json", "No space left")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.exr", "seq"]


def test_unwritable_folder_is_refused_before_the_work_naming_the_output(base, tmp_path, monkeypatch):
    real_open = os.open

    def read_only(path, flags, *args, **kwargs):
        if str(path).startswith(str(tmp_path / "ro")) and flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, "Permission denied")
        return real_open(path, flags, *args, **kwargs)

    (tmp_path / "ro").mkdir()
    monkeypatch.setattr(os, "open", read_only)
    from specgpu.calibration import procedure

    monkeypatch.setattr(procedure, "calibrate", lambda *a, **k: pytest.fail("calibrated before refusing"))
    error = one_line_error(run("calibrate", "--rig", base / "rig.toml", "--out", tmp_path / "ro" / "c.npz",
                               ok=False), "c.npz", "permission denied")
    assert ".tmp" not in error and ".lock" not in error


def test_huge_sequence_header_names_the_file(seq, tmp_path, monkeypatch):
    doc = json.loads((seq / "sequence.json").read_text())
    doc["width"], doc["height"] = 100000, 100000
    (seq / "sequence.json").write_text(json.dumps(doc))

    def no_memory(*args, **kwargs):
        raise MemoryError("Unable to allocate 335 GiB")

    monkeypatch.setattr(io_sequence.np, "empty", no_memory)
    # the header's size is checked against the first frame before anything is allocated
    one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", ok=False), "sequence.json", "100000 x 100000")


def test_reflectance_to_XYZ_outside_the_cmfs_is_a_value_error():
    from specgpu.engine.colorimetry import reflectance_to_XYZ

    w = np.arange(200.0, 300.0, 10.0)
    with pytest.raises(ValueError, match="colour-matching functions"):
        reflectance_to_XYZ(np.ones((2, 2, w.size), np.float32), w)


def test_plan_with_a_huge_decoder_is_refused_naming_the_file(base, tmp_path):
    from dataclasses import replace

    from specgpu.planning import load_plan

    plan = load_plan(base / "tri.npz")
    with pytest.raises(ValueError, match="decoder A must be finite in float32"):  # never built, so never saved
        replace(plan, A=np.full_like(plan.A, 1e300))
    # a file holding one (written by hand, bypassing the class) is refused at load, naming the file
    with np.load(base / "tri.npz", allow_pickle=False) as z:
        fields = {k: z[k] for k in z.files}
    fields["A"] = np.full_like(fields["A"], 1e300)
    np.savez(tmp_path / "huge.npz", **fields)
    with pytest.raises(ValueError, match="huge.npz"):
        load_plan(tmp_path / "huge.npz")


def test_calibration_with_an_impossible_dark_is_refused(base, tmp_path):
    from dataclasses import replace

    from specgpu.calibration.bundle import load_calibration

    bundle = load_calibration(base / "calib.npz")
    with pytest.raises(ValueError, match="dark must lie in"):  # never built, so never saved
        replace(bundle, dark=np.full_like(bundle.dark, -1e30))
    with np.load(base / "calib.npz", allow_pickle=False) as z:  # a file holding one, written by hand
        fields = {k: z[k] for k in z.files}
    fields["dark"] = np.full_like(fields["dark"], -1e30)
    np.savez(tmp_path / "bad.npz", **fields)
    with pytest.raises(ValueError, match="bad.npz"):
        load_calibration(tmp_path / "bad.npz")


def test_disk_full_during_capture_stops_it_and_keeps_the_complete_sequences(base, tmp_path, monkeypatch):
    real = io_sequence._write_tiff
    frames = []

    def filling(path, frame, *rest):
        frames.append(path)
        if len(frames) == 5:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, frame, *rest)

    monkeypatch.setattr(io_sequence, "_write_tiff", filling)
    error = one_line_error(run("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib",
                               base / "calib.npz", "--scene", "colorchecker", "--out", tmp_path / "s",
                               "--sequences", "20", ok=False), "No space left")
    assert "frame_000004.tif" in error
    assert len(frames) == 5  # stopped at once, not after the whole capture
    # the tristimulus plan has 3 frames: the first sequence is kept, the second's frame 3 removed with it
    frames_kept, _, meta = io.read_sequence(tmp_path / "s")
    assert frames_kept.shape[0] == 3 and meta["metadata"]["sequences_requested"] == 20
    assert sorted(p.name for p in (tmp_path / "s").glob("frame_*")) == [f"frame_{i:06d}.tif" for i in range(3)]
