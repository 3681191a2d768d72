"""The README's and the documentation's code runs as written: their Python snippets, the recording readers on a real
recording, the step-by-step experiment; every option they name for a ``specgpu`` command exists on that command, and
the README's one command table lists every command of the CLI."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import calibrated_rig, python_path, run

from specgpu.apps.cli import main

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
# the pages of the documentation site written by hand (not what a build generates under docs/_build, docs/api ...)
GENERATED = ("_build", "api", "auto_examples")
PAGES = {path.relative_to(ROOT).as_posix(): path.read_text() for path in sorted((ROOT / "docs").rglob("*.md"))
         if path.relative_to(ROOT / "docs").parts[0] not in GENERATED}
TEXTS = {"README.md": README, **PAGES}


def blocks(language: str, texts=None) -> list[str]:
    return [b for text in (texts or TEXTS).values()
            for b in re.findall(rf"^ *```{language}\n(.*?)^ *```", text, flags=re.S | re.M)]


def block(language: str, needle: str) -> str:
    found = [b for b in blocks(language) if needle in b]
    assert len(found) == 1, f"{len(found)} {language} blocks of the README and docs/ hold {needle!r}"
    return found[0]


# the Python blocks of the README and the docs, each found by a name only it holds; every block is one of them
PYTHON_BLOCKS = ("apply_linear", "open_recording", "xr.open_zarr", "PLAN_METHODS", "SequenceDecoder(",
                 "estimate_motion(", "with_floor")


def test_every_python_block_is_executed_by_a_test():
    assert len(PAGES) > 10  # the documentation's pages are found
    assert sorted(blocks("python")) == sorted(block("python", needle) for needle in PYTHON_BLOCKS)


def test_the_readme_holds_the_api_example():
    assert "apply_linear" in "".join(blocks("python", {"README.md": README}))


def test_rooms_import_snippet_runs(capsys):
    exec(compile(block("python", "PLAN_METHODS"), "docs (rooms' names)", "exec"), {})
    assert "symmetric" in capsys.readouterr().out


def test_motion_methods_snippet_runs(capsys):
    exec(compile(block("python", "estimate_motion("), "docs (motion methods)", "exec"), {})
    assert capsys.readouterr().out == "['none', 'global', 'affine', 'flow'] [-2. -1.  0.  1.  2.]\n12\n"


def test_noise_floor_snippet_runs(capsys):
    exec(compile(block("python", "with_floor"), "docs (the check's noise floor)", "exec"), {})
    out = capsys.readouterr().out
    assert out.endswith(" 0 with the floor\n") and int(out.split()[0]) > 100  # flagged by the median's test alone


def test_python_api_snippet_runs():
    code = block("python", "apply_linear")
    ns: dict = {}
    exec(compile(code, "README.md (API snippet)", "exec"), ns)
    assert ns["cube"].shape == (480, 640, 31) and ns["cube"].dtype == np.float32
    assert ns["cube16"].shape == (31, 480, 640) and ns["cube16"].dtype == np.float16
    assert ns["XYZ"].shape == ns["Lab"].shape == (480, 640, 3)
    assert ns["dE"].shape == (480, 640) and np.isfinite(ns["dE"]).all()
    np.testing.assert_array_equal(ns["cube_read"], ns["cube"])
    np.testing.assert_array_equal(ns["wl_read"], ns["wl"])


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A stream recording with the default outputs (REC.zarr) and one with the cube (CUBE.zarr), on the small twin
    with a narrowband plan."""
    d = tmp_path_factory.mktemp("readme")
    calibrated_rig(d)
    run("plan", "narrowband", "--calib", d / "calib.npz", "--out", d / "nb.npz")
    for name, outputs in (("REC.zarr", []), ("CUBE.zarr", ["--outputs", "cube"])):
        run("stream", "--rig", d / "rig.toml", "--plan", d / "nb.npz", "--calib", d / "calib.npz", "--seconds", "1",
            "--pacing", "free", "--out", d / name, *outputs)
    return d


def test_sequence_decoder_snippet_runs_on_a_capture(tmp_path, monkeypatch):
    # a 7-band plan, as the motion tests decode: the motion-compensated pass is compiled per number of frames on
    # PoCL, and a 31-frame one costs minutes of compiling on a fresh machine for a snippet that shows an API
    calibrated_rig(tmp_path)
    monkeypatch.chdir(tmp_path)
    run("plan", "narrowband", "--step-nm", "50", "--calib", "calib.npz", "--out", "nb7.npz")
    run("capture", "--rig", "rig.toml", "--plan", "nb7.npz", "--calib", "calib.npz", "--scene", "colorchecker",
        "--out", "seq", "--sequences", "1")
    ns: dict = {}
    exec(compile(block("python", "SequenceDecoder("), "docs (sequence decoder)", "exec"), ns)
    assert ns["cube"].shape[:2] == (240, 320) and ns["cube"].dtype == np.float32


