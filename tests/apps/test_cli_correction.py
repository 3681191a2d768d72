"""The drift corrections through the command line: a white ROI outside the frame refused in one line, drift probes
planned with an ambient frame."""

import pytest
from correction_helpers import DESC, white_chart_setup

from specgpu.pipeline.recovery import capture_plan
from specgpu.planning.correction import ambient_index, probe_indices


@pytest.fixture(scope="module")
def setup():
    return white_chart_setup()



def test_cli_recover_white_roi_outside_frame(setup, tmp_path):
    from click.testing import CliRunner

    from specgpu.apps.cli import main
    from specgpu.pipeline.capture_folder import save_plan_and_calibration, write_capture

    bundle, plan, scene, _ = setup
    plan_path, cal_path = save_plan_and_calibration(tmp_path, plan, bundle)
    res = capture_plan(DESC, plan, scene, noise_seed=1, calibration=bundle)
    write_capture(tmp_path / "seq", res.sequences, res.assembly, plan_path, cal_path)
    out = CliRunner().invoke(main, ["recover", str(tmp_path / "seq"), "--out", str(tmp_path / "c.exr"),
                                    "--white-roi", "310,230,40,40"])
    assert out.exit_code != 0
    assert "--white-roi 310,230,40,40 lies outside the 320 x 240 frame" in out.output
    assert not (tmp_path / "c.exr").exists()


def test_cli_plan_drift_probe(setup, tmp_path):
    from cli_helpers import one_line_error, run

    from specgpu.calibration.bundle import save_calibration
    from specgpu.planning import load_plan

    bundle = setup[0]
    cal = tmp_path / "cal.npz"
    save_calibration(cal, bundle)
    run("plan", "tristimulus", "--calib", cal, "--out", tmp_path / "p.npz", "--drift-probe", 430, "--ambient")
    plan = load_plan(tmp_path / "p.npz")
    assert plan.K == 5 and probe_indices(plan) == [3] and ambient_index(plan) == 4
    assert plan.params["drift_probe_nm"] == [430.0]
    bad = run("plan", "tristimulus", "--calib", cal, "--out", tmp_path / "q.npz", "--drift-probe", 200, ok=False)
    one_line_error(bad, "--drift-probe centres must lie within the light's")
    assert not (tmp_path / "q.npz").exists()
