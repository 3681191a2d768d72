"""Every programmable light: ``[light] kind = "dmd" | "led" | "ol490"``, the LED array's model (spectra, PWM,
rise and fall, droop and peak shift, cross-talk) and the OL490's grey depth against its frame rate."""

import tomllib
import warnings

import numpy as np
import pytest

from specgpu.rig.config import RigDescription, dump_rig, load_rig, rig_from_dict
from specgpu.rig.led import LED_PRESETS, LEDLight, LEDParameters, period_levels
from specgpu.rig.light import K_M, LightParameters, photopic_y
from specgpu.rig.lights import light_kind, make_light
from specgpu.rig.ol490 import SLIT_FWHM_NM, OL490Parameters
from specgpu.rig.twin import TwinRig

SMALL = "[camera]\nroi_width = 320\nroi_height = 240\n"


def rig_file(tmp_path, light: str, name="rig.toml"):
    path = tmp_path / name
    path.write_text("[light]\n" + light + "\n" + SMALL)
    return path


def centroid(light, spectrum):
    return float(spectrum @ light.wavelengths / spectrum.sum())


def test_an_led_preset_is_enough(tmp_path):
    d = load_rig(rig_file(tmp_path, 'kind = "led"\npreset = "led12"'))
    assert isinstance(d.light, LEDParameters) and light_kind(d.light) == "led"
    assert d.light.columns == 12 and d.light.rows == 255
    rig = TwinRig(d)
    light = rig.light
    assert light.column_matrix.shape == (light.wavelengths.size, 12)
    np.testing.assert_allclose(light.column_wavelengths, LED_PRESETS["led12"])
    # each LED alone peaks at its own wavelength; all on gives the rig's illuminance
    one = np.eye(12, dtype=np.int32) * 255
    peaks = light.wavelengths[np.argmax(light.pattern_to_spectrum(one), axis=1)]
    np.testing.assert_allclose(peaks, LED_PRESETS["led12"], atol=0.5)
    lux = K_M * light.pattern_to_spectrum(np.full(12, 255)) @ photopic_y(light.wavelengths)
    assert lux == pytest.approx(d.light.illuminance_lux, rel=1e-9)
    rig.load_sequence(one[:3])
    frame, _ = rig.render(0, 0, 0.0)
    assert frame.shape == (240, 320) and frame.mean() == pytest.approx(rig.expected_frame(0).mean(), abs=0.5)
    assert rig.expected_frame(0).mean() > 40  # lit well above the dark level (about 25 DN)


def test_the_dmd_stays_the_default_and_its_description_unchanged(tmp_path):
    default = load_rig(None)
    assert type(default.light) is LightParameters and "kind" not in default.to_dict()["light"]
    explicit = load_rig(rig_file(tmp_path, 'kind = "dmd"'))
    assert explicit.light == LightParameters()


