"""What the command line says: usage errors in one line, help texts naming every format and the options' own
spellings, info's device lists, and refusals that name the right file and the command to use instead."""

from __future__ import annotations

import re

import pytest
from cli_helpers import one_line_error, other_calibration, run, tristimulus_rig
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.apps.cli import main


def lines(result):
    return [line for line in result.output.splitlines() if line.strip()]


def flat(text):
    """Help text with click's wrapping undone."""
    return " ".join(text.split())


# ---- usage errors: one line, exit status 2, naming the option ---------------------------------------------------

@pytest.mark.parametrize("args, named", [
    (["capture", "--plan", "no-such-plan.npz"], "'--plan'"),
    (["recover"], "'SEQ'"),
    (["bench", "--sizes", "64Ox48"], "--sizes"),
    (["plan", "optimal", "--calib", "missing.npz", "--out", "o.npz"], "'--calib'"),
    (["plan"], "'METHOD'"),
    (["stream", "--seconds", "nan"], "--seconds"),
    (["info", "--nope"], "'--nope'"),
    (["nosuch"], "'nosuch'"),
    (["--bogus"], "'--bogus'"),
])
def test_usage_errors_are_one_line(args, named):
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2, result.output
    out = lines(result)
    assert len(out) == 1 and out[0].startswith("Error: "), result.output  # no "Usage:" / "Try" lines before it
    assert named in out[0] and "--help" in out[0], out[0]


@settings(max_examples=40, deadline=None)
@given(command=st.sampled_from(["calibrate", "plan", "capture", "recover", "evaluate", "stream", "batch", "info",
                                "salvage", "bench", "demo", "selftest"]),
       name=st.text(st.characters(min_codepoint=97, max_codepoint=122), min_size=3, max_size=12))
def test_any_unknown_option_is_one_line_naming_it(command, name):
    option = f"--zz{name}"  # no command has an option starting with --zz
    result = CliRunner().invoke(main, [command, option])
    assert result.exit_code == 2, result.output
    out = lines(result)
    assert len(out) == 1 and out[0].startswith("Error: ") and option in out[0], result.output


def test_no_arguments_still_prints_the_help():
    result = CliRunner().invoke(main, [])
    assert "Usage:" in result.output and "Commands:" in result.output


# ---- help texts -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command, option", [("capture", "--scene"), ("stream", "--scene"), ("evaluate", "--truth")])
def test_help_names_every_scene_format(command, option):
    text = flat(run(command, "--help").output)
    described = text[text.index(option):]
    assert re.match(rf"{option} TEXT .*\.exr / \.npz / \.hdr \(ENVI\)", described), described[:200]


def test_evaluate_help_names_envi_cubes():
    assert ".hdr" in flat(run("evaluate", "--help").output).split("Options:")[0]


def test_unknown_scene_error_names_envi():
    from specgpu.rig.scene import load_scene

    with pytest.raises(ValueError, match=r"unknown scene 'chart\.tif'; give a \.exr, \.npz or \.hdr \(ENVI\) file"):
        load_scene("chart.tif", 8, 8)


def test_objective_is_spelled_as_in_the_guide():
    from pathlib import Path

    text = flat(run("plan", "--help").output)
    assert "--objective [rmse|dE2000|dEab]" in text
    guide = (Path(__file__).resolve().parents[2] / "docs" / "guide" / "plans.md").read_text()
    assert "--objective rmse|dE2000|dEab" in guide


def test_stream_help_does_not_ask_for_an_estimator_for_sigma():
    # every plan specgpu plan writes records the noise model; --estimator is not what sigma needs
    text = flat(run("stream", "--help").output)
    assert "--estimator" not in text and "noise model" in text


# ---- info -------------------------------------------------------------------------------------------------------

def test_info_devices_lists_the_opencl_devices_alone():
    from specgpu.engine.runtime import list_devices

    result = run("info", "--devices")
    out = lines(result)
    assert len(out) == len(list_devices()) >= 1
    assert all(re.match(r"^[* ] \d+:\d+  \S", line) for line in out), out
    assert sum(line.startswith("*") for line in out) == 1  # the one chosen
    assert "USB" not in result.output


def test_info_help_separates_opencl_and_usb():
    text = flat(run("info", "--help").output)
    assert "--devices List only the OpenCL devices" in text and "--usb Also list the USB devices" in text


# ---- refusals naming what the user has and what to run -----------------------------------------------------------

@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """Two calibrations of the small twin (seeds 0 and 1: different bundles), a tristimulus plan from the first,
    and a zarr recording of its raw frames."""
    d = tmp_path_factory.mktemp("words")
    tristimulus_rig(d)
    other_calibration(d / "other.npz")
    run("capture", "--rig", d / "rig.toml", "--plan", d / "tri.npz", "--calib", d / "calib.npz", "--scene", "white",
        "--out", d / "rec.zarr")
    return d


def test_recover_on_a_zarr_recording_points_to_batch(rig, tmp_path):
    result = run("recover", rig / "rec.zarr", "--out", tmp_path / "xyz.exr", ok=False)
    line = one_line_error(result, f"{rig / 'rec.zarr'}: a zarr recording, not a sequence folder",
                          f"specgpu batch {rig / 'rec.zarr'} --plan PLAN --out OUT.zarr", code=1)
    assert "complete frame sequence" not in line
    assert not (tmp_path / "xyz.exr").exists()


def test_read_capture_names_a_recording_without_frames(tmp_path):
    import zarr

    from specgpu.pipeline.capture_folder import read_capture

    group = zarr.open_group(str(tmp_path / "r.zarr"), mode="w", zarr_format=3)
    group.attrs.update({"format": "specgpu.recording", "frames": False})
    with pytest.raises(ValueError, match=r"r\.zarr: a zarr recording without raw frames, not a sequence folder; "
                                         r"its results are in it \(specgpu\.io\.recording\.open_recording"):
        read_capture(tmp_path / "r.zarr")
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w", zarr_format=3)
    with pytest.raises(ValueError, match=r"other\.zarr: a zarr store, not a sequence folder"):
        read_capture(tmp_path / "other.zarr")


def test_batch_stale_plan_names_the_plan_and_the_calibration(rig, tmp_path):
    result = run("batch", rig / "rec.zarr", "--plan", rig / "tri.npz", "--calib", rig / "other.npz", "--out",
                 tmp_path / "b.zarr", ok=False)
    one_line_error(result, f"{rig / 'tri.npz'} is stale: made from calibration", f"{rig / 'other.npz'} is",
                   "re-plan", code=1)
    assert not (tmp_path / "b.zarr").exists()
