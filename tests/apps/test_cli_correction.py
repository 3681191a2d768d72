"""The drift corrections through the command line: a white ROI outside the frame refused in one line, drift probes
planned with an ambient frame."""

import pytest

from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.recovery import capture_plan
from specgpu.planning import make_plan
from specgpu.planning.correction import ambient_index, probe_indices
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import colorchecker_scene, white_tile_roi

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


@pytest.fixture(scope="module")
def setup():
    bundle = oracle_calibration(DESC)
    plan = make_plan("narrowband", bundle, step_nm=20.0)
    scene = colorchecker_scene(240, 320, white_tile=0.99)
    return bundle, plan, scene, white_tile_roi(240, 320)



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