@pytest.mark.parametrize("light, words", [
    ('kind = "laser"', ("light.kind", "dmd, led, ol490")),
    ('kind = "led"\npwm_bits = 0', ("light.pwm_bits",)),
    ('kind = "led"\npeaks_nm = [500, 450]', ("light.peaks_nm", "increasing")),
    ('kind = "led"\npeaks_nm = [450, 500]\nfwhm_nm = [20, 20, 20]', ("light.fwhm_nm", "one per LED")),
    ('kind = "led"\nlamp = "xenon"', ("unknown key light.lamp",)),
    ('kind = "led"\npreset = "led99"', ("light.preset", "led12")),
    ('kind = "led"\npwm_mismatch = "ignore"', ("light.pwm_mismatch",)),
    ('kind = "led"\nspectra = "missing.csv"', ("light.spectra", "not found")),
    ('kind = "led"\ncrosstalk = 0.5', ("light.crosstalk",)),
    ('kind = "ol490"\ngrey_bits = 7', ("light.grey_bits",)),
    ('kind = "ol490"\nslit = 5', ("light.slit",)),
    ('kind = "ol490"\ngrey_bits = 4\nrows = 100', ("light.rows", "grey_bits")),
])
def test_every_new_key_is_checked_in_one_line_naming_the_file(tmp_path, light, words):
    path = rig_file(tmp_path, light)
    with pytest.raises(ValueError) as err:
        load_rig(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    for w in words:
        assert w in msg


@pytest.mark.parametrize("light", ['kind = "led"\npreset = "led16"\ncrosstalk = 0.01\npeak_shift_nm_per_K = 0.1',
                                   'kind = "led"\npeaks_nm = [450, 550, 650]\nfwhm_nm = [20]',
                                   'kind = "ol490"\ngrey_bits = 3\nslit = 4'])
def test_a_light_round_trips_through_its_toml(tmp_path, light):
    d = load_rig(rig_file(tmp_path, light))
    again = rig_from_dict(tomllib.loads(dump_rig(d)))
    assert again.light == d.light


def test_measured_spectra_from_a_csv(tmp_path):
    wl = np.arange(380, 781, 2.0)
    cols = [np.exp(-0.5 * ((wl - c) / 10.0) ** 2) for c in (600.0, 450.0, 520.0)]  # out of order on purpose
    (tmp_path / "leds.csv").write_text("wavelength,a,b,c\n" + "\n".join(
        f"{w:g},{a:.6g},{b:.6g},{c:.6g}" for w, a, b, c in zip(wl, *cols)))
    d = load_rig(rig_file(tmp_path, 'kind = "led"\nspectra = "leds.csv"'))
    assert d.light.columns == 3 and d.light.line_fwhm_nm == pytest.approx(2.3548 * 10.0, abs=0.3)
    light = TwinRig(d).light
    np.testing.assert_allclose(light.column_wavelengths, [450.0, 520.0, 600.0], atol=0.05)  # in order of wavelength
    # the shape is the file's: one LED alone has a 10 nm sigma
    s = light.pattern_to_spectrum([0, 255, 0])
    c = centroid(light, s)
    sigma = np.sqrt(s @ (light.wavelengths - c) ** 2 / s.sum())
    assert sigma == pytest.approx(10.0, rel=0.01)


def test_pwm_levels_over_partial_periods():
    assert period_levels(np.array([0.8]), 2.5)[0] == pytest.approx((2 * 0.8 + 0.5) / 2.5)
    assert period_levels(np.array([0.3]), 2.5)[0] == pytest.approx((2 * 0.3 + 0.3) / 2.5)
    np.testing.assert_array_equal(period_levels(np.array([0.3, 0.7]), 40.0), [0.3, 0.7])


def test_an_exposure_not_of_whole_pwm_periods_is_refused_or_warned(tmp_path):
    refuse = LEDLight(LEDParameters(pwm_mismatch="refuse", pwm_frequency_hz=1000.0), exposure_s=0.0105)
    with pytest.raises(ValueError, match=r"not a whole number of PWM periods at light.pwm_frequency_hz = 1000"):
        refuse.check_exposure(0.0105, "camera.exposure_s")
    warn = LEDLight(LEDParameters(pwm_frequency_hz=1000.0), exposure_s=0.0105)
    with pytest.warns(UserWarning, match="not a whole number of PWM periods"):
        warn.check_exposure(0.0105, "camera.exposure_s")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn.check_exposure(0.010, "camera.exposure_s")  # ten periods: silent
    with pytest.raises(ValueError, match="shorter than one PWM period"):
        warn.check_exposure(0.0005, "camera.exposure_s")
    # the partial period is in the light the exposure sees: a duty under one half over 10.5 periods is on 11
    # times, all on is on throughout
    half = warn.pattern_to_spectrum(np.full(12, 127)).sum()
    full = warn.pattern_to_spectrum(np.full(12, 255)).sum()
    assert half / full == pytest.approx(11 * (127 / 255) / 10.5, rel=1e-9)


def test_rise_and_fall_shift_a_partial_duty_only():
    p = LEDParameters(rise_time_s=5e-6, fall_time_s=2e-6, pwm_frequency_hz=10000.0)
    light = LEDLight(p)
    w = light.effective_levels(np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(w, [0.0, 0.5 - 3e-6 * 1e4, 1.0])
    assert p.switch_time_s == pytest.approx(p.settle_s + 25e-6)


def test_thermal_droop_and_peak_shift_follow_the_duty_and_the_clock():
    hot = LEDParameters(junction_K_per_duty=40.0, droop_per_K=0.004, peak_shift_nm_per_K=0.1,
                        thermal_time_constant_s=60.0)
    warm = LEDLight(hot, clock_s=1e6)
    one = np.zeros(12, np.int32)
    one[8] = 255
    low = one * 51 // 255
    # full duty heats the junction by 40 K: 16 % less light than linear, the peak 4 nm to the red
    ratio = warm.pattern_to_spectrum(one).sum() / (5 * warm.pattern_to_spectrum(low).sum())
    assert ratio == pytest.approx((1 - 0.004 * 40) / (1 - 0.004 * 8), rel=1e-6)
    shift = centroid(warm, warm.pattern_to_spectrum(one)) - centroid(warm, warm.pattern_to_spectrum(low))
    assert shift == pytest.approx(0.1 * 32, abs=0.05)
    cold = LEDLight(hot, clock_s=0.0)  # just switched on: the junction has not warmed yet
    np.testing.assert_allclose(cold.pattern_to_spectrum(one), LEDLight(LEDParameters()).pattern_to_spectrum(one))


def test_crosstalk_lights_the_neighbours():
    light = LEDLight(LEDParameters(crosstalk=0.02))
    w = light.effective_levels(np.eye(12)[5])
    np.testing.assert_allclose(w[[4, 5, 6]], [0.02, 1.0, 0.02])
    assert w[[0, 1, 2, 3, 7, 8, 9, 10, 11]].max() == 0


def test_the_ol490_trades_grey_depth_for_frame_rate(tmp_path):
    d = load_rig(rig_file(tmp_path, 'kind = "ol490"\ngrey_bits = 6\nslit = 3'))
    p = d.light
    assert isinstance(p, OL490Parameters) and p.rows == 63 and p.line_fwhm_nm == SLIT_FWHM_NM[3]
    assert p.columns == 1024
    periods = {b: OL490Parameters(grey_bits=b).grey_period_s for b in range(1, 7)}
    assert periods[1] == pytest.approx(1 / 9600) and periods[6] == pytest.approx(63 / 9600)
    rates = [OL490Parameters(grey_bits=b).max_spectra_per_s for b in range(1, 7)]
    assert all(a > b for a, b in zip(rates, rates[1:]))
    light = make_light(OL490Parameters(grey_bits=6), exposure_s=2 * periods[6])
    with pytest.raises(ValueError, match="grey period .* light.grey_bits = 6"):
        light.check_exposure(periods[6] / 2, "camera.exposure_s")
    # whole grey periods give the level exactly; a level sits in 63 steps
    np.testing.assert_allclose(light.pattern_to_spectrum(np.full(1024, 63)), light.max_spectrum, rtol=1e-12)
    bad = load_rig(rig_file(tmp_path, 'kind = "ol490"\ngrey_bits = 6', "fast.toml"))
    fast = RigDescription(light=bad.light, camera=bad.camera.__class__(roi_width=320, roi_height=240,
                                                                       exposure_s=0.002))
    with pytest.raises(ValueError, match="camera.exposure_s .* grey period"):
        TwinRig(fast)
