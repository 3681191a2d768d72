"""The residual check's chi2 on the device against the NumPy reference (:func:`specgpu.motion.residual.
residual_chi2`), on synthetic samples with a known covariance."""

from __future__ import annotations

import numpy as np
import pytest

from specgpu.engine.residual import residual_chi2_device
from specgpu.motion.residual import ResidualCheck, residual_chi2
from specgpu.planning.noise import NoiseModel


def _check(N: int, R: int, seed: int = 0) -> ResidualCheck:
    rng = np.random.default_rng(seed)
    project = rng.normal(size=(R, N))
    m = rng.normal(size=(R, R))
    return ResidualCheck(K=N, frames=tuple(range(N)), project=project, mismatch=m @ m.T + np.eye(R),
                         noise=NoiseModel(gain_e_per_dn=2.5, read_var_dn2=4.0, light_rms=0.01), threshold=20.0)


@pytest.mark.parametrize("variant", ["cpu", "gpu"])  # 8 pixels per work-item as vectors, or one
@pytest.mark.parametrize(("N", "R"), [(9, 4), (5, 1), (12, 7)])
def test_device_chi2_equals_the_numpy_reference(N, R, variant, monkeypatch):
    monkeypatch.setenv("SPECGPU_VARIANT", variant)
    rng = np.random.default_rng(N)
    check = _check(N, R)
    samples = rng.uniform(0.0, 800.0, size=(23, 41, N)).astype(np.float32)  # 943 pixels: a partial last vector
    samples[::5, ::3] += rng.normal(0.0, 60.0, size=samples[::5, ::3].shape).astype(np.float32)  # disagreeing
    samples[2, 3, 1] = np.nan  # outside the field
    samples[4, 5, 0] = -3.0  # below dark: no shot noise
    gain = rng.uniform(0.8, 1.2, size=(23, 41)).astype(np.float32)
    gain[6, 7] = np.nan  # no response: read as 1
    gain[8, 9] = 0.0
    want = residual_chi2(samples, check, gain)
    nm = check.noise
    got, flagged = residual_chi2_device(samples, check.project, check.mismatch, gain_e_per_dn=nm.gain_e_per_dn,
                                        read_var_dn2=nm.read_var_dn2, light_rms=nm.light_rms,
                                        threshold=check.threshold, gain=gain)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(got[2, 3])
    np.testing.assert_allclose(np.nan_to_num(got), np.nan_to_num(want), rtol=2e-4, atol=1e-3)
    near = np.abs(np.nan_to_num(want) - check.threshold) < 1e-2 * check.threshold
    np.testing.assert_array_equal(flagged[~near], (np.nan_to_num(want) > check.threshold)[~near])
    assert 0 < flagged.sum() < flagged.size


def test_without_a_flat_field_every_gain_is_one():
    check = _check(6, 3, seed=3)
    samples = np.random.default_rng(1).uniform(0.0, 500.0, size=(8, 16, 6)).astype(np.float32)
    nm = check.noise
    got, _ = residual_chi2_device(samples, check.project, check.mismatch, gain_e_per_dn=nm.gain_e_per_dn,
                                  read_var_dn2=nm.read_var_dn2, light_rms=nm.light_rms)
    np.testing.assert_allclose(got, residual_chi2(samples, check), rtol=2e-4, atol=1e-3)


def test_shapes_are_checked_in_one_line():
    check = _check(6, 3)
    nm = check.noise
    kw = dict(gain_e_per_dn=nm.gain_e_per_dn, read_var_dn2=nm.read_var_dn2, light_rms=nm.light_rms)
    with pytest.raises(ValueError, match="samples hold 5 per pixel; project reads 6"):
        residual_chi2_device(np.zeros((4, 4, 5), np.float32), check.project, check.mismatch, **kw)
    with pytest.raises(ValueError, match=r"mismatch \(R, R\)"):
        residual_chi2_device(np.zeros((4, 4, 6), np.float32), check.project, np.eye(2), **kw)
