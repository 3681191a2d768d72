"""Output files a user can share and trust: the mode a plain open() gives, companion files (an ENVI header's data
file) treated as inputs and outputs, locks on the resolved path, and a full disk named as the output and its cause.

Every test reads only the module fixture (a calibration, a tristimulus plan, one captured sequence, an ENVI cube)
and writes only under its own ``tmp_path``.
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import lock_holder as holder
from cli_helpers import one_line_error, run, tristimulus_rig

from specgpu import io
from specgpu.core import locks
from specgpu.io import paths


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tristimulus_rig(tmp_path_factory.mktemp("files"))
    run("capture", "--rig", d / "rig.toml", "--plan", d / "tri.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", d / "seq", "--sequences", "1", "--seed", "3")
    run("plan", "narrowband", "--rig", d / "rig.toml", "--calib", d / "calib.npz", "--out", d / "nb.npz",
        "--step-nm", "60")  # a reflectance plan, for ENVI cubes
    run("capture", "--rig", d / "rig.toml", "--plan", d / "nb.npz", "--calib", d / "calib.npz", "--scene",
        "colorchecker", "--out", d / "seqr", "--sequences", "1", "--seed", "3")
    wl = np.arange(400.0, 701.0, 10.0)
    cube = np.random.default_rng(0).uniform(0.05, 0.9, (240, 320, wl.size)).astype(np.float32)
    io.write_cube(d / "e.hdr", cube, wl)
    return d


@pytest.fixture
def seq(base, tmp_path):
    shutil.copytree(base / "seq", tmp_path / "seq")
    return tmp_path / "seq"


@pytest.fixture
def seqr(base, tmp_path):
    """A sequence of a reflectance plan (its cube may be written as ENVI)."""
    shutil.copytree(base / "seqr", tmp_path / "seq")
    return tmp_path / "seq"


def mode(path) -> int:
    return os.stat(path).st_mode & 0o777


def capture_args(base, out, *more):
    return ("capture", "--rig", base / "rig.toml", "--plan", base / "tri.npz", "--calib", base / "calib.npz",
            "--scene", "colorchecker", "--out", out, "--sequences", "1", "--seed", "3", *more)


# ---- the mode of every output --------------------------------------------------------------------------------------
@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_every_output_gets_the_mode_a_plain_open_gives(base, seq, tmp_path, umask):
    old = os.umask(umask)
    try:
        out = tmp_path / "out"
        out.mkdir()
        run("plan", "tristimulus", "--calib", base / "calib.npz", "--out", out / "p.npz")
        run(*capture_args(base, out / "s"))
        run("recover", seq, "--out", out / "c.exr", "--lab", out / "lab.exr", "--delta-e-ref", "50,0,0",
            "--delta-e", out / "dE.png")
        run("evaluate", base / "e.hdr", "--truth", "colorchecker", "--json", out / "report.json")
        cube, wl, _ = io.read_cube(base / "e.hdr")
        io.write_cube(out / "e.hdr", cube, wl)  # ENVI: header and data file
        io.write_cube(out / "c.npz", cube[:8, :8], wl)
        # the projector study's renderings
        io.write_png(out / "projector.png", np.zeros((4, 4, 3), np.uint8), {"specgpu:illuminant": "A"})
        reference = out / "plain.txt"
        with open(reference, "w") as fh:
            fh.write("what open() gives")
    finally:
        os.umask(old)
    expected = 0o666 & ~umask
    assert mode(reference) == expected
    files = [p for p in out.rglob("*") if p.is_file() and not p.name.startswith(".")]
    assert {"p.npz", "frame_000000.tif", "sequence.json", "plan.npz", "calibration.npz", "c.exr", "lab.exr",
            "dE.png", "report.json", "e.hdr", "e.img", "c.npz", "projector.png"} <= {p.name for p in files}
    wrong = {str(p.relative_to(out)): oct(mode(p)) for p in files if mode(p) != expected}
    assert wrong == {}, f"expected {oct(expected)}"


def test_a_rewritten_file_keeps_its_mode_and_a_link_is_written_through(base, seq, tmp_path):
    target = tmp_path / "p.npz"
    run("plan", "tristimulus", "--calib", base / "calib.npz", "--out", target)
    os.chmod(target, 0o640)  # the user's choice, as open() keeps it
    run("plan", "tristimulus", "--calib", base / "calib.npz", "--out", target)
    assert mode(target) == 0o640
    run("recover", seq, "--out", tmp_path / "c.exr")
    os.chmod(tmp_path / "c.exr", 0o444)  # read-only: replaced as before, and still read-only
    run("recover", seq, "--out", tmp_path / "c.exr")
    assert mode(tmp_path / "c.exr") == 0o444
    (tmp_path / "real").mkdir()
    link = tmp_path / "link.npz"
    link.symlink_to(tmp_path / "real" / "p.npz")
    run("plan", "tristimulus", "--calib", base / "calib.npz", "--out", link)
    assert link.is_symlink() and (tmp_path / "real" / "p.npz").is_file()
    assert [p.name for p in (tmp_path / "real").iterdir()] == ["p.npz"]  # no temporary left behind


def test_new_temporary_is_created_with_the_umask_and_named_after_its_file(tmp_path):
    old = os.umask(0o002)
    try:
        tmp = paths.new_temporary(tmp_path / "a.exr")
    finally:
        os.umask(old)
    assert mode(tmp) == 0o664 and tmp.suffix == ".exr"
    assert paths.final_name(tmp.name) == "a.exr"
    assert paths.final_name(paths.new_temporary(tmp).name) == "a.exr"  # the temporary of a temporary
    assert paths.final_name(tmp.with_suffix(".img").name) == "a.img"  # a companion renamed with it
    assert locks.clean_stale_temporaries(tmp_path / "a.exr") == []  # a live writer's: left alone


# ---- companion files are inputs and outputs ------------------------------------------------------------------------
def test_evaluate_refuses_to_write_its_report_over_the_cubes_data_file(base, tmp_path):
    shutil.copy(base / "e.hdr", tmp_path / "e.hdr")
    shutil.copy(base / "e.img", tmp_path / "e.img")
    before = (tmp_path / "e.img").read_bytes()
    one_line_error(run("evaluate", tmp_path / "e.hdr", "--truth", "colorchecker", "--json", tmp_path / "e.img",
                       ok=False), "--json", "e.img", "CUBE's ENVI data file", code=2)
    assert (tmp_path / "e.img").read_bytes() == before
    io.read_cube(tmp_path / "e.hdr")


def test_an_envi_data_file_named_in_its_header_is_an_input_too(base, tmp_path):
    text = (base / "e.hdr").read_text() + "data file = cube.bin\n"
    (tmp_path / "e.hdr").write_text(text)
    shutil.copy(base / "e.img", tmp_path / "cube.bin")
    one_line_error(run("evaluate", tmp_path / "e.hdr", "--truth", "colorchecker", "--json", tmp_path / "cube.bin",
                       ok=False), "cube.bin", code=2)
    assert (tmp_path / "cube.bin").stat().st_size == (base / "e.img").stat().st_size


def test_recover_refuses_an_output_on_a_reference_cubes_data_file(base, seq, tmp_path):
    shutil.copy(base / "e.hdr", tmp_path / "ref.hdr")
    shutil.copy(base / "e.img", tmp_path / "ref.img")
    one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", "--delta-e-ref", tmp_path / "ref.hdr",
                       "--delta-e", tmp_path / "ref.img", ok=False), "--delta-e", "ref.img", code=2)
    assert (tmp_path / "ref.img").stat().st_size == (base / "e.img").stat().st_size


def refused_while_held(path, *args):
    proc = holder(path)
    try:
        t0 = time.perf_counter()
        result = run(*args, ok=False)
        assert time.perf_counter() - t0 < 5
    finally:
        proc.kill()
        proc.wait()
    return one_line_error(result, f"pid {proc.pid}")


def test_a_writer_of_an_envi_header_holds_the_lock_of_its_data_file(seqr, tmp_path):
    seq = seqr
    refused_while_held(tmp_path / "e.img", "recover", seq, "--out", tmp_path / "e.hdr")
    assert not (tmp_path / "e.hdr").exists() and not (tmp_path / "e.img").exists()


# ---- locks on the resolved path ------------------------------------------------------------------------------------
def test_a_capture_through_a_link_meets_the_lock_of_the_folder(base, tmp_path):
    (tmp_path / "cf").mkdir()
    (tmp_path / "cfl").symlink_to("cf")
    refused_while_held(tmp_path / "cf", *capture_args(base, tmp_path / "cfl"))
    assert list((tmp_path / "cf").iterdir()) == []
    refused_while_held(tmp_path / "cfl", *capture_args(base, tmp_path / "cf"))
    (tmp_path / "rl.zarr").symlink_to("r.zarr")  # a recording, not yet there, through a link
    refused_while_held(tmp_path / "r.zarr", *capture_args(base, tmp_path / "rl.zarr"))


def test_locks_meet_through_links_in_process(tmp_path):
    (tmp_path / "cf").mkdir()
    (tmp_path / "cfl").symlink_to(tmp_path / "cf")
    (tmp_path / "dl").symlink_to(tmp_path)
    with locks.output_lock(tmp_path / "cf"):
        for other in (tmp_path / "cfl", tmp_path / "dl" / "cf", tmp_path / "dl" / "cfl"):
            with pytest.raises(locks.OutputLocked, match=str(os.getpid())):
                with locks.output_lock(other):
                    pass
    with locks.output_locks([tmp_path / "cf", tmp_path / "cfl"]) as held:  # one folder, two names: one lock
        assert len(held) == 1
    assert locks.lock_path(tmp_path / "cfl") == locks.lock_path(tmp_path / "cf")


# ---- a full disk names the output and its cause --------------------------------------------------------------------
class _FullDisk:
    """The disk fills while a library writes an image: its write fails with the library's own words (naming the
    temporary file it was given), and from then on the operating system refuses to sync any more data."""

    def __init__(self, monkeypatch, message):
        import OpenImageIO as oiio

        self.full = False
        real_create, real_fsync = oiio.ImageOutput.create, os.fsync
        disk = self

        class Output:
            def __init__(self, real):
                self.real = real

            def open(self, name, spec, *args):
                self.name = name
                Path(name).write_bytes(b"partial")
                return True

            def write_image(self, pixels):
                disk.full = True
                return False

            def geterror(self, *args):
                return message.format(name=self.name)

            def close(self):
                return True

        def create(*args, **kwargs):
            return Output(real_create(*args, **kwargs))

        def fsync(fd):
            if disk.full:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real_fsync(fd)

        monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(create))
        monkeypatch.setattr(os, "fsync", fsync)


def test_capture_on_a_full_disk_names_the_frame_and_the_cause(base, tmp_path, monkeypatch):
    _FullDisk(monkeypatch, "TIFFWriteScanline failed writing line y=160,z=0 (Write error at scanline 160)")
    error = one_line_error(run(*capture_args(base, tmp_path / "s"), ok=False), "frame_000000.tif",
                           "No space left on device")
    assert "TIFFWriteScanline" not in error and ".tmp" not in error


def test_recover_to_exr_on_a_full_disk_names_the_output_not_its_temporary(seq, tmp_path, monkeypatch):
    _FullDisk(monkeypatch, 'Failed OpenEXR write: Failed to write pixel data to image file "{name}". File output '
                           "failed.")
    error = one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", ok=False), f"{tmp_path / 'c.exr'}:",
                           "No space left on device")
    assert ".tmp" not in error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_a_library_error_never_names_a_temporary(tmp_path, monkeypatch):
    _FullDisk(monkeypatch, 'cannot write "{name}"')
    monkeypatch.setattr(os, "fsync", lambda fd: None)  # not the disk: the library's own words, names fixed
    with pytest.raises(ValueError) as caught:
        io.write_map(tmp_path / "x.exr", np.zeros((2, 2, 3), np.float32), "XYZ")
    assert str(caught.value).startswith(f"{tmp_path / 'x.exr'}: cannot write EXR (")
    assert f'"{tmp_path / "x.exr"}"' in str(caught.value) and ".tmp" not in str(caught.value)


def test_envi_on_a_full_disk_names_the_data_file(seqr, tmp_path, monkeypatch):
    seq = seqr
    import builtins

    real_open = builtins.open

    def full(file, mode="r", *args, **kwargs):
        fh = real_open(file, mode, *args, **kwargs)
        if "w" in mode and str(file).endswith(".img"):
            class Full:
                def __enter__(self):
                    return self

                def __exit__(self, *exc):
                    fh.close()

                def write(self, data):
                    fh.write(bytes(memoryview(data))[:100])
                    raise OSError(errno.ENOSPC, "No space left on device")
            return Full()
        return fh

    monkeypatch.setattr(builtins, "open", full)
    error = one_line_error(run("recover", seq, "--out", tmp_path / "e.hdr", ok=False),
                           f"{tmp_path / 'e.img'}:", "No space left on device")
    assert ".tmp" not in error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


@pytest.fixture
def small_disk(tmp_path):
    """A real 400 KiB file system (tmpfs; needs the right to mount, else the test is skipped)."""
    where = tmp_path / "small"
    where.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(where)], capture_output=True)
    if done.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


def test_a_real_full_disk_names_each_output_and_the_cause(base, seqr, small_disk):
    seq = seqr
    error = one_line_error(run(*capture_args(base, small_disk / "s", "--sequences", "3"), ok=False),
                           "frame_", "No space left on device")
    assert "TIFFWriteScanline" not in error and ".tmp" not in error
    shutil.rmtree(small_disk / "s", ignore_errors=True)
    (small_disk / "fill").write_bytes(bytes(300_000))
    for out, named in (("c.exr", "c.exr"), ("e.hdr", "e.img"), ("c.npz", "c.npz")):
        error = one_line_error(run("recover", seq, "--out", small_disk / out, ok=False),
                               f"{small_disk / named}:", "No space left on device")
        assert ".tmp" not in error and "requested" not in error
    assert sorted(p.name for p in small_disk.iterdir()) == ["fill"]


def test_a_folder_where_a_file_goes_is_refused_in_one_line_before_any_write(tmp_path):
    wl = np.arange(400.0, 701.0, 30.0)
    cube = np.zeros((4, 4, wl.size), np.float32)
    for name in ("c.exr", "e.hdr", "c.npz"):
        (tmp_path / name).mkdir()
        with pytest.raises(IsADirectoryError) as caught:
            io.write_cube(tmp_path / name, cube, wl)
        assert str(caught.value) == f"{tmp_path / name}: is a folder, not a file; choose a file name"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.exr", "c.npz", "e.hdr"]  # no e.img written


def test_an_envi_write_that_fails_replaces_neither_file(tmp_path, monkeypatch):
    wl = np.arange(400.0, 701.0, 30.0)
    io.write_cube(tmp_path / "e.hdr", np.zeros((4, 4, wl.size), np.float32), wl)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real = Path.write_text

    def full(self, *args, **kwargs):
        if self.suffix == ".hdr":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(OSError, match="e.hdr: cannot write .No space left on device"):
        io.write_cube(tmp_path / "e.hdr", np.ones((4, 4, wl.size), np.float32), wl)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # the old pair, whole
