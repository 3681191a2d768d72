"""Offline capture on the twin: what ``capture_plan`` refuses before any frame is made."""

from __future__ import annotations

import numpy as np
import pytest

from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.twin_capture import capture_plan, check_scene_covers
from specgpu.planning import make_plan
from specgpu.rig.config import rig_from_dict
from specgpu.rig.scene import read_scene, white_plate_scene

CAMERA = {"roi_width": 320, "roi_height": 240}


def cube(path, lo, hi):
    wl = np.arange(lo, hi + 1.0, 10.0)
    np.savez(path, wavelengths=wl, reflectance=np.full((30, 40, wl.size), 0.5, np.float32))
    return path


@pytest.fixture(scope="module")
def plan():
    bundle = oracle_calibration(rig_from_dict({"camera": CAMERA}))
    return make_plan("narrowband", bundle, step_nm=20.0)


def test_a_motion_object_that_misses_the_lit_wavelengths_is_refused_naming_the_key_and_files(plan, tmp_path):
    """An infrared object is refused as an infrared scene is, not rendered flat over the visible."""
    cube(tmp_path / "ir.npz", 800.0, 1100.0)
    rig = rig_from_dict({"camera": CAMERA, "motion": {"object": "ir.npz", "object_velocity_px_per_frame": [2.0, 0]}},
                        source=str(tmp_path / "rig.toml"), base_dir=tmp_path)
    scene = white_plate_scene(240, 320)
    with pytest.raises(ValueError) as err:
        capture_plan(rig, plan, scene, noise_seed=1)
    msg = str(err.value)
    assert msg.startswith(f"{tmp_path / 'rig.toml'}: [motion] object {tmp_path / 'ir.npz'} covers 800-1100 nm")
    assert "\n" not in msg
    # the same cube as the scene: the same words, one check
    with pytest.raises(ValueError, match="covers 800-1100 nm but the narrowband plan lights"):
        check_scene_covers(read_scene(tmp_path / "ir.npz"), plan)


def test_a_motion_object_covering_the_lit_wavelengths_passes(plan, tmp_path):
    cube(tmp_path / "vis.npz", 380.0, 780.0)
    rig = rig_from_dict({"camera": CAMERA, "motion": {"object": "vis.npz"}}, source="rig.toml", base_dir=tmp_path)
    check_scene_covers(white_plate_scene(240, 320), plan, rig.light.line_fwhm_nm, rig=rig)  # no error
