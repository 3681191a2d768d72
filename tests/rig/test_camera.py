"""The camera model: timing rule, responsivity, frame statistics against the analytic noise model, SNR figures."""

import dataclasses
import math

import numpy as np
import pytest

from specgpu.capture.twin_driver import TwinDriver
from specgpu.rig.camera import Camera, CameraParameters, sensitivity_curve
from specgpu.rig.config import RigDescription
from specgpu.rig.light import LightParameters
from specgpu.rig.twin import TwinRig, band_patterns, measure_snr

SMALL = CameraParameters(roi_width=320, roi_height=240)


def small_rig(*, light=None, camera=SMALL, scene="white", seed=0):
    desc = RigDescription(light=light or LightParameters(), camera=camera, seed=seed)
    return TwinRig(desc, scene=scene)


def grab(rig, n):
    driver = TwinDriver(rig, n_frames=n)
    frames = np.empty((n,) + rig.camera.shape, np.uint16)
    infos = []
    driver.start()
    for i in range(n):
        infos.append(driver.fill(frames[i]))
    assert driver.fill(frames[0]) is None
    driver.stop()
    return frames, infos


# ---- timing rule -------------------------------------------------------------------------------------------------
def test_frame_rate_rule_reproduces_the_paper_end_points():
    full = CameraParameters(frame_rate_hz=90.0)
    assert full.max_frame_rate_hz == pytest.approx(200.0, rel=0.005)
    small = CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=90.0)
    assert 775.0 <= small.max_frame_rate_hz <= 785.0
    CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=778.0, exposure_s=1e-3)
    with pytest.raises(ValueError, match=r"frame_rate_hz = 250 exceeds the 200\.\d fps that a 640 x 480 ROI"):
        CameraParameters(frame_rate_hz=250.0, exposure_s=1e-3)


