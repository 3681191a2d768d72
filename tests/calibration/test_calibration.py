"""Calibration: both feedback loops on the noisy twin from a perturbed start, the bundle against the twin's
ground truth, and the bundle file (version, hash, staleness)."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.calibration.bundle import (
    CalibrationBundle,
    CalibrationRig,
    TwinCalibrationRig,
    calibrate,
    camera_loop,
    distribute_counts,
    load_calibration,
    oracle_calibration,
    rig_fingerprint,
    save_calibration,
    spectral_loop,
)
from specgpu.planning import make_plan
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.light import LightParameters
from specgpu.rig.scene import white_plate_scene
from specgpu.rig.twin import TwinRig

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))  # paper noise, smallest ROI


@pytest.fixture(scope="module")
def oracle():
    return oracle_calibration(DESC)


@pytest.fixture(scope="module")
def calibrated():
    return calibrate(DESC, perturbation=0.3, repeats=4, seed=5)


def test_loop_a_converges_from_a_perturbed_start_with_noise(calibrated):
    rep = calibrated.reports["loop_a"]
    assert rep["history"][0] > 0.05  # the start really was off (30 % spread)
    assert rep["converged"] and rep["residual"] <= rep["tolerance"] == 0.01
    assert 1 <= rep["iterations"] <= 3
    assert len(rep["history"]) == rep["iterations"] + 1
    assert rep["clipped"] <= 3  # only the violet end, below the light guide's cut-off, cannot reach the target


def test_loop_b_converges_from_a_perturbed_start_with_noise(calibrated):
    rep = calibrated.reports["loop_b"]
    assert rep["history"][0] > rep["tolerance"]
    assert rep["converged"] and 1 <= rep["iterations"] <= 20


def test_bundle_matches_the_twin(calibrated, oracle):
    sel = (calibrated.wavelengths >= 410) & (calibrated.wavelengths <= 690)
    # What planning needs is the product lamp x V per wavelength (the system's response).
    est = calibrated.system_matrix.sum(axis=1)[sel]
    true = oracle.system_matrix.sum(axis=1)[sel]
    assert np.abs(est / true - 1).max() < 0.02
    assert np.abs(calibrated.column_wavelengths - oracle.column_wavelengths).max() < 0.1  # nm
    assert np.abs(calibrated.dark - oracle.dark).mean() < 0.3  # DN (noise of the averaged dark frames)
    assert calibrated.dark_rate_dn_per_s == pytest.approx(oracle.dark_rate_dn_per_s, rel=0.2)
    assert np.abs(calibrated.flat_field / oracle.flat_field - 1).mean() < 0.005
    assert calibrated.rig == oracle.rig == rig_fingerprint(DESC)


def test_the_converged_sequence_is_the_reciprocal_of_V(calibrated, oracle):
    """With the white as target, loop (a) equalizes the outputs: its mirror counts per band are proportional
    to 1 / (lamp V), which the twin knows and the loop did not."""
    pats = calibrated.reciprocal_patterns
    bands = calibrated.reciprocal_bands
    resp = np.array([oracle.forward_matrix(p[None], [380.0, 780.0], 1.0).sum() for p in pats])  # true DN/s
    centre = bands.mean(axis=1)
    inside = (centre >= 400) & (centre <= 700)
    assert resp[inside].std() / resp[inside].mean() < 0.01
    # ... although the light's power per band varies several-fold over the range.
    full = np.array([oracle.forward_matrix(np.where(p > 0, 768, 0)[None], [380.0, 780.0], 1.0).sum() for p in pats])
    assert full[inside].max() / full[inside].min() > 3


def test_camera_loop_alone():
    rig = TwinRig(DESC, scene=white_plate_scene(240, 320))
    cw = rig.light.column_wavelengths
    masks = np.stack([(cw >= a) & (cw < a + 50) for a in (450, 500, 550, 600)])
    targets = np.array([40.0, 60.0, 80.0, 60.0])
    dark = np.full(rig.camera.shape, float(rig.expected_frame(0).mean()))  # loaded sequence is all dark
    res = camera_loop(rig, masks, targets, dark=dark, initial_levels=[0.02, 0.5, 0.05, 0.9], repeats=3,
                      tolerance=0.02, max_iterations=6)
    assert res.converged and res.iterations <= 4
    np.testing.assert_allclose(res.outputs, targets, rtol=0.05)
    with pytest.raises(ValueError, match="targets must be"):
        camera_loop(rig, masks, targets[:2])


def test_calibrate_runs_on_any_calibration_rig():
    """The procedure is written once against CalibrationRig: the twin's, passed explicitly, gives the same bundle
    as the default, bit for bit (the hardware rig's run is in test_hw_calibration.py)."""
    kw = {"repeats": 1, "band_step_nm": 25.0, "spectral_check": False, "seed": 2}
    white = white_plate_scene(240, 320, reflectance=0.99)
    rig = TwinCalibrationRig(DESC, scene=white)
    assert isinstance(rig, CalibrationRig) and rig.frame_shape == (240, 320) and rig.max_code == 1023
    assert calibrate(DESC, rig=rig, **kw).hash == calibrate(DESC, **kw).hash
    with pytest.raises(TypeError, match="TwinRig or a CalibrationRig"):
        camera_loop(object(), np.ones((1, 4), bool), [1.0])


def test_spectral_loop_reaches_d65(oracle):
    rig = TwinRig(DESC, scene="white")
    import colour

    d65 = colour.SDS_ILLUMINANTS["D65"]
    grid = rig.light.wavelengths
    target = np.interp(grid, d65.wavelengths, d65.values)
    sel = (grid >= 400) & (grid <= 700)
    target = np.where(sel, target, 0.0)
    target *= 0.5 * float(np.min(rig.light.max_spectrum[sel] / target[sel]))
    start = np.full(rig.light.params.columns, 300)
    res = spectral_loop(rig, target, initial=start, tolerance=0.01, max_iterations=20)
    assert res.history[0] > 0.1 and res.converged and res.iterations <= 20
    # The light really emits the target (truth, not the instrument's reading).
    emitted = rig.light.pattern_to_spectrum(res.patterns[0])
    inner = (grid >= 412) & (grid <= 688)
    assert np.sqrt(np.mean((emitted - target)[inner] ** 2)) / target[inner].max() < 0.02
    with pytest.raises(ValueError, match="target must be finite"):
        spectral_loop(rig, -target)


def test_plans_from_a_calibrated_bundle(calibrated):
    plan = make_plan("narrowband", calibrated)
    assert plan.calibration == calibrated.hash
    assert plan.patterns.max() <= 768 and plan.exposure_s >= calibrated.min_exposure_s


def test_bundle_file_round_trip(tmp_path, calibrated):
    path = tmp_path / "calib.npz"
    assert save_calibration(path, calibrated) == calibrated.hash
    back = load_calibration(path, rig=DESC)
    assert back.hash == calibrated.hash
    np.testing.assert_array_equal(back.responsivity, calibrated.responsivity)
    np.testing.assert_array_equal(back.flat_field, calibrated.flat_field)
    assert back.reports == calibrated.reports
    # A plan chooses its own exposure and frame rate: that does not make the calibration stale.
    faster = replace(DESC, camera=replace(DESC.camera, exposure_s=0.002, frame_rate_hz=200.0))
    load_calibration(path, rig=faster)


def test_stale_or_corrupt_bundles_are_refused(tmp_path, oracle):
    path = tmp_path / "calib.npz"
    save_calibration(path, oracle)
    other_lamp = replace(DESC, light=LightParameters(lamp_colour_temperature_k=5000))
    with pytest.raises(ValueError, match=r"calib\.npz is stale: it was made on another rig configuration"):
        load_calibration(path, rig=other_lamp)
    other_camera = replace(DESC, seed=9)  # another camera: another fixed pattern
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


def test_calibrate_refuses_bad_arguments():
    with pytest.raises(ValueError, match="white_reflectance"):
        calibrate(DESC, white_reflectance=0.0)
    with pytest.raises(ValueError, match="band_step_nm"):
        calibrate(DESC, band_step_nm=1.0)
    with pytest.raises(ValueError, match="perturbation"):
        calibrate(DESC, perturbation=2.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 1), st.integers(1, 40)), min_size=1, max_size=6), st.integers(1, 768))
