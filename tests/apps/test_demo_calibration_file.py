"""The demo's report keeps the main rig's calibration as the file the calibration cache wrote (copied, not
compressed a second time), and saves it itself only when there is no such file."""

from __future__ import annotations

from specgpu.apps.demo import _copy_calibration
from specgpu.calibration import load_calibration, oracle_calibration, save_calibration
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


def test_the_kept_file_is_copied_byte_for_byte(tmp_path):
    bundle = oracle_calibration(DESC)
    kept = tmp_path / "calibrations" / "calibration-abc.npz"
    kept.parent.mkdir()
    save_calibration(kept, bundle)
    _copy_calibration(kept, tmp_path / "calibration.npz", bundle)
    assert (tmp_path / "calibration.npz").read_bytes() == kept.read_bytes()
    assert load_calibration(tmp_path / "calibration.npz").hash == bundle.hash


def test_without_a_kept_file_the_bundle_is_saved(tmp_path):
    bundle = oracle_calibration(DESC)
    _copy_calibration(tmp_path / "missing.npz", tmp_path / "calibration.npz", bundle)
    _copy_calibration(None, tmp_path / "again.npz", bundle)
    for name in ("calibration.npz", "again.npz"):
        assert load_calibration(tmp_path / name).hash == bundle.hash
    assert not (tmp_path / "missing.npz").exists()
