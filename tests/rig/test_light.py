"""The programmable light source: DMD pattern <-> spectrum, timing limits, spot profile, lamp behaviour."""

import dataclasses
import math

import colour
import numpy as np
import pytest

from specgpu.rig.light import K_M, LightParameters, ProgrammableLight, lamp_spd, photopic_y


@pytest.fixture(scope="module")
def light():
    return ProgrammableLight()


def test_grid_and_columns(light):
    assert light.wavelengths[0] == 380 and light.wavelengths[-1] == 780 and light.wavelengths.size == 401
    cw = light.column_wavelengths
    assert cw.size == 1024
    np.testing.assert_allclose(np.diff(cw), 400 / 1024)
    assert 380 < cw[0] < 380.4 and 779.6 < cw[-1] < 780


def test_every_mirror_on_gives_the_rated_illuminance(light):
    full = np.full(1024, 768)
    spd = light.pattern_to_spectrum(full)
    lux = K_M * np.sum(spd * photopic_y(light.wavelengths))
    assert lux == pytest.approx(15000.0, rel=1e-9)
    np.testing.assert_allclose(spd, light.max_spectrum)


def test_emission_is_linear_in_mirror_counts(light):
    rng = np.random.default_rng(3)
    a, b = rng.integers(0, 385, (2, 1024))
    sa, sb, sab = light.pattern_to_spectrum(a), light.pattern_to_spectrum(b), light.pattern_to_spectrum(a + b)
    np.testing.assert_allclose(sab, sa + sb, rtol=1e-12, atol=1e-15)
    assert np.all(light.pattern_to_spectrum(np.zeros(1024, int)) == 0)


def test_single_column_band_has_the_slit_width(light):
    n = np.zeros(1024, int)
    n[512] = 768
    spd = light.pattern_to_spectrum(n)
    centre = light.column_wavelengths[512]
    assert abs(light.wavelengths[np.argmax(spd)] - centre) <= 0.5
    # Gaussian slit of 5 nm FWHM: half maximum 2.5 nm either side of the centre (1 nm grid, linear interpolation).
    peak = spd.max()
    assert np.interp(centre + 2.5, light.wavelengths, spd) / peak == pytest.approx(0.5, abs=0.03)
    assert np.interp(centre - 2.5, light.wavelengths, spd) / peak == pytest.approx(0.5, abs=0.03)


def test_xenon_model_is_weak_in_the_violet():
    wl = np.arange(380.0, 781.0)
    spd = lamp_spd(LightParameters(), wl)
    assert spd.max() == pytest.approx(1.0)
    # Paper Fig. 3: low output at the short-wavelength end.
    assert spd[wl == 390][0] < 0.15 and spd[wl == 550][0] > 0.7
    # The Xe I line at 467.1 nm stands out of the continuum.
    assert spd[wl == 467][0] > spd[wl == 455][0]


def test_lamp_csv_override(tmp_path):
    csv = tmp_path / "lamp.csv"
    csv.write_text("wavelength,value\n380,1\n580,1\n780,1\n")
    flat = ProgrammableLight(LightParameters(lamp=str(csv)))
    inner = flat.max_spectrum[20:-20]
    assert inner.std() / inner.mean() < 1e-6
    csv.write_text("380,1\n480,nan\n")
    with pytest.raises(ValueError, match=r"lamp.csv:2: NaN"):
        ProgrammableLight(LightParameters(lamp=str(csv)))


def test_kinoton_lamp_is_available_and_dark_in_the_far_red():
    light = ProgrammableLight(LightParameters(lamp="kinoton-75p"))
    assert light.max_spectrum[light.wavelengths == 750][0] < 0.05 * light.max_spectrum.max()


