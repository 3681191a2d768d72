"""`calibrate` on the hardware path, in CI without hardware.

The rig is the real driver stack: the DLPC900 light over the simulated controller (USB reports, LUT, uploaded
images decoded back), a GenICam camera driver through ring buffer and assembler, and an Ocean spectrometer driver.
Only the optics are faked, from the twin's physics and from what the controller really displays: the fake camera
(a harvesters-like acquirer) strobes the controller on each exposure and renders the twin's frame of the LUT entry
on display, at the exposure written to its ExposureTime feature; the fake seabreeze device reads the twin light's
spectrum of the mirrors on display (plus a dark offset the spectrometer's dark reading must remove).
"""

from __future__ import annotations

import numpy as np
import pytest
from hw_fakes import DARK_COUNTS, DESC, WHITE, TwinCamera, TwinSeaBreeze, hardware_table, spectrometer_cal

from specgpu.calibration import CalibrationRig, calibrate, oracle_calibration
from specgpu.hardware.dlpc900 import SimulatedDLPC900
from specgpu.hardware.errors import BackendMissing
from specgpu.hardware.rig import open_calibration_rig, open_hardware
from specgpu.planning import make_plan


def _open(tmp_path, **camera):
    sim = SimulatedDLPC900("lightcrafter-6500")
    rig = open_calibration_rig(DESC, hardware=hardware_table(tmp_path), acquirer=TwinCamera(sim, **camera),
                               transport=sim, spectrometer=TwinSeaBreeze(sim, cal=spectrometer_cal()))
    return sim, rig


@pytest.fixture(scope="module")
def hardware_bundle(tmp_path_factory):
    sim, rig = _open(tmp_path_factory.mktemp("hw"), lost={5, 300, 2000})
    with rig:
        bundle = calibrate(DESC, rig=rig, repeats=4, white_reflectance=WHITE, perturbation=0.3, seed=3)
    return bundle, sim, rig


def test_hardware_rig_is_a_calibration_rig(tmp_path):
    sim, rig = _open(tmp_path)
    with rig:
        assert isinstance(rig, CalibrationRig) and rig.max_code == 1023 and rig.frame_shape == (240, 320)
        assert rig.exposure_s == DESC.camera.exposure_s and rig.max_spectrum is None
        frames = rig.capture_mean(np.zeros((2, DESC.light.columns), np.int32), 2, exposure_s=0.004)
        assert frames.shape == (2, 240, 320)
        nm = rig.camera.acquirer.remote_device.node_map
        assert nm.ExposureTime.value == pytest.approx(4000.0) and sim.lut[0]["exposure_us"] == 4000
        rig.zero_spectrometer()
        np.testing.assert_allclose(rig.spectroradiometer.dark_counts, DARK_COUNTS, atol=3)
    assert rig.spectroradiometer.device.closed and not sim.running


def test_calibration_converges_through_the_hardware_drivers(hardware_bundle):
    bundle, sim, rig = hardware_bundle
    rep = bundle.reports
    assert rep["loop_a"]["history"][0] > 0.05  # the start was off
    assert rep["loop_a"]["converged"] and rep["loop_a"]["residual"] <= 0.01
    assert rep["loop_b"]["converged"]
    assert rig.sequences_lost >= 1  # a lost frame discarded its sequence, the mean went on without it
    # exposures were set on the camera: the calibration one, the short dark one and loop (a)'s
    t = {round(x, 9) for x in rig.camera.acquirer.exposures}
    assert {round(x, 9) for x in (DESC.camera.exposure_s, DESC.camera.exposure_s / 4, rep["loop_a_exposure_s"])} <= t
    assert bundle.max_code == 1023 and bundle.frame_shape == (240, 320)
    assert not sim.running  # closing the rig stopped the light


def test_hardware_bundle_matches_the_twin(hardware_bundle):
    bundle = hardware_bundle[0]
    oracle = oracle_calibration(DESC)
    np.testing.assert_allclose(bundle.column_wavelengths, oracle.column_wavelengths, atol=0.5)
    sel = (bundle.wavelengths >= 410) & (bundle.wavelengths <= 690)
    est = bundle.system_matrix.sum(axis=1)[sel]
    true = oracle.system_matrix.sum(axis=1)[sel]
    assert np.median(np.abs(est / true - 1)) < 0.05
    np.testing.assert_allclose(bundle.dark.mean(), oracle.dark.mean(), rtol=0.02)


def test_hardware_bundle_plans_and_reads_the_white_back(hardware_bundle):
    """The bundle is the planner's model: a narrowband plan made from it, captured through the same drivers with
    the bundle's column map, reads the white's reflectance back."""
    bundle = hardware_bundle[0]
    plan = make_plan("narrowband", bundle)
    assert plan.calibration == bundle.hash
    sim = SimulatedDLPC900("lightcrafter-6500")
    camera = open_hardware(DESC, hardware={"light": "dlpc900-simulated", "camera_first_frame_id": 1,
                                           "exposure_s": plan.exposure_s},
                           patterns=plan.patterns, calibration=bundle, n_frames=2 * plan.K,
                           acquirer=TwinCamera(sim), transport=sim)
    from specgpu.capture.session import capture_sequences

    result = capture_sequences(camera, plan.K)
    frames = np.mean([s.frames for s in result.sequences], axis=0)
    o = (frames - bundle.dark_at(plan.exposure_s)) * bundle.flat_field
    h, w = bundle.frame_shape
    centre = o[:, h // 2 - 20:h // 2 + 20, w // 2 - 20:w // 2 + 20].mean(axis=(1, 2))
    y = plan.A @ centre
    inside = (plan.output_wavelengths >= 420) & (plan.output_wavelengths <= 680)
    assert np.median(np.abs(y[inside] - WHITE)) < 0.03


def test_calibration_needs_a_spectrometer_with_its_calibration(tmp_path):
    with pytest.raises(ValueError, match="calibration needs a spectrometer"):
        open_calibration_rig(DESC, hardware={"light": "dlpc900-simulated"})
    with pytest.raises(ValueError, match="spectrometer_calibration"):
        open_calibration_rig(DESC, hardware={"light": "dlpc900-simulated", "spectrometer": "ocean"})


def test_missing_camera_backend_is_one_clear_error(tmp_path):
    try:
        import harvesters  # noqa: F401
    except ImportError:
        with pytest.raises(BackendMissing, match="harvesters"):
            open_calibration_rig(DESC, hardware=hardware_table(tmp_path), transport=SimulatedDLPC900())
    else:
        pytest.skip("harvesters is installed")


def test_missing_spectrometer_backend_is_one_clear_error(tmp_path):
    try:
        import seabreeze  # noqa: F401
    except ImportError:
        sim = SimulatedDLPC900("lightcrafter-6500")
        with pytest.raises(BackendMissing, match="seabreeze"):
            open_calibration_rig(DESC, hardware=hardware_table(tmp_path), acquirer=TwinCamera(sim), transport=sim)
    else:
        pytest.skip("seabreeze is installed")


def test_twin_and_hardware_rigs_share_one_interface():
    from specgpu.calibration import TwinCalibrationRig

    assert isinstance(TwinCalibrationRig(DESC), CalibrationRig)  # the hardware rig's check is above