def test_distribute_counts_property(spec, rows):
    columns = 64
    masks = np.zeros((len(spec), columns), bool)
    rng = np.random.default_rng(len(spec))
    for k, (_, n) in enumerate(spec):
        masks[k, rng.choice(columns, size=n, replace=False)] = True
    levels = np.array([lv for lv, _ in spec])
    out = distribute_counts(levels, masks, rows)
    assert out.min() >= 0 and out.max() <= rows
    for k in range(len(spec)):
        assert np.all(out[k, ~masks[k]] == 0)
        inside = out[k, masks[k]]
        assert inside.max() - inside.min() <= 1  # spread evenly: one mirror of dither at most
        assert inside.sum() == int(round(levels[k] * rows * masks[k].sum()))


# ---- a calibration that holds on an imperfect bench ----------------------------------------------------------
def test_calibration_error_against_the_truth(calibrated, oracle):
    from specgpu.calibration.bundle import calibration_error

    good = calibration_error(calibrated, DESC)
    assert good["rms_relative"] < 0.004 and good["rms_centroid_nm"] < 0.2
    assert calibration_error(oracle, DESC)["rms_relative"] < 1e-6
    assert calibrated.reports["white_reflectance_uncertainty"] == 0.01
    assert calibrated.reports["rig_clock_end_s"] > 1.0


@pytest.fixture(scope="module")
def lab_calibrated():
    from specgpu.rig.realism import LAB

    desc = replace(DESC, profile="lab", realism=LAB)
    return desc, calibrate(desc, seed=3)


