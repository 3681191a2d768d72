"""The calibration bundle: its file (round trip, version, hash, staleness), its checks, and the forward model's
pieces (linearization, the wavelength-dependent flat field, tabulated line shapes)."""

from dataclasses import replace

import numpy as np
import pytest

from specgpu.calibration.bundle import (
    CalibrationBundle,
    _gaussian_columns,
    _tabulated_columns,
    load_calibration,
    save_calibration,
)
from specgpu.rig.light import LightParameters


def test_bundle_file_round_trip(small_rig, tmp_path, calibrated):
    path = tmp_path / "calib.npz"
    assert save_calibration(path, calibrated) == calibrated.hash
    back = load_calibration(path, rig=small_rig)
    assert back.hash == calibrated.hash
    np.testing.assert_array_equal(back.responsivity, calibrated.responsivity)
    np.testing.assert_array_equal(back.flat_field, calibrated.flat_field)
    assert back.reports == calibrated.reports
    # A plan chooses its own exposure and frame rate: that does not make the calibration stale.
    faster = replace(small_rig, camera=replace(small_rig.camera, exposure_s=0.002, frame_rate_hz=200.0))
    load_calibration(path, rig=faster)


def test_stale_or_corrupt_bundles_are_refused(small_rig, tmp_path, oracle):
    path = tmp_path / "calib.npz"
    save_calibration(path, oracle)
    other_lamp = replace(small_rig, light=LightParameters(lamp_colour_temperature_k=5000))
    with pytest.raises(ValueError, match=r"calib\.npz is stale: it was made on another rig configuration"):
        load_calibration(path, rig=other_lamp)
    other_camera = replace(small_rig, seed=9)  # another camera: another fixed pattern
    with pytest.raises(ValueError, match="stale"):
        load_calibration(path, rig=other_camera)
    data = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) - 50])
    with pytest.raises(ValueError, match=r"cut\.npz: corrupt specgpu.calibration file"):
        load_calibration(tmp_path / "cut.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["dark"] = arrays["dark"] + np.float32(1)
    np.savez(tmp_path / "edited.npz", **arrays)
    with pytest.raises(ValueError, match=r"edited\.npz: corrupt specgpu.calibration file \(content does not match"):
        load_calibration(tmp_path / "edited.npz")
    arrays["dark"] = arrays["dark"] - np.float32(1)
    arrays["__meta__"] = np.array(str(arrays["__meta__"]).replace('"version": 1', '"version": 2'))
    np.savez(tmp_path / "v2.npz", **arrays)
    with pytest.raises(ValueError, match=r"v2\.npz: unknown specgpu.calibration version 2"):
        load_calibration(tmp_path / "v2.npz")
    with pytest.raises(ValueError, match=r"nothing\.npz: specgpu.calibration file not found"):
        load_calibration(tmp_path / "nothing.npz")


def test_bundle_validation(oracle):
    with pytest.raises(ValueError, match="flat_field finite and positive"):
        replace(oracle, flat_field=np.zeros_like(oracle.flat_field))
    with pytest.raises(ValueError, match="responsivity must be"):
        replace(oracle, responsivity=oracle.responsivity[:10])
    assert isinstance(oracle, CalibrationBundle)


def test_linearize_inverts_the_measured_compression(oracle):
    c = 0.01 / 1023**2
    b = replace(oracle, reports={**oracle.reports, "linearity_c_per_dn2": c})
    s = np.array([10.0, 500.0, 900.0], np.float32)
    y = s * (1 - c * s**2)
    np.testing.assert_allclose(b.linearize(y), s, rtol=2e-5)
    np.testing.assert_array_equal(oracle.linearize(y), y)  # no measured compression: unchanged


def test_wavelength_dependent_flat_field(oracle):
    blue = oracle.flat_field * np.float32(1.1)
    red = oracle.flat_field * np.float32(0.9)
    b = replace(oracle, flat_fields=np.stack([blue, red]), flat_wavelengths=np.array([450.0, 650.0]))
    pats = np.zeros((3, oracle.columns), np.int32)
    pats[0, (oracle.column_wavelengths > 440) & (oracle.column_wavelengths < 460)] = oracle.rows
    pats[1, (oracle.column_wavelengths > 540) & (oracle.column_wavelengths < 560)] = oracle.rows
    r = b.flat_ratio(pats)
    assert abs(float(r[0].mean()) - 1.1) < 0.01 and abs(float(r[1].mean()) - 1.0) < 0.02
    np.testing.assert_array_equal(r[2], 1.0)  # all-off (ambient) frame untouched
    assert oracle.flat_ratio(pats) is None
    with pytest.raises(ValueError, match="go together"):
        replace(oracle, flat_fields=np.stack([blue]))
    assert b.hash != oracle.hash


def test_tabulated_line_shape_reproduces_a_gaussian_slit():
    grid = np.arange(380.0, 781.0)
    centres = np.array([420.3, 555.0, 689.7])
    offsets = np.arange(-15.0, 15.5, 0.5)
    sigma = 5.0 / (2 * np.sqrt(2 * np.log(2)))
    table = np.tile(np.exp(-0.5 * (offsets / sigma) ** 2), (3, 1))
    ref = _gaussian_columns(grid, centres, 5.0)
    got = _tabulated_columns(grid, centres, offsets, table)
    np.testing.assert_allclose(got.sum(axis=0), ref.sum(axis=0), rtol=1e-9)
    assert np.max(np.abs(got - ref)) < 0.01 * ref.max()


def test_measured_line_shape_survives_the_file(tmp_path, lab_measured):
    _, _, measured = lab_measured
    path = tmp_path / "cal.npz"
    digest = save_calibration(path, measured)
    back = load_calibration(path)
    assert back.hash == digest == measured.hash
    np.testing.assert_array_equal(back.column_matrix, measured.column_matrix)
    with pytest.raises(ValueError, match="line_shapes and line_offsets_nm go together"):
        replace(measured, line_offsets_nm=None)
