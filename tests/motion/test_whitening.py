"""One whitening for every registration: the half spectrum (fitted peak) and the full one (upsampled DFT) carry the
same Gaussian weight, and a translation comes out of either as a linear phase."""

from __future__ import annotations

import numpy as np
from scipy import fft

from specgpu.motion.whitening import frequency_weight, hann, whitened_half_spectrum, whitened_spectrum


def test_the_half_and_the_full_spectrum_share_one_weight():
    shape, cutoff = (24, 30), 0.12
    full, half = frequency_weight(shape, cutoff, half=False), frequency_weight(shape, cutoff)
    assert full.shape == shape and half.shape == (24, 16) and half.dtype == np.float32 and full.dtype == np.float64
    np.testing.assert_allclose(half, full[:, :16], rtol=1e-6)
    fy, fx = np.meshgrid(fft.fftfreq(24), fft.fftfreq(30), indexing="ij")
    np.testing.assert_allclose(full, np.exp(-(fx**2 + fy**2) / (4 * cutoff**2)), rtol=1e-12)
    assert not full.flags.writeable and frequency_weight(shape, cutoff) is half  # made once per shape


def test_either_spectrum_is_phase_only_under_the_weight():
    rng = np.random.default_rng(3)
    image = rng.uniform(0, 1, (32, 40)).astype(np.float32)
    F = whitened_spectrum(hann(image), 0.12)
    np.testing.assert_allclose(np.abs(F), frequency_weight((32, 40), 0.12, half=False), rtol=1e-5)  # single precision
    H = whitened_half_spectrum(image, 0.12)
    assert H.dtype == np.complex64
    np.testing.assert_allclose(np.abs(H), frequency_weight((32, 40), 0.12), rtol=1e-5)
    np.testing.assert_allclose(H, F[:, :21], rtol=2e-5, atol=1e-6)  # the same spectrum, halved, in float32