@pytest.mark.parametrize("name, target_fn", [
    ("D65", lambda wl: np.interp(wl, colour.SDS_ILLUMINANTS["D65"].wavelengths, colour.SDS_ILLUMINANTS["D65"].values)),
    ("A", lambda wl: np.interp(wl, colour.SDS_ILLUMINANTS["A"].wavelengths, colour.SDS_ILLUMINANTS["A"].values)),
    ("narrow 550", lambda wl: np.exp(-0.5 * ((wl - 550) / 5.0) ** 2)),
])
def test_spectrum_to_pattern_round_trip_error_is_bounded(light, name, target_fn):
    target = target_fn(light.wavelengths)
    fit = light.spectrum_to_pattern(target, light.wavelengths, fit="scale")
    assert fit.pattern.dtype == np.int32 and fit.pattern.min() >= 0 and fit.pattern.max() <= 768
    assert fit.clipped == 0.0
    np.testing.assert_allclose(fit.emitted, light.pattern_to_spectrum(fit.pattern))
    # Round-trip error relative to the target's peak. Over 380-780 nm it is dominated by the range edges, where
    # the slit function of the outermost columns has no neighbours beyond 380 / 780 nm; inside 390-770 nm what is
    # left is D65's fine structure (narrower than the 5 nm slit) and the 1/768 mirror quantization.
    bound = {"D65": 0.01, "A": 0.015, "narrow 550": 0.005}[name]
    assert fit.relative_rmse < bound
    inner = (light.wavelengths >= 390) & (light.wavelengths <= 770)
    inner_rmse = np.sqrt(np.mean((fit.emitted - fit.target)[inner] ** 2)) / fit.target.max()
    assert inner_rmse < 0.003
    # Pattern -> spectrum -> pattern -> spectrum reproduces the spectrum to the mirror quantization.
    again = light.spectrum_to_pattern(fit.emitted)
    assert again.relative_rmse < 0.003


def test_target_beyond_the_lamp_is_clipped_and_reported(light):
    target = 2.0 * light.max_spectrum
    fit = light.spectrum_to_pattern(target)
    assert fit.clipped > 0.9
    assert np.all(fit.pattern >= 767)
    scaled = light.spectrum_to_pattern(target, fit="scale")
    assert scaled.scale == pytest.approx(0.995 / 2.0)
    assert scaled.clipped == 0.0


def test_spectrum_to_pattern_rejects_bad_targets(light):
    with pytest.raises(ValueError, match="target contains 1 NaN"):
        t = np.ones(401)
        t[7] = np.nan
        light.spectrum_to_pattern(t)
    with pytest.raises(ValueError, match="target must be >= 0"):
        light.spectrum_to_pattern(-np.ones(401))
    with pytest.raises(ValueError, match=r"target must have shape \(401,\)"):
        light.spectrum_to_pattern(np.ones(50))
    with pytest.raises(ValueError, match="fit must be one of"):
        light.spectrum_to_pattern(np.ones(401), fit="stretch")


def test_patterns_are_validated(light):
    with pytest.raises(ValueError, match=r"mirror counts must lie in \[0, 768\]"):
        light.pattern_to_spectrum(np.full(1024, 769))
    with pytest.raises(ValueError, match="1024 columns"):
        light.pattern_to_spectrum(np.zeros(1000, int))
    with pytest.raises(ValueError, match="integer mirror counts"):
        light.pattern_to_spectrum(np.full(1024, 0.5))


def test_mirror_image_has_the_counted_mirrors_on(light):
    n = np.random.default_rng(0).integers(0, 769, 1024)
    mirrors = light.pattern_to_mirrors(n)
    assert mirrors.shape == (768, 1024)
    np.testing.assert_array_equal(mirrors.sum(axis=0), n)


def test_exposure_shorter_than_switch_time_is_refused(light):
    assert light.minimum_exposure_s == pytest.approx(80e-6)
    assert light.check_exposure(80e-6) == 80e-6
    with pytest.raises(ValueError, match=r"79\.0 us is shorter than .* 80 us \(62 us load \+ 18 us mirror"):
        light.check_exposure(79e-6)


def test_sequence_and_trigger_cycle():
    light = ProgrammableLight()
    pats = np.zeros((3, 1024), int)
    for k in range(3):
        pats[k, 300 * k:300 * k + 100] = 100 * (k + 1)
    light.load_sequence(pats)
    assert light.pattern_index == 0
    assert [light.trigger() for _ in range(5)] == [1, 2, 0, 1, 2]
    np.testing.assert_allclose(light.emitted_spectrum(), light.pattern_to_spectrum(pats[2]))
    light.set_steady(pats[1])
    assert light.sequence.shape == (1, 1024) and light.trigger() == 0
    with pytest.raises(ValueError, match=r"shape \(K, 1024\)"):
        light.load_sequence(np.zeros(1024, int))


