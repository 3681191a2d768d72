"""An ENVI scene through the command line: accepted wherever a scene is."""

import numpy as np

from specgpu import io
from specgpu.rig.scene import load_scene


def test_an_envi_scene_is_accepted_wherever_a_scene_is(tmp_path):
    from click.testing import CliRunner

    from specgpu.apps.cli import main

    scene = load_scene("colorchecker", 240, 320)
    io.write_cube(tmp_path / "chart.hdr", scene.reflectance, scene.wavelengths, interleave="bil")
    again = load_scene(str(tmp_path / "chart.hdr"), 240, 320)
    np.testing.assert_array_equal(again.reflectance, scene.reflectance.astype(np.float32))
    np.testing.assert_array_equal(again.wavelengths, scene.wavelengths)
    # evaluate a cube (ENVI) against a truth (ENVI): a perfect recovery scores 0
    result = CliRunner().invoke(main, ["evaluate", str(tmp_path / "chart.hdr"), "--truth",
                                       str(tmp_path / "chart.hdr")])
    assert result.exit_code == 0, result.output
    assert "rmse mean 0 max 0, dE76 mean 0 max 0, dE2000 mean 0 max 0" in result.output
