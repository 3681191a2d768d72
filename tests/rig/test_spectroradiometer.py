"""The spectroradiometer of the spectral feedback loop: bandpass, sampling, noise, scale error."""

import numpy as np
import pytest

from specgpu.rig.config import RigDescription, load_rig
from specgpu.rig.light import ProgrammableLight
from specgpu.rig.spectroradiometer import Spectroradiometer, SpectroradiometerParameters
from specgpu.rig.twin import TwinRig


def test_flat_spectrum_reads_back_unchanged_and_a_line_takes_the_bandpass():
    meter = Spectroradiometer(SpectroradiometerParameters(noise_rms=0.0, noise_floor=0.0))
    wl = np.arange(300.0, 900.0, 0.5)
    np.testing.assert_allclose(meter.measure(np.full(wl.size, 2.0), wl), 2.0, rtol=1e-9)
    line = np.where(wl == 550.0, 1.0, 0.0)
    got = meter.measure(line, wl)
    assert meter.wavelengths[np.argmax(got)] == 550.0
    # Triangular bandpass, 5 nm FWHM: the line reads half its peak 2.5 nm away, nothing beyond 5 nm.
    peak = got.max()
    assert got[meter.wavelengths == 552.0][0] / peak == pytest.approx(1 - 2 / 5)
    assert got[np.abs(meter.wavelengths - 550) >= 5].max() == 0.0
    assert got.sum() * 1.0 == pytest.approx(0.5, rel=1e-9)  # line energy (0.5 nm bin) conserved


def test_noise_and_scale_error():
    p = SpectroradiometerParameters(noise_rms=0.01, noise_floor=0.0, scale_error=0.02, step_nm=5.0)
    meter = Spectroradiometer(p, seed=1)
    wl = np.arange(380.0, 781.0)
    reads = np.stack([meter.measure(np.ones(wl.size), wl) for _ in range(400)])
    inner = slice(2, -2)
    assert reads[:, inner].mean() == pytest.approx(1.02, rel=1e-3)
    assert reads[:, inner].std(axis=0).mean() == pytest.approx(0.0102, rel=0.05)
    assert meter.wavelengths.size == 81


def test_twin_measures_its_light():
    rig = TwinRig(RigDescription(), scene="white")
    pat = np.zeros((1, 1024), np.int32)
    pat[0, 300:700] = 500
    rig.load_sequence(pat)
    wl, measured = rig.measure_spectrum(0)
    truth = rig.light.emitted_spectrum(0)
    np.testing.assert_array_equal(wl, rig.light.wavelengths)
    inner = (wl > 520) & (wl < 640)
    assert np.abs(measured[inner] / truth[inner] - 1).mean() < 0.01


def test_parameters_from_toml_and_validation(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text("[spectroradiometer]\nbandwidth_nm = 2.0\nstep_nm = 2\n")
    d = load_rig(path)
    assert d.spectroradiometer.bandwidth_nm == 2.0 and d.spectroradiometer.step_nm == 2.0
    path.write_text("[spectroradiometer]\nbandwith_nm = 2.0\n")
    with pytest.raises(ValueError, match="unknown key spectroradiometer.bandwith_nm"):
        load_rig(path)
    with pytest.raises(ValueError, match="spectroradiometer.noise_rms must be <= 1"):
        SpectroradiometerParameters(noise_rms=2.0)
    with pytest.raises(ValueError, match="spectrum must be >= 0"):
        Spectroradiometer().measure(-np.ones(3), np.array([400.0, 500.0, 600.0]))
    assert ProgrammableLight().wavelengths.size == Spectroradiometer().wavelengths.size