def test_flicker_and_drift_are_averaged_over_the_exposure():
    p = LightParameters(fluctuation_rms=0.0, flicker_amplitude=0.1, flicker_frequency_hz=100.0, drift_per_hour=0.036)
    light = ProgrammableLight(p)
    t = np.array([0.0, 0.0025, 3600.0])
    f = light.power_factors(t, 0.01)  # a whole number of ripple periods: the ripple averages out
    np.testing.assert_allclose(f, 1.0 + 0.036 * t / 3600.0, atol=1e-12)
    f = light.power_factors(np.array([0.0]), 0.0025)  # a quarter period from a zero crossing of sin
    assert f[0] == pytest.approx(1.0 + 0.1 * 2 / math.pi, rel=1e-9)


def test_fluctuation_statistics_follow_the_exposure():
    light = ProgrammableLight(LightParameters(fluctuation_rms=0.01, fluctuation_reference_exposure_s=0.01))
    rng = np.random.default_rng(5)
    f = light.power_factors(np.zeros(40000), 0.0025, rng)
    assert f.mean() == pytest.approx(1.0, abs=3e-4)
    assert f.std() == pytest.approx(0.02, rel=0.02)  # sqrt(0.01 / 0.0025) = 2x the reference RMS


def test_field_profile_matches_paper_figures_4_and_5():
    light = ProgrammableLight()
    prof = light.field_profile(480, 640, 0.048)
    assert prof.dtype == np.float32 and prof.shape == (480, 640)
    assert prof.max() <= 1.0 and prof[239:241, 319:321].min() > 0.9999
    # Default spot: good uniformity (paper Fig. 4), a few per cent fall-off in the corners.
    assert 0.95 < prof[0, 0] < 0.97  # about 4 % in the corners
    # Half maximum at half the spot diameter.
    flat = ProgrammableLight(LightParameters(spot_diameter_mm=10.0))
    row = flat.field_profile(1, 2001, 0.01)[0]
    assert row[1000 + 500] == pytest.approx(0.5, abs=1e-3)
    # Fig. 5: the same flux over a wider spot gives less illuminance.
    assert light.centre_illuminance(160.0) == pytest.approx(15000.0 / 4)


def test_second_order_leakage_adds_violet_to_red_columns_only():
    clean = ProgrammableLight()
    leaky = ProgrammableLight(LightParameters(second_order_leakage=0.05))
    red = np.zeros(1024, int)
    red[clean.column_wavelengths > 765] = 768
    s0, s1 = clean.pattern_to_spectrum(red), leaky.pattern_to_spectrum(red)
    violet = (clean.wavelengths >= 380) & (clean.wavelengths <= 395)
    assert s0[violet].max() < 1e-12 < s1[violet].max()
    green = np.zeros(1024, int)
    green[(clean.column_wavelengths > 500) & (clean.column_wavelengths < 600)] = 768
    g0, g1 = clean.pattern_to_spectrum(green), leaky.pattern_to_spectrum(green)
    # Both normalized to the same illuminance; the second order of green columns is UV, outside the grid.
    np.testing.assert_allclose(g1 / g1.max(), g0 / g0.max(), atol=1e-3)


@pytest.mark.parametrize("key, value, message", [
    ("columns", 1, "light.columns must be >= 2"),
    ("line_fwhm_nm", 0.0, "light.line_fwhm_nm must be > 0"),
    ("fluctuation_rms", float("nan"), "light.fluctuation_rms must be finite"),
    ("illuminance_lux", -5.0, "light.illuminance_lux must be > 0"),
    ("wavelength_max_nm", 385.0, "must exceed wavelength_min_nm"),
])
def test_parameters_are_validated(key, value, message):
    with pytest.raises(ValueError, match=message):
        LightParameters(**{key: value})


def test_parameters_are_frozen():
    p = LightParameters()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.rows = 10


def test_illuminance_and_spectral_distribution_targets(light):
    full = np.full(1024, 768)
    assert light.illuminance(full) == pytest.approx(15000.0)
    assert light.illuminance(full // 2) == pytest.approx(7500.0, rel=1e-3)
    sd = colour.SDS_ILLUMINANTS["D65"]
    a = light.spectrum_to_pattern(sd, fit="scale")
    b = light.spectrum_to_pattern(sd.values, sd.wavelengths, fit="scale")
    np.testing.assert_array_equal(a.pattern, b.pattern)
    with pytest.raises(ValueError, match="wavelengths must not be given"):
        light.spectrum_to_pattern(sd, sd.wavelengths)
