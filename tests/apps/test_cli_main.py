"""The main job through the CLI, end to end at the camera's smallest ROI, and every bad input a user gives it.

Each bad input must give a non-zero exit, a one-line reason, and no output left looking complete.
"""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from cli_helpers import RIG, one_line_error, other_calibration, run, tristimulus_rig

from specgpu import io


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A calibrated twin, a symmetric and a tristimulus plan (for D65, the default: the session's, made once), and a
    captured sequence of each."""
    d = tristimulus_rig(tmp_path_factory.mktemp("main"))
    run("plan", "symmetric", "--calib", d / "calib.npz", "--out", d / "sym.npz")
    for plan, seq, n in (("sym.npz", "seq", 2), ("tri.npz", "seqtri", 1)):
        run("capture", "--rig", d / "rig.toml", "--plan", d / plan, "--calib", d / "calib.npz", "--scene",
            "colorchecker", "--out", d / seq, "--sequences", n, "--seed", 5)
    return d


@pytest.fixture(scope="module")
def cube(work, tmp_path_factory):
    """A cube recovered from the symmetric sequence, in a folder of its own (tests read it, never write it)."""
    path = tmp_path_factory.mktemp("cube") / "cube.exr"
    run("recover", work / "seq", "--out", path)
    return path


def test_capture_keeps_plan_and_calibration_with_the_frames(work):
    frames, records, meta = io.read_sequence(work / "seq")
    assert frames.shape == (18, 240, 320) and frames.dtype == np.uint16
    assert [r["pattern_index"] for r in records] == list(range(9)) * 2
    assert (work / "seq" / "plan.npz").is_file() and (work / "seq" / "calibration.npz").is_file()
    assert meta["metadata"]["assembly"]["dropped"] == 0


def test_recover_and_evaluate_symmetric(work, tmp_path):
    out = run("recover", work / "seq", "--out", tmp_path / "cube.exr", "--xyz", tmp_path / "xyz.exr", "--lab",
              tmp_path / "lab.exr", "--delta-e-ref", "colorchecker", "--delta-e", tmp_path / "dE.exr")
    assert "symmetric: 9 projections, 2 sequences" in out.output
    cube, wavelengths, meta = io.read_cube(tmp_path / "cube.exr")
    assert cube.shape == (240, 320, 31) and wavelengths[0] == 400 and wavelengths[-1] == 700
    assert meta["projections"] == 9 and meta["sequences_averaged"] == 2
    dE, channels, _ = io.read_map(tmp_path / "dE.exr")
    assert channels == ("dE2000",) and dE.shape == (240, 320, 1)
    run("evaluate", tmp_path / "cube.exr", "--truth", "colorchecker", "--json", tmp_path / "report.json")
    report = json.loads((tmp_path / "report.json").read_text())
    for key in ("rmse_mean", "rmse_max", "dE76_mean", "dE76_max", "dE2000_mean", "dE2000_max"):
        assert np.isfinite(report[key]), key
    assert report["projections"] == 9 and len(report["patches"]) == 24
    assert report["rmse_mean"] < 0.03 and report["dE76_mean"] < 4.0  # the paper: 0.0153 and 2.52
    assert report["rmse_max"] >= report["rmse_mean"] and report["dE2000_max"] >= report["dE2000_mean"]


def test_recover_and_evaluate_tristimulus(work, tmp_path):
    run("recover", work / "seqtri", "--out", tmp_path / "tri.exr")
    XYZ, channels, _ = io.read_map(tmp_path / "tri.exr", "XYZ")
    assert channels == ("X", "Y", "Z")
    result = run("evaluate", tmp_path / "tri.exr", "--truth", "colorchecker", "--json", tmp_path / "tri.json")
    report = json.loads((tmp_path / "tri.json").read_text())
    assert "rmse_mean" not in report and report["dE76_mean"] < 4.0  # the paper: 2.43
    assert "per patch" in result.output


@pytest.mark.parametrize("method", ["narrowband", "reciprocal", "biased", "camera", "steady"])
def test_every_plan_method(work, method, tmp_path):
    out = run("plan", method, "--calib", work / "calib.npz", "--out", tmp_path / f"{method}.npz")
    assert f"wrote {tmp_path / method}.npz" in out.output


def test_demo_writes_the_report(tmp_path, monkeypatch):
    monkeypatch.setenv("SPECGPU_CACHE_DIR", "")  # no user cache: every rig calibrated here, as the estimate says
    (tmp_path / "rig.toml").write_text(RIG)
    result = run("demo", "--out", tmp_path / "report", "--rig", tmp_path / "rig.toml")
    # first what it runs and how long that takes: the quick demo, one profile (this rig has no imperfections)
    assert re.fullmatch(r"demo: \w+ profile, 8 plans, 1 noise draw, a moving scene: about \d+ s \(--full: .*\)",
                        result.output.splitlines()[0]), result.output.splitlines()[0]
    for table in ("Table 1", "Table 2", "Table 3"):
        assert table in result.output
    assert "paper" in result.output and "demo finished in" in result.output
    report = tmp_path / "report"
    for path in ("index.html", "report.json", "calibration.npz", "basis.npz", "cubes/symmetric.exr",
                 "cubes/tristimulus-A.exr", "maps/narrowband-dE2000.png", "png/truth.png",
                 "figures/spectra-symmetric.png", "figures/illuminants-tristimulus-D65.png",
                 "sequences/narrowband/sequence.json"):
        assert (report / path).is_file(), path
    figures = json.loads((report / "report.json").read_text())
    assert figures["methods"]["symmetric"]["projections"] == 9
    assert figures["methods"]["narrowband"]["rmse_mean"] < 0.02
    page = (report / "index.html").read_text()  # one self-contained page: real tables, embedded images
    assert page.count("<table") >= 4 and "<pre" not in page and "Recovered vs true spectra" in page
    assert "src='data:image/png;base64," in page and "src='figures/" not in page
    # the moving-scene section: the motion visible, compensation giving the still scene's error back
    assert "Moving scene: symmetric-9 at 200 fps" in result.output and "<h2>A moving scene</h2>" in page
    rows = figures["moving_scene"]["rows"]
    assert rows["moving"]["rmse_field"] > 1.5 * rows["still"]["rmse_field"]
    assert rows["compensated"]["rmse_field"] < 1.3 * rows["still"]["rmse_field"]
    # the estimate printed first is the sum of its steps, each within a tolerance of what it cost here (CPU
    # seconds: what a busy machine changes least)
    steps = figures["steps"]
    assert set(steps) == {"start", "calibration", "planning", "measuring", "led", "moving", "report"}
    cpu = sum(step["cpu_s"] for step in steps.values())
    assert 0.6 < sum(step["estimate_s"] for step in steps.values()) / cpu < 1.6, steps
    for name, step in steps.items():
        assert step["cpu_s"] / 3 - 1 < step["estimate_s"] < 3 * step["cpu_s"] + 1, (name, step)
    # each rig's calibration kept for the next run (this rig and the LED rig); the page's figures are the files
    assert len(list((report / "calibrations").glob("calibration-*.npz"))) == 2
    assert "figures/spectra-optimal-9@60ms.png" in {str(p.relative_to(report)) for p in report.rglob("*.png")}


@pytest.mark.slow
def test_demo_full_runs_every_row_on_both_profiles(tmp_path, monkeypatch):
    """``--full``: the estimator rows and every method at equal sequence time, on the lab profile and the ideal one
    beside it, two noise draws each; the 12-LED rig's rows of the 60 ms budget after them."""
    monkeypatch.setenv("SPECGPU_CACHE_DIR", "")
    (tmp_path / "rig.toml").write_text(RIG + "[twin]\nprofile = \"lab\"\n")
    result = run("demo", "--full", "--out", tmp_path / "report", "--rig", tmp_path / "rig.toml")
    assert result.output.startswith("demo: lab, ideal profiles, 17 plans, 2 noise draws, a moving scene: about ")
    draws = json.loads((tmp_path / "report" / "report.json").read_text())["draws"]
    assert list(draws) == ["lab", "ideal", "led12"]
    assert set(draws["led12"]) == {"symmetric-9@60ms", "wiener-9@60ms", "optimal-9@60ms"}
    assert all(len(row["dE00"]["values"]) == 2 for row in draws["led12"].values())
    for runs in (draws["lab"], draws["ideal"]):
        assert {"wiener-9", "optimal-3", "symmetric-9@60ms", "wiener-6@40ms", "tristimulus-D65@20ms"} <= set(runs)
        assert all(len(row["dE00"]["values"]) == 2 for row in runs.values())


# ------------------------------------------------------------------------------------------------ bad input


def test_missing_file(work, tmp_path):
    result = run("evaluate", tmp_path / "none.exr", "--truth", "colorchecker", ok=False)
    assert result.exit_code == 2 and "does not exist" in result.output


def test_truncated_exr(cube, tmp_path):
    data = cube.read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    one_line_error(run("evaluate", tmp_path / "cut.exr", "--truth", "colorchecker", ok=False), "cut.exr")


def test_corrupt_tiff_frame(work, tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(work / "seq", seq)
    frame = sorted(seq.glob("*.tif*"))[3]
    raw = bytearray(frame.read_bytes())
    raw[-100:] = bytes(100)
    frame.write_bytes(bytes(raw))
    one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", ok=False), frame.name)
    assert not (tmp_path / "c.exr").exists()


def test_corrupt_sequence_json(work, tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(work / "seq", seq)
    (seq / "sequence.json").write_text((seq / "sequence.json").read_text()[:200])
    one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", ok=False), "sequence.json")


def test_sequence_with_a_missing_frame(work, tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(work / "seq", seq)
    sorted(seq.glob("*.tif*"))[5].unlink()
    one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", ok=False), "missing")
    assert not (tmp_path / "c.exr").exists()


def test_scene_not_covering_the_plans_range(work, cube, tmp_path):
    wl = np.arange(450.0, 651.0, 10.0)
    np.savez(tmp_path / "narrow.npz", wavelengths=wl, reflectance=np.full((240, 320, wl.size), 0.5, np.float32))
    result = run("capture", "--rig", work / "rig.toml", "--plan", work / "sym.npz", "--calib", work / "calib.npz",
                 "--scene", tmp_path / "narrow.npz", "--out", tmp_path / "seq", ok=False)
    one_line_error(result, "covers 450-650 nm")
    assert not (tmp_path / "seq" / "sequence.json").exists()
    # and a truth that does not cover the cube's wavelengths
    wl = np.arange(420.0, 681.0, 10.0)
    np.savez(tmp_path / "narrow2.npz", wavelengths=wl, reflectance=np.full((240, 320, wl.size), 0.5, np.float32))
    one_line_error(run("evaluate", cube, "--truth", tmp_path / "narrow2.npz", ok=False),
                   "covers 420-680 nm")


def test_plan_from_another_calibration(work, tmp_path):
    other_calibration(tmp_path / "other.npz")
    result = run("capture", "--rig", work / "rig.toml", "--plan", work / "sym.npz", "--calib",
                 tmp_path / "other.npz", "--scene", "colorchecker", "--out", tmp_path / "seq", ok=False)
    one_line_error(result, "stale")
    # a sequence folder whose calibration was swapped
    seq = tmp_path / "seq2"
    shutil.copytree(work / "seq", seq)
    shutil.copyfile(tmp_path / "other.npz", seq / "calibration.npz")
    one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", ok=False), "stale")


def test_sequence_captured_with_another_plan(work, tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(work / "seq", seq)
    shutil.copyfile(work / "tri.npz", seq / "plan.npz")
    one_line_error(run("recover", seq, "--out", tmp_path / "c.exr", ok=False), "captured with plan")


def test_unknown_method_name(work, tmp_path):
    one_line_error(run("plan", "wiener", "--calib", work / "calib.npz", "--out", tmp_path / "p.npz", ok=False),
                   "METHOD='wiener' is not one of", "narrowband")
    one_line_error(run("recover", work / "seq", "--out", tmp_path / "c.exr", "--method", "CMC", ok=False),
                   "method='CMC'")


def test_no_partial_output_when_a_later_write_fails(work, tmp_path):
    result = run("recover", work / "seq", "--out", tmp_path / "c.exr", "--xyz", tmp_path / "nowhere" / "x.exr",
                 ok=False)
    one_line_error(result)
    assert not (tmp_path / "c.exr").exists()


def test_bad_rig_toml(tmp_path):
    (tmp_path / "rig.toml").write_text("[camera]\nroi_widht = 320\n")
    one_line_error(run("calibrate", "--rig", tmp_path / "rig.toml", "--out", tmp_path / "c.npz", ok=False),
                   "rig.toml", "roi_widht")
    assert not (tmp_path / "c.npz").exists()


def test_rig_naming_hardware(work, tmp_path):
    """A [hardware] table selects real devices: checked, and each missing piece is a one-line error."""
    (tmp_path / "typo.toml").write_text(RIG + '[hardware]\nligth = "dlpc900"\n')
    one_line_error(run("capture", "--rig", tmp_path / "typo.toml", "--plan", work / "sym.npz", "--calib",
                       work / "calib.npz", "--out", tmp_path / "seq", ok=False), "unknown key hardware.ligth")
    (tmp_path / "hw.toml").write_text(RIG + '[hardware]\nlight = "dlpc900-simulated"\n')
    one_line_error(run("calibrate", "--rig", tmp_path / "hw.toml", "--out", tmp_path / "c.npz", ok=False),
                   "calibration needs a spectrometer")
    (tmp_path / "hwcal.toml").write_text(RIG + '[hardware]\nlight = "dlpc900-simulated"\nspectrometer = "ocean"\n'
                                         'spectrometer_calibration = "irradiance_cal.csv"\n')
    result = run("calibrate", "--rig", tmp_path / "hwcal.toml", "--out", tmp_path / "c.npz", ok=False)
    try:
        import harvesters  # noqa: F401
    except ImportError:
        one_line_error(result, "harvesters")  # the camera is opened first
    else:
        one_line_error(result)
    assert not (tmp_path / "c.npz").exists()
    result = run("capture", "--rig", tmp_path / "hw.toml", "--plan", work / "sym.npz", "--calib",
                 work / "calib.npz", "--scene", "colorchecker", "--out", tmp_path / "seq", ok=False)
    try:
        import harvesters  # noqa: F401
    except ImportError:
        one_line_error(result, "harvesters")
    assert not (tmp_path / "seq" / "sequence.json").exists()


def test_info_usb_lists_usb_or_says_what_is_missing():
    result = run("info", "--usb", ok=False)
    if result.exit_code == 0:
        assert "USB devices:" in result.output
    else:
        one_line_error(result, "libusb")


def test_capture_without_scene_uses_the_rigs(work, tmp_path):
    (tmp_path / "rig.toml").write_text(RIG + '[scene]\nsource = "white"\n')
    out = run("capture", "--rig", tmp_path / "rig.toml", "--plan", work / "tri.npz", "--calib", work / "calib.npz",
              "--out", tmp_path / "seq")
    assert "(white, 320 x 240)" in out.output
