"""Calibration of a light of a few broad primaries (an LED array): each LED measured whole by the
spectroradiometer, the bundle's model of each against the twin's truth, and what the bundle records of the light."""

from dataclasses import replace

import numpy as np
import pytest

from specgpu.calibration import calibrate, oracle_calibration
from specgpu.calibration.bundle import calibration_error, load_calibration, save_calibration
from specgpu.calibration.loops import spectral_loop
from specgpu.calibration.rigs import TwinCalibrationRig
from specgpu.core.numerics import fit_levels
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.led import LEDParameters
from specgpu.rig.ol490 import OL490Parameters
from specgpu.rig.realism import Realism
from specgpu.rig.scene import white_plate_scene
from specgpu.rig.twin import TwinRig

CAM = CameraParameters(roi_width=320, roi_height=240)
LED = RigDescription(light=LEDParameters(preset="led12"), camera=CAM)


@pytest.fixture(scope="module")
def led_bundle():
    return calibrate(LED, repeats=1, band_step_nm=10.0)


def test_each_led_is_measured_against_the_twins_truth(led_bundle):
    b = led_bundle
    assert b.light_kind == "led" and b.columns == 12 and b.rows == 255
    light = TwinRig(LED).light
    truth = (light.wavelengths @ light.column_matrix) / light.column_matrix.sum(axis=0)
    np.testing.assert_allclose(b.light["primaries_nm"], truth, atol=0.3)
    np.testing.assert_allclose(b.column_wavelengths, truth, atol=0.3)
    # each LED's spectrum as measured (the instrument's bandpass taken out) against the twin's
    model = b.column_matrix
    true = light.column_matrix
    np.testing.assert_allclose(model.sum(axis=0), true.sum(axis=0), rtol=0.01)
    shape_err = np.sqrt(np.mean((model - true) ** 2, axis=0)) / true.max(axis=0)
    assert shape_err.max() < 0.01
    # and the camera's response to each (the responsivity known at the 12 LEDs only: the ends extrapolated)
    err = calibration_error(b, LED)
    assert err["bands"].shape == (12, 2)  # one band per LED, at its measured centroid
    assert err["max_relative"] < 0.01 and err["max_centroid_nm"] < 0.5 and err["max_shape"] < 0.04
    assert b.reports["loop_a"]["converged"] and "column_map" not in b.reports
    # the spectral check aims at the closest the LEDs make to a flat band, and reaches it to the instrument's floor
    assert b.reports["loop_b"]["residual"] < 0.01


def test_the_oracle_bundle_of_an_led_rig_is_the_truth():
    b = oracle_calibration(LED)
    err = calibration_error(b, LED)
    assert err["max_relative"] < 1e-3 and err["max_centroid_nm"] < 0.02
    assert b.whole_periods(0.006612) == pytest.approx(132 / 20000.0)  # whole PWM periods, rounded down


def test_a_bundle_keeps_its_light_through_its_file(led_bundle, tmp_path):
    path = tmp_path / "led.npz"
    save_calibration(path, led_bundle)
    again = load_calibration(path, rig=LED)
    assert again.light == led_bundle.light and again.light_kind == "led"
    np.testing.assert_array_equal(again.line_shapes, led_bundle.line_shapes)


def test_the_dmd_bundle_records_no_light_and_keeps_its_exposures():
    b = oracle_calibration(RigDescription(camera=CAM))
    assert "light" not in b.reports and b.light == {} and b.light_kind == "dmd"
    assert b.whole_periods(0.0123456) == 0.0123456


def test_the_ol490_bundle_records_its_grey_period():
    b = oracle_calibration(RigDescription(light=OL490Parameters(grey_bits=3), camera=CAM))
    assert b.light_kind == "ol490" and b.rows == 7 and b.columns == 1024
    assert b.light["exposure_quantum_s"] == pytest.approx(7 / 9600)


def test_an_led_array_has_no_off_state_light():
    off = Realism(dmd_off_state=0.01)
    assert oracle_calibration(RigDescription(camera=CAM, realism=off)).mirrors_off_light is True
    assert oracle_calibration(replace(LED, realism=off)).mirrors_off_light is False


def test_the_spectral_loop_follows_a_target_the_leds_can_make():
    bundle = oracle_calibration(LED)
    rig = TwinCalibrationRig(LED, scene=white_plate_scene(240, 320))
    g = bundle.wavelengths
    w = fit_levels(bundle.column_matrix, np.where((g >= 400) & (g <= 700), 1.0, 0.0))
    w = 0.4 * w / w.max()
    result = spectral_loop(rig, bundle.column_matrix @ w, bundle=bundle, initial=np.rint(0.7 * w * 255))
    assert result.history[0] > 0.1  # 30 % short of the target
    assert max(result.history[1:]) < 0.008  # one step to the instrument's bandpass floor, and it stays there
