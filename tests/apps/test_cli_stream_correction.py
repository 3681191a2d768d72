"""`specgpu stream --white-roi`: the white reference and sigma recorded, bad white ROIs refused in one line."""


import numpy as np
import pytest
from cli_helpers import stream_cli_files
from correction_helpers import white_stream_setup

H, W = 240, 320
SEQUENCES = 3


@pytest.fixture(scope="module")
def setup():
    """The twin recording, its plan given a noise model (and the expected error on a smooth prior)."""
    return white_stream_setup(W, H, SEQUENCES)


def _chart_white_roi():
    from specgpu.rig.scene import colorchecker_scene

    mask = colorchecker_scene(H, W).masks["white 9.5 (.05 D)"]
    ys, xs = np.nonzero(mask)
    return f"{xs.min()},{ys.min()},{xs.max() - xs.min() + 1},{ys.max() - ys.min() + 1}"



def test_cli_stream_white_roi_and_sigma_are_recorded(setup, tmp_path):
    import zarr
    from click.testing import CliRunner

    from specgpu.apps.cli import main

    args = stream_cli_files(setup, tmp_path)
    result = CliRunner().invoke(main, [*args, "--seconds", "0.5", "--out", str(tmp_path / "rec"), "--policy",
                                       "block", "--outputs", "XYZ,sigma,dE_sigma", "--white-roi", _chart_white_roi(),
                                       "--white-reflectance", "0.9"])
    assert result.exit_code == 0, result.output
    g = zarr.open_group(str(tmp_path / "rec"), mode="r")
    n = g.attrs["sequences_committed"]
    assert n >= 1 and g["white_gains"].shape == (n, setup.plan.K) and g["sigma"].shape[0] == n
    assert np.all(np.isfinite(np.asarray(g["white_gains"]))) and g["dE_sigma"].shape == (n, H, W)
    assert g.attrs["metadata"]["white_roi"] == _chart_white_roi()
    assert g.attrs["metadata"]["white_reflectance"] == "0.9"


@pytest.mark.parametrize("extra, message", [
    (["--white-roi", f"{W},0,4,4"], "--white-roi"),
    (["--white-reflectance", "0.9"], "--white-reflectance needs --white-roi"),
    (["--white-roi", "0,0,4,4"], "gives no signal"),
])
def test_cli_stream_white_roi_refusals_are_one_line(setup, tmp_path, extra, message):
    from click.testing import CliRunner

    from specgpu.apps.cli import main

    result = CliRunner().invoke(main, [*stream_cli_files(setup, tmp_path), "--seconds", "5", "--policy", "block",
                                       "--outputs", "XYZ", *extra])
    assert result.exit_code != 0 and message in result.output
    assert "Traceback" not in result.output
    assert len([line for line in result.output.splitlines() if message in line]) == 1
