"""The bench's imperfections: profiles, the [realism] and [drift] tables, each effect on its own, the
rig's clock from calibration to capture."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.calibration import TwinCalibrationRig, rig_fingerprint
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription, dump_rig, load_rig, rig_from_dict
from specgpu.rig.light import ProgrammableLight
from specgpu.rig.realism import LAB, Drift, Realism
from specgpu.rig.scene import colorchecker_scene, white_plate_scene, white_tile_roi
from specgpu.rig.twin import TwinRig, band_patterns

SMALL = CameraParameters(roi_width=320, roi_height=240)
BANDS = [(420.0, 440.0), (540.0, 560.0), (660.0, 680.0)]


def rig(realism=None, drift=None, scene=None, **kw):
    d = RigDescription(camera=SMALL, realism=realism or Realism(), drift=drift or Drift())
    r = TwinRig(d, scene=scene if scene is not None else white_plate_scene(240, 320), **kw)
    r.load_sequence(band_patterns(r.light, BANDS))
    return r


def frames(r):
    return np.stack([r.expected_frame(k) for k in range(len(BANDS))]).astype(np.float64)


@pytest.fixture(scope="module")
def ideal():
    r = rig()
    return r, frames(r)


# ---- configuration ----------------------------------------------------------------------------------------------
def test_profiles_and_overrides():
    assert RigDescription().realism == Realism() and not Realism().any
    lab = rig_from_dict({"twin": {"profile": "lab"}})
    assert lab.realism == LAB and lab.capture_delay == 1800.0
    over = rig_from_dict({"twin": {"profile": "lab"}, "realism": {"stray_light_fraction": 0.01}})
    assert over.realism.stray_light_fraction == 0.01 and over.realism.blur_px == LAB.blur_px
    assert RigDescription(profile="lab").realism == LAB


@pytest.mark.parametrize("table,key,value,word", [
    ("realism", "stray_light_fraction", -0.01, "realism.stray_light_fraction must be >= 0"),
    ("realism", "nonlinearity", 0.5, "realism.nonlinearity must be <= 0.2"),
    ("drift", "lamp_cct_K", -5000, "drift.lamp_cct_K must be >= -1500"),
    ("drift", "lamp_output", 0.9, "drift.lamp_output must be <= 0.5"),
    ("drift", "cut_on_nm", 40, "drift.cut_on_nm must be <= 30"),
])
def test_out_of_range_is_one_line_error(tmp_path, table, key, value, word):
    p = tmp_path / "rig.toml"
    p.write_text(f"[{table}]\n{key} = {value}\n")
    with pytest.raises(ValueError) as err:
        load_rig(p)
    msg = str(err.value)
    assert "\n" not in msg and word in msg and str(p) in msg


def test_unknown_profile_and_key(tmp_path):
    with pytest.raises(ValueError, match="twin.profile must be one of ideal, lab"):
        rig_from_dict({"twin": {"profile": "bench"}})
    with pytest.raises(ValueError, match="unknown key realism.glare"):
        rig_from_dict({"realism": {"glare": 0.1}})


@settings(max_examples=30, deadline=None)
@given(st.floats(-3000, 3000, allow_nan=False), st.floats(-1, 1, allow_nan=False))
def test_drift_validator_property(cct, output):
    ok = -1500 <= cct <= 1500 and -0.5 <= output <= 0.5
    if ok:
        d = Drift(lamp_cct_K=cct, lamp_output=output)
        assert d.lamp_cct_K == cct
    else:
        with pytest.raises(ValueError, match=r"^drift\.lamp_(cct_K|output) must be"):
            Drift(lamp_cct_K=cct, lamp_output=output)


def test_drift_not_in_fingerprint_realism_is(tmp_path):
    base = rig_from_dict({"twin": {"profile": "lab"}})
    drifted = replace(base, drift=Drift(lamp_cct_K=-200, lamp_output=-0.03, cut_on_nm=5))
    assert rig_fingerprint(base) == rig_fingerprint(drifted)
    assert rig_fingerprint(base) != rig_fingerprint(RigDescription())
    assert rig_fingerprint(RigDescription()) == rig_fingerprint(rig_from_dict({"twin": {"profile": "ideal"}}))
    p = tmp_path / "r.toml"
    p.write_text(dump_rig(drifted))
    back = load_rig(p)
    assert back.realism == drifted.realism and back.drift == drifted.drift and back.profile == "lab"


# ---- each effect changes what it should and nothing else ---------------------------------------------------------
def light(**kw):
    return ProgrammableLight(realism=Realism(**{k: v for k, v in kw.items() if k in Realism.keys()}),
                             drift=Drift(**{k: v for k, v in kw.items() if k in Drift().to_dict()}))


BASE = ProgrammableLight()


def test_lamp_output_drift_scales_every_wavelength():
    lt = light(lamp_output=-0.03)
    np.testing.assert_allclose(lt.max_spectrum, 0.97 * BASE.max_spectrum, rtol=1e-12)
    np.testing.assert_array_equal(lt.column_wavelengths, BASE.column_wavelengths)


def test_cct_drift_reddens_and_keeps_the_map():
    lt = light(lamp_cct_K=-200)
    ratio = lt.max_spectrum / BASE.max_spectrum
    assert ratio[BASE.wavelengths == 420][0] < 0.97 and ratio[BASE.wavelengths == 700][0] > 1.01
    assert abs(ratio[BASE.wavelengths == 560][0] - 1) < 2e-3
    np.testing.assert_array_equal(lt.column_wavelengths, BASE.column_wavelengths)


def test_cut_on_shift_acts_only_at_the_violet_end():
    ratio = light(cut_on_nm=5).max_spectrum / BASE.max_spectrum
    wl = BASE.wavelengths
    assert ratio[wl == 400][0] < 0.8
    np.testing.assert_allclose(ratio[wl >= 550], 1.0, atol=2e-3)


def test_stray_light_spreads_a_fraction_broadband():
    lt = light(stray_light_fraction=0.01)
    p = band_patterns(BASE, [(540.0, 560.0)])[0]
    e0, e1 = BASE.pattern_to_spectrum(p), lt.pattern_to_spectrum(p)
    out = (BASE.wavelengths < 500) | (BASE.wavelengths > 600)
    assert abs((e1 - e0).sum() / e0.sum() - 0.01) < 1e-3
    assert e1[out].sum() > 0.003 * e0.sum() and e0[out].sum() < 1e-6 * e0.sum()
    np.testing.assert_array_equal(lt.pattern_to_spectrum(np.zeros(1024, int)), 0.0)


def test_dmd_off_state_lights_the_object_with_every_mirror_off():
    lt = light(dmd_off_state=0.001)
    off = lt.pattern_to_spectrum(np.zeros(1024, int))
    np.testing.assert_allclose(off, 0.001 * BASE.max_spectrum, rtol=1e-9)
    np.testing.assert_allclose(lt.max_spectrum, BASE.max_spectrum, rtol=1e-9)


def test_grating_ripple_and_slit_and_bow():
    rip = light(grating_ripple=0.02).max_spectrum / BASE.max_spectrum
    sel = (BASE.wavelengths > 420) & (BASE.wavelengths < 760)
    assert 0.015 < np.max(np.abs(rip[sel] - 1)) < 0.025
    bow = light(column_bow_nm=1.5)
    shift = bow.column_wavelengths - BASE.column_wavelengths
    assert abs(shift[512] - 1.5) < 0.01 and abs(shift[0]) < 0.01 and abs(shift[-1]) < 0.01
    slit = light(slit_flat_top=0.6, slit_fwhm_slope=0.08)
    np.testing.assert_array_equal(slit.column_wavelengths, BASE.column_wavelengths)

    def fwhm(lt, c):
        col = lt.column_matrix[:, c]
        above = np.flatnonzero(col >= col.max() / 2)
        return above[-1] - above[0]

    assert fwhm(slit, 1000) > fwhm(slit, 20)  # wider at the red end
    col = slit.column_matrix[:, 512] / slit.column_matrix[:, 512].max()
    g = BASE.column_matrix[:, 512] / BASE.column_matrix[:, 512].max()
    assert np.max(np.abs(col - g)) > 0.05  # not the Gaussian


def test_sensor_ripple_changes_the_camera_only(ideal):
    r = rig(Realism(sensor_ripple=0.03))
    ratio = r.camera.responsivity(BASE.wavelengths) / ideal[0].camera.responsivity(BASE.wavelengths)
    assert 0.025 < np.max(np.abs(ratio - 1)) <= 0.0301
    np.testing.assert_array_equal(r.light.max_spectrum, ideal[0].light.max_spectrum)


def test_vignetting_and_field_colour(ideal):
    r0, f0 = ideal
    v = frames(rig(Realism(vignetting=0.06)))
    dark = np.stack([r0.expected_frame(0, power=0.0)] * 3).astype(np.float64)
    s0, sv = f0 - dark, v - dark
    assert abs(sv[1, 120, 160] / s0[1, 120, 160] - 1) < 1e-3
    assert abs(sv[1, 0, 0] / s0[1, 0, 0] - 0.94) < 0.01
    c = frames(rig(Realism(field_colour=0.05))) - dark
    corner_blue, corner_red = c[0, 0, 0] / s0[0, 0, 0], c[2, 0, 0] / s0[2, 0, 0]
    assert corner_blue < 0.98 and corner_red > 1.02
    assert abs(c[1, 120, 160] / s0[1, 120, 160] - 1) < 1e-3


def test_blur_and_lateral_colour_move_edges_not_levels():
    scene = colorchecker_scene(240, 320)
    f0 = frames(rig(scene=scene))
    fb = frames(rig(Realism(blur_px=1.5), scene=scene))
    assert np.abs(np.diff(fb[1], axis=1)).max() < 0.7 * np.abs(np.diff(f0[1], axis=1)).max()
    m = list(scene.masks.values())[21]  # neutral 5
    assert abs(fb[1][m].mean() / f0[1][m].mean() - 1) < 2e-3
    fc = frames(rig(Realism(lateral_ca_px=3.0), scene=scene))
    # the red image is magnified, the blue one shrunk: at the chart's corners they differ, in its middle not
    assert np.abs(fc[2] - f0[2])[:, :40].mean() > 5 * np.abs(fc[2] - f0[2])[100:140, 140:180].mean()


def test_ambient_adds_light_to_every_frame_even_all_off(ideal):
    r0, f0 = ideal
    r = rig(Realism(ambient_lux=5.0))
    off0 = r0.expected_frame(0, power=0.0)
    r.load_sequence(np.zeros((1, 1024), np.int32))
    r0b = rig()
    r0b.load_sequence(np.zeros((1, 1024), np.int32))
    assert r.expected_frame(0).mean() > r0b.expected_frame(0).mean() + 0.5
    assert float(np.abs(off0 - r0b.expected_frame(0)).max()) < 1e-3


def test_nonlinearity_compresses_near_full_well_only():
    r0 = rig()
    r1 = rig(Realism(nonlinearity=0.02))
    top = r0.camera.params.max_code
    dark = r0.expected_frame(0, power=0.0)
    for power in (0.05, 1.0):
        s0 = r0.expected_frame(1, power) - dark
        s1 = r1.expected_frame(1, power) - dark
        x = float(s0[120, 160])
        assert abs(float(s1[120, 160]) / x - (1 - 0.02 * (x / top) ** 2)) < 1e-4


def test_white_tile_scene_and_true_white():
    s = colorchecker_scene(240, 320, white_tile=0.98)
    x, y, w, h = white_tile_roi(240, 320)
    assert np.all(s.reflectance[y:y + h, x:x + w] == np.float32(0.98))
    assert len(s.masks) == 24


# ---- the clock ---------------------------------------------------------------------------------------------------
def test_clock_runs_through_calibration_and_sets_the_capture_start():
    d = RigDescription(camera=SMALL, realism=Realism(lamp_output_drift_per_hour=-0.18))
    cal = TwinCalibrationRig(d)
    t0 = cal.clock_s
    cal.capture_mean(np.zeros((2, 1024), np.int32), 3)
    assert cal.clock_s - t0 == pytest.approx(6 * cal.rig.frame_period_s)
    cal.measure_spectrum(0)
    assert cal.clock_s - t0 == pytest.approx(6 * cal.rig.frame_period_s + cal.SPECTRUM_READ_S)
    # a capture starting 1000 s on sees the lamp 0.05 % dimmer (-0.18 / h)
    late = TwinRig(replace(d, light=replace(d.light, fluctuation_rms=0.0)), scene=white_plate_scene(240, 320),
                   clock_start_s=1000.0)
    late.load_sequence(band_patterns(late.light, BANDS))
    _, f = late.render(0, 0, 0.0)
    assert f == pytest.approx(1 - 0.18 * 1000 / 3600)


def test_capture_clock_starts_where_calibration_ended(monkeypatch):
    import specgpu.pipeline.twin_capture as pipeline

    seen = {}

    class Stop(Exception):
        pass

    def fake(desc, scene=None, clock_start_s=0.0, **kw):
        seen["clock"] = clock_start_s
        raise Stop

    monkeypatch.setattr(pipeline, "TwinRig", fake)

    class Bundle:
        reports = {"rig_clock_end_s": 42.0}

    class Plan:
        target_spectra = np.zeros((1, 3))
        light_wavelengths = np.array([400.0, 500.0, 600.0])

        def rig_description(self, d):
            return d

    d = rig_from_dict({"twin": {"profile": "lab"}})
    with pytest.raises(Stop):
        pipeline.capture_plan(d, Plan(), None, calibration=Bundle())
    assert seen["clock"] == 42.0 + 1800.0


def test_colour_drifts_frame_by_frame_within_a_capture():
    """The colour temperature's drift per hour acts on each frame's timestamp, not only at the clock start: a
    blue band loses and a red band gains in proportion to the time since the start; without it nothing moves."""
    fast = Realism(lamp_cct_drift_K_per_hour=-500.0)
    r = rig(realism=fast, scene=white_plate_scene(240, 320))
    r.light.params = replace(r.light.params, fluctuation_rms=0.0)
    p0 = [r.render(k, frame_id=k, timestamp_s=0.0)[1] for k in range(3)]
    p1 = [r.render(k, frame_id=k, timestamp_s=3600.0)[1] for k in range(3)]
    np.testing.assert_allclose(p0, 1.0, rtol=1e-12)
    ratio = np.array(p1) / np.array(p0)
    # -500 K from 6000 K: the Planck ratio (normalised at 560 nm) weighted by each band's light on the camera,
    # -11 % at 430 nm and +8 % at 670 nm; first order in the change, so within 1 % of it
    from specgpu.rig.light import lamp_change

    wl = r.light.wavelengths
    w = r.light.sequence_spectra * r.camera.responsivity(wl)[None, :]
    exact = (w @ lamp_change(r.light.params, wl, -500.0, 0.0)) / w.sum(axis=1)
    assert exact[0] < 0.9 and exact[2] > 1.05
    np.testing.assert_allclose(ratio, exact, atol=0.01)
    half = np.array([r.render(k, frame_id=k, timestamp_s=1800.0)[1] for k in range(3)])
    np.testing.assert_allclose(half - 1.0, (ratio - 1.0) / 2.0, rtol=1e-9)
    still = rig(realism=Realism(lamp_output_drift_per_hour=0.0))
    still.light.params = replace(still.light.params, fluctuation_rms=0.0)
    assert [still.render(k, frame_id=k, timestamp_s=3600.0)[1] for k in range(3)] == [1.0, 1.0, 1.0]