def test_calibration_holds_on_the_lab_bench(lab_calibrated):
    from specgpu.calibration.bundle import calibration_error
    from specgpu.rig.light import ProgrammableLight

    desc, bundle = lab_calibrated
    err = calibration_error(bundle, desc)
    # the rest is the white's certificate error (1 %), which no measurement on that white can see
    assert err["max_relative"] < 0.015 and abs(float(err["relative"].mean()) + 0.006) < 0.006
    true_map = ProgrammableLight(desc.light, realism=desc.realism).column_wavelengths
    assert np.max(np.abs(bundle.column_wavelengths - true_map)[30:-30]) < 0.6  # the bow (1.5 nm) is followed
    assert bundle.rig != rig_fingerprint(DESC)


def test_white_uncertainty_is_checked():
    with pytest.raises(ValueError, match=r"white_uncertainty must lie in \[0, 0.2\]"):
        calibrate(DESC, white_uncertainty=0.5)


def test_linearize_inverts_the_measured_compression(oracle):
    c = 0.01 / 1023**2
    b = replace(oracle, reports={**oracle.reports, "linearity_c_per_dn2": c})
    s = np.array([10.0, 500.0, 900.0], np.float32)
    y = s * (1 - c * s**2)
    np.testing.assert_allclose(b.linearize(y), s, rtol=2e-5)
    np.testing.assert_array_equal(oracle.linearize(y), y)  # no measured compression: unchanged


def test_wavelength_dependent_flat_field(oracle):
    h, w = oracle.dark.shape
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
    from specgpu.calibration.bundle import _gaussian_columns, _tabulated_columns

    grid = np.arange(380.0, 781.0)
    centres = np.array([420.3, 555.0, 689.7])
    offsets = np.arange(-15.0, 15.5, 0.5)
    sigma = 5.0 / (2 * np.sqrt(2 * np.log(2)))
    table = np.tile(np.exp(-0.5 * (offsets / sigma) ** 2), (3, 1))
    ref = _gaussian_columns(grid, centres, 5.0)
    got = _tabulated_columns(grid, centres, offsets, table)
    np.testing.assert_allclose(got.sum(axis=0), ref.sum(axis=0), rtol=1e-9)
    assert np.max(np.abs(got - ref)) < 0.01 * ref.max()


@pytest.fixture(scope="module")
def lab_measured(lab_calibrated):
    desc, gaussian = lab_calibrated
    return desc, gaussian, calibrate(desc, seed=3, line_shape="measured")


def test_measured_line_shape_follows_the_lab_slit(lab_measured):
    """The lab slit (flat-topped, FWHM growing with wavelength): the line tabulated from the probe scans cuts the
    model's band-shape error several-fold and changes neither the band responses nor the map."""
    from specgpu.calibration.bundle import calibration_error

    desc, gaussian, measured = lab_measured
    assert measured.reports["slit_model"] == "measured" and gaussian.reports["slit_model"] == "gaussian"
    assert measured.line_shapes.shape == (measured.columns, measured.line_offsets_nm.size)
    dx = measured.line_offsets_nm[1] - measured.line_offsets_nm[0]
    np.testing.assert_allclose(measured.line_shapes.sum(axis=1) * dx, 1.0, rtol=1e-6)
    eg, em = calibration_error(gaussian, desc), calibration_error(measured, desc)
    assert eg["rms_shape"] > 0.006 and em["rms_shape"] < 0.3 * eg["rms_shape"]
    assert abs(em["rms_relative"] - eg["rms_relative"]) < 0.001
    np.testing.assert_array_equal(measured.column_wavelengths, gaussian.column_wavelengths)
    # the lab line is wider in the red: the measured table says so
    x = measured.line_offsets_nm
    width = [np.sqrt(np.sum(measured.line_shapes[c] * x**2) * dx) for c in (100, 900)]  # about 420 and 730 nm
    assert width[1] > 1.1 * width[0]


def test_measured_line_shape_survives_the_file(tmp_path, lab_measured):
    _, _, measured = lab_measured
    path = tmp_path / "cal.npz"
    digest = save_calibration(path, measured)
    back = load_calibration(path)
    assert back.hash == digest == measured.hash
    np.testing.assert_array_equal(back.column_matrix, measured.column_matrix)
    with pytest.raises(ValueError, match="line_shapes and line_offsets_nm go together"):
        replace(measured, line_offsets_nm=None)


def test_line_shape_argument_is_checked():
    with pytest.raises(ValueError) as err:
        calibrate(DESC, line_shape="lorentzian")
    assert "line_shape must be 'measured' or 'gaussian'" in str(err.value) and "\n" not in str(err.value)


def test_light_fluctuation_is_measured(calibrated):
    p = DESC.light
    t = calibrated.reports["light_fluctuation_exposure_s"]
    truth = p.fluctuation_rms * np.sqrt(p.fluctuation_reference_exposure_s / t)
    assert 0.5 * truth < calibrated.reports["light_fluctuation"] < 1.6 * truth  # 16 frames: +-18 % (1 sigma)
