"""An LED rig end to end through the real commands (calibrate, plan optimal within a budget, capture, recover,
evaluate), narrow bands refused on it in one line, and ``specgpu bound`` on it."""

import json

import pytest
from cli_helpers import one_line_error, run

from specgpu.calibration.bundle import load_calibration, oracle_calibration, save_calibration
from specgpu.planning import load_plan
from specgpu.rig.config import load_rig

LED_RIG = '[light]\nkind = "led"\npreset = "led12"\n[camera]\nroi_width = 320\nroi_height = 240\n'


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    """The LED rig and its exact bundle (the end-to-end test calibrates its own)."""
    d = tmp_path_factory.mktemp("led")
    rig = d / "led.toml"
    rig.write_text(LED_RIG)
    save_calibration(d / "oracle.npz", oracle_calibration(load_rig(rig)))
    return d, rig, d / "oracle.npz"


@pytest.mark.slow  # the real commands on the twin, calibration included: about a minute
def test_an_led_rig_end_to_end(oracle):
    d, rig, _ = oracle
    run("calibrate", "--rig", rig, "--out", d / "cal.npz")
    cal = d / "cal.npz"
    bundle = load_calibration(cal)
    assert bundle.light_kind == "led" and bundle.columns == 12
    out = run("plan", "optimal", "--frames", "9", "--sequence-ms", "60", "--calib", cal, "--rig", rig,
              "--out", d / "plan.npz", "--no-ambient").output
    assert "(budget 60 ms)" in out
    plan = load_plan(d / "plan.npz")
    assert plan.K == 9 and plan.patterns.shape == (9, 12) and plan.sequence_s <= 0.060 * (1 + 1e-9)
    run("capture", "--rig", rig, "--plan", d / "plan.npz", "--calib", cal, "--scene", "colorchecker",
        "--out", d / "seq", "--sequences", "1")
    run("recover", d / "seq", "--out", d / "cube.exr")
    scored = run("evaluate", d / "cube.exr", "--truth", "colorchecker", "--json", d / "report.json").output
    report = json.loads((d / "report.json").read_text())
    assert "per patch" in scored and report["patches_scored"] == 24
    assert report["rmse_mean"] < 0.03 and report["dE2000_mean"] < 1.5


def test_narrowband_on_an_led_rig_is_one_line_naming_its_bands(oracle):
    d, rig, cal = oracle
    line = one_line_error(run("plan", "narrowband", "--calib", cal, "--rig", rig, "--out", d / "nb.npz", ok=False),
                          "narrowband needs a light tunable", "12 fixed bands at 430, 450, 470", code=2)
    assert "use one of" in line and not (d / "nb.npz").exists()


def test_bound_on_an_led_rig(oracle):
    d, rig, cal = oracle
    out = run("bound", "--frames", "9", "--sequence-ms", "60", "--calib", cal, "--rig", rig, "--starts", "1").output
    assert "lower bound, any linear design" in out and "noise-free limit of the light's primaries" in out