@pytest.mark.parametrize("kwargs, message", [
    (dict(roi_width=300), "camera.roi must be between 320 x 240 and 640 x 480"),
    (dict(roi_height=481), "camera.roi must be between"),
    (dict(bit_depth=9), r"camera.bit_depth must be one of \(8, 10, 12\)"),
    (dict(exposure_s=0.02), "longer than the frame period"),
    (dict(read_noise_e=-1.0), "camera.read_noise_e must be >= 0"),
    (dict(quantum_efficiency_peak=1.5), "camera.quantum_efficiency_peak must be <= 1"),
])
def test_parameters_are_validated(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CameraParameters(**kwargs)


def test_conversion_gain_maps_full_well_to_top_code():
    for bits in (8, 10, 12):
        p = CameraParameters(bit_depth=bits)
        assert p.max_code == 2**bits - 1
        assert p.gain_e_per_dn * p.max_code == pytest.approx(p.full_well_e)


# ---- responsivity ----------------------------------------------------------------------------------------------
def test_responsivity_is_the_camera_equation():
    p = CameraParameters()
    cam = Camera(p)
    wl = np.array([450.0, 560.0, 700.0])
    h, c = 6.62607015e-34, 299792458.0
    m = 9.9 / 48.0
    qe = 0.40 * sensitivity_curve("cmos", wl)
    expected = qe * wl * 1e-9 / (h * c) * (9.9e-6) ** 2 * 0.9 / (4 * 8.0**2 * (1 + m) ** 2)
    np.testing.assert_allclose(cam.responsivity(wl), expected, rtol=1e-12)
    half_aperture = Camera(dataclasses.replace(p, f_number=16.0))
    np.testing.assert_allclose(half_aperture.responsivity(wl), expected / 4, rtol=1e-12)


def test_default_sensitivity_is_broad():
    wl = np.arange(380.0, 781.0)
    v = sensitivity_curve("cmos", wl)
    assert v.max() == pytest.approx(1.0) and wl[np.argmax(v)] == 560
    above = wl[v >= 0.5]
    assert above[0] < 425 and above[-1] > 740  # paper Fig. 6: broad over the visible


def test_sensitivity_csv_override(tmp_path):
    csv = tmp_path / "v.csv"
    csv.write_text("# relative sensitivity\n700 0.5\n400 1.0\n")  # unsorted on purpose
    v = sensitivity_curve(str(csv), np.array([400.0, 550.0, 700.0]))
    np.testing.assert_allclose(v, [1.0, 0.75, 0.5])
    csv.write_text("400,1\n400,2\n")
    with pytest.raises(ValueError, match="400 nm appears more than once"):
        sensitivity_curve(str(csv), np.array([400.0]))


def test_fixed_pattern_maps_are_per_camera():
    a, b, c = Camera(seed=1), Camera(seed=1), Camera(seed=2)
    np.testing.assert_array_equal(a.prnu, b.prnu)
    assert not np.array_equal(a.prnu, c.prnu)
    assert a.prnu.std() == pytest.approx(0.008, rel=0.02)
    assert a.dsnu_e.std() == pytest.approx(20.0, rel=0.02)


# ---- frame statistics ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def steady_frames():
    """200 frames of a white plate under a steady green band, light fluctuation off."""
    rig = small_rig(light=LightParameters(fluctuation_rms=0.0))
    pat = band_patterns(rig.light, [(500.0, 600.0)])
    pat = (pat * 0.5).astype(np.int32)
    rig.load_sequence(pat)
    frames, infos = grab(rig, 200)
    return rig, frames, infos


def test_mean_is_the_integral_of_s_i_v_times_exposure_and_gain(steady_frames):
    rig, frames, _ = steady_frames
    cam, light = rig.camera, rig.light
    p = cam.params
    # Independent evaluation of O = t * integral S I V dlambda (1 nm grid), times field and PRNU, through the gain.
    e = p.exposure_s * np.sum(0.99 * light.emitted_spectrum(0) * cam.responsivity(light.wavelengths))
    expected = (e * rig.field * cam.prnu + p.pedestal_e + p.dark_current_e_per_s * p.exposure_s + cam.dsnu_e)
    expected = expected / p.gain_e_per_dn
    mean = frames.mean(axis=0)
    sd = np.sqrt(cam.temporal_variance_dn(e)) / math.sqrt(len(frames))
    diff = mean - expected
    assert abs(diff.mean()) < 0.02  # DN; rounding half up is unbiased for a continuous signal
    assert np.sqrt(np.mean(diff**2)) == pytest.approx(sd, rel=0.1)  # only the noise of the 200-frame mean is left
    assert 300 < expected.mean() < 900


def test_variance_follows_the_noise_model(steady_frames):
    rig, frames, _ = steady_frames
    cam = rig.camera
    mean_e = (frames.mean(axis=0) * cam.params.gain_e_per_dn - cam.params.pedestal_e
              - cam.dark_electrons() - cam.dsnu_e)
    predicted = cam.temporal_variance_dn(mean_e)  # shot + dark shot + read + 1/12 quantization
    measured = frames.astype(np.float64).var(axis=0, ddof=1)
    assert measured.mean() / predicted.mean() == pytest.approx(1.0, abs=0.02)
    # Shot noise dominates: the variance is far above read noise and quantization alone.
    floor = cam.temporal_variance_dn(0.0)
    assert predicted.mean() > 20 * floor


def test_light_fluctuation_adds_its_own_variance():
    p = LightParameters(fluctuation_rms=0.02, fluctuation_reference_exposure_s=0.0110)
    rig = small_rig(light=p)
    rig.load_sequence(band_patterns(rig.light, [(500.0, 600.0)]) // 2)
    frames, _ = grab(rig, 300)
    means = frames.reshape(300, -1).mean(axis=1)  # frame means: pixel noise averages out, the light does not
    signal_dn = (rig.expected_frame(0) - rig.expected_frame(0, power=0.0)).mean()
    assert means.std(ddof=1) / signal_dn == pytest.approx(0.02, rel=0.15)


def test_response_is_linear_in_the_mirror_count():
    rig = small_rig(light=LightParameters(fluctuation_rms=0.0))
    band = band_patterns(rig.light, [(450.0, 650.0)])[0]
    levels = np.array([0, 32, 64, 128, 192])  # the top one reaches about 3/4 of the full well
    rig.load_sequence(np.stack([(band * (lv / 768)).astype(np.int32) for lv in levels]))
    frames, infos = grab(rig, 5 * 20)
    pidx = np.array([i.pattern_index for i in infos])
    means = np.array([frames[pidx == k].mean() for k in range(5)])
    slope, icpt = np.polyfit(levels, means, 1)
    resid = means - (slope * levels + icpt)
    assert np.abs(resid).max() < 0.002 * means.max()
    assert icpt == pytest.approx(rig.expected_frame(0).mean(), abs=0.1)  # all mirrors off: the dark level


def test_saturation_and_bit_depth():
    bright = LightParameters(illuminance_lux=2e5, fluctuation_rms=0.0)
    for bits in (8, 12):
        cam = dataclasses.replace(SMALL, bit_depth=bits)
        rig = small_rig(light=bright, camera=cam)
        rig.load_sequence(band_patterns(rig.light, [(380.0, 780.0)]))
        frames, _ = grab(rig, 3)
        assert frames.max() == 2**bits - 1
        assert np.mean(frames == 2**bits - 1) > 0.99
    # 8-bit quantization: 1/12 DN^2 of the variance is quantization; dark frames sit on the pedestal.
    rig = small_rig(camera=dataclasses.replace(SMALL, bit_depth=8))
    frames, _ = grab(rig, 50)  # light's default sequence: all mirrors off
    assert frames.max() <= 255
    assert frames.mean() == pytest.approx(rig.expected_frame(0).mean(), abs=0.05)


# ---- the paper's SNR figures ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def snr_runs():
    desc = RigDescription(camera=dataclasses.replace(CameraParameters(), roi_width=320, roi_height=240))
    return [measure_snr(desc, seed=s) for s in range(4)]


def test_sensor_snr_is_44_2_db(snr_runs):
    for r in snr_runs:
        assert r.sensor_db == pytest.approx(44.2, abs=0.5)
        assert r.repeats == 100 and r.frame_rate_hz == 90.0
        for ch in "RGB":
            assert r.sensor_db_per_channel[ch] == pytest.approx(44.2, abs=0.5)
            assert r.mean_dn[ch] == pytest.approx(0.75 * 1023, rel=0.02)


def test_temporal_snr_is_39_1_db(snr_runs):
    # Each run measures mean / std over 100 repeats, as the paper did; the light's fluctuation is common to the
    # whole frame, so one run's estimate carries about 0.25 dB of sampling spread: the mean of four runs is tested
    # at 0.5 dB, each run at 1 dB.
    values = [r.temporal_db for r in snr_runs]
    assert np.mean(values) == pytest.approx(39.1, abs=0.5)
    for v in values:
        assert v == pytest.approx(39.1, abs=1.0)
    assert all(r.temporal_db < r.sensor_db - 3.0 for r in snr_runs)


def test_snr_falls_at_higher_frame_rates():
    desc = RigDescription(camera=dataclasses.replace(CameraParameters(), roi_width=320, roi_height=240))
    # Same signal level (0.15 of the well: what the blue band reaches at 400 fps), so the camera's own SNR is the
    # same and the difference is the lamp's fluctuation, which shorter exposures average less (paper Section 2.F).
    fast = measure_snr(desc, frame_rate_hz=400.0, repeats=60, level=0.15)
    slow = measure_snr(desc, frame_rate_hz=90.0, repeats=60, level=0.15)
    assert fast.exposure_s < slow.exposure_s
    assert fast.sensor_db == pytest.approx(slow.sensor_db, abs=0.3)
    assert fast.temporal_db < slow.temporal_db - 1.5


def test_snr_refuses_a_too_dim_light():
    desc = RigDescription(light=LightParameters(illuminance_lux=500.0),
                          camera=dataclasses.replace(CameraParameters(), roi_width=320, roi_height=240))
    with pytest.raises(ValueError, match="the light is too dim: band B"):
        measure_snr(desc, repeats=2)


def test_expose_gives_the_modelled_mean_and_variance():
    cam = Camera(SMALL, seed=4)
    rng = np.random.default_rng(0)
    frames = np.stack([cam.expose(10000.0, rng) for _ in range(100)]).astype(float)
    expected = cam.expected_dn(10000.0)
    assert np.abs(frames.mean(axis=0) - expected).mean() < 0.6  # 100-frame mean of ~3 DN noise
    assert frames.mean() == pytest.approx(expected.mean(), abs=0.02)
    var = frames.var(axis=0, ddof=1).mean()
    assert var == pytest.approx(cam.temporal_variance_dn(10000.0 * cam.prnu).mean(), rel=0.03)
    with pytest.raises(ValueError, match="signal_e must be >= 0"):
        cam.expose(-1.0, rng)


def test_snr_measurement_ignores_fault_injection_and_pacing():
    from specgpu.rig.config import FaultRates

    base = RigDescription(camera=dataclasses.replace(CameraParameters(), roi_width=320, roi_height=240))
    noisy = dataclasses.replace(base, faults=FaultRates(drop_rate=0.3, duplicate_rate=0.3), pacing="paced")
    a = measure_snr(base, repeats=10, seed=5)
    b = measure_snr(noisy, repeats=10, seed=5)
    assert a.temporal_db == b.temporal_db and a.sensor_db == b.sensor_db