def test_recording_snippets_run_on_a_default_recording(recordings, monkeypatch):
    pytest.importorskip("xarray")  # the README says to install it; the test extra has it
    monkeypatch.chdir(recordings)
    own = {}
    exec(compile(block("python", "open_recording"), "docs (recording reader)", "exec"), own)
    assert own["XYZ"].shape == (240, 320, 3) and own["cube"].shape == (240, 320, 31)
    assert own["wavelengths"].shape == (31,) and own["XYZ_all"].shape[1:] == (240, 320, 3)
    xr_ns = {}
    exec(compile(block("python", "xr.open_zarr"), "docs (xarray)", "exec"), xr_ns)
    cube = xr_ns["cube"]
    assert cube.dims == ("time", "y", "x", "basis_wavelength")
    np.testing.assert_allclose(cube.isel(time=0).values, own["cube"], rtol=1e-5, atol=1e-6)
    # the cube recording's line as the documentation writes it
    line, = re.findall(r'`(ds\["cube"\][^`]*)`', "".join(TEXTS.values()))
    import xarray as xr

    assert eval(line, {"ds": xr.open_zarr("CUBE.zarr")}).dims == ("time", "y", "x")


@pytest.mark.slow
def test_step_by_step_experiment_runs_as_written(tmp_path):
    """The step-by-step experiment (Getting started), each line through bash with ``specgpu`` and ``python`` being
    this tree's."""
    code = block("bash", "specgpu evaluate cube.exr --truth colorchecker --json report.json")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, command in (("specgpu", f'exec "{sys.executable}" -m specgpu "$@"'),
                          ("python", f'exec "{sys.executable}" "$@"')):
        (bin_dir / name).write_text(f"#!/bin/sh\n{command}\n")
        (bin_dir / name).chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "PYTHONPATH": python_path(ROOT), "HOME": str(Path.home())}
    work = tmp_path / "work"
    work.mkdir()
    result = subprocess.run(["bash", "-e", "-c", code], cwd=work, env=env, capture_output=True, text=True,
                            timeout=900)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    for name in ("rig.toml", "calib.npz", "sym.npz", "seq/sequence.json", "cube.exr", "xyz.exr", "dE.png",
                 "report.json"):
        assert (work / name).is_file(), name
    assert "per patch under D65: rmse mean" in result.stdout


def _command_spans(texts=None):
    """(command, text) for every ``specgpu COMMAND ...`` the README and the docs write: inline code and code-block
    lines."""
    out = []
    prose = "\n".join(re.sub(r"^ *```.*?^ *```", "", text, flags=re.S | re.M) for text in (texts or TEXTS).values())
    texts = [" ".join(t.split()) for t in re.findall(r"`([^`]*)`", prose)]  # a span may wrap onto the next line
    lines = [line for b in blocks("bash") for line in b.replace("\\\n", " ").splitlines()]
    texts += [line.split(" # ")[0] for line in lines]  # without the comments
    for text in texts:
        for m in re.finditer(r"specgpu (\w+)(.*?)(?=specgpu \w|$)", text):
            out.append((m.group(1), m.group(2)))
    return out


def test_every_option_the_readme_and_docs_name_exists():
    commands = {name: main.get_command(None, name) for name in main.list_commands(None)}  # loaded on demand
    spans = [(c, t) for c, t in _command_spans() if c in commands]
    assert len(spans) > 30  # the parser finds the README's commands
    missing = []
    for command, text in spans:
        names = {o for p in commands[command].params for o in (*p.opts, *p.secondary_opts)}
        missing += [f"specgpu {command} {opt}" for opt in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", text)
                    if opt not in names]
    assert not missing, missing


def _table_commands(text: str) -> list[str]:
    """The command of each row of a Markdown table whose first cell is ``specgpu COMMAND ...`` in code."""
    return re.findall(r"^\| `specgpu (\w+)(?:\\\||[^|])*` \|", text, flags=re.M)


def test_the_readme_has_one_command_table_listing_every_command_once():
    names = sorted(main.list_commands(None))
    listed = _table_commands(README)
    assert sorted(listed) == names, (sorted(set(names) - set(listed)), sorted(set(listed) - set(names)))
    # one table: its rows are consecutive lines
    rows = [i for i, line in enumerate(README.splitlines()) if re.match(r"^\| `specgpu \w+", line)]
    assert rows == list(range(rows[0], rows[0] + len(names)))


def test_the_command_table_check_finds_a_missing_and_an_unknown_command():
    rows = [line for line in README.splitlines() if re.match(r"^\| `specgpu \w+", line)]
    assert sorted(_table_commands("\n".join(rows[1:]))) != sorted(main.list_commands(None))
    assert "frobnicate" in _table_commands("| `specgpu frobnicate --x` | no such command |")
