"""The spectroradiometer of the paper's second feedback loop (Fig. 8(b)): it measures the light's spectrum.

The calibration that makes the light emit a target spectrum compares a measured spectrum with the target, so the
twin needs the instrument too, with the imperfections that limit such a loop: a finite bandpass (triangular slit
function, as in grating spectroradiometers), sampling on its own wavelength grid, relative (shot-like) noise,
an absolute noise floor and an optional systematic scale error of the calibration lamp it was calibrated with.
Defaults are typical of a laboratory instrument (5 nm bandwidth, 1 nm sampling, 0.3 % noise).

The measured quantity is the spectral irradiance the light puts on the object at the centre of its spot, in
W m^-2 nm^-1 (as if measured off a perfect white diffuser and converted).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.validate import check_array, check_number

__all__ = ["SpectroradiometerParameters", "Spectroradiometer"]


@dataclass(frozen=True)
class SpectroradiometerParameters:
    """Parameters of the spectroradiometer; every field is a key of the rig TOML's ``[spectroradiometer]`` table.

    Attributes
    ----------
    wavelength_min_nm, wavelength_max_nm : float
        Measured range, nm. Defaults 380 and 780.
    step_nm : float
        Sampling interval, nm, > 0. Default 1.
    bandwidth_nm : float
        Full width at half maximum of the triangular bandpass, nm, >= 0 (0: ideal sampling). Default 5.
    noise_rms : float
        Relative RMS noise of each sample, in [0, 1]. Default 0.003.
    noise_floor : float
        Absolute RMS noise of each sample, W m^-2 nm^-1, >= 0. Default 1e-5.
    scale_error : float
        Systematic relative error of the instrument's calibration (the same for every measurement), in
        [-0.5, 0.5]. Default 0.
    """

    wavelength_min_nm: float = 380.0
    wavelength_max_nm: float = 780.0
    step_nm: float = 1.0
    bandwidth_nm: float = 5.0
    noise_rms: float = 0.003
    noise_floor: float = 1e-5
    scale_error: float = 0.0

    def __post_init__(self):
        n = "spectroradiometer."
        lo = check_number(n + "wavelength_min_nm", self.wavelength_min_nm, low=100, high=3000)
        hi = check_number(n + "wavelength_max_nm", self.wavelength_max_nm, low=100, high=3000)
        step = check_number(n + "step_nm", self.step_nm, low=0, low_open=True, high=100)
        if hi - lo < step:
            raise ValueError(f"{n}wavelength_max_nm ({hi:g}) must exceed wavelength_min_nm ({lo:g}) by a step")
        check_number(n + "bandwidth_nm", self.bandwidth_nm, low=0, high=100)
        check_number(n + "noise_rms", self.noise_rms, low=0, high=1)
        check_number(n + "noise_floor", self.noise_floor, low=0)
        check_number(n + "scale_error", self.scale_error, low=-0.5, high=0.5)

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


class Spectroradiometer:
    """A simulated spectroradiometer.

    Parameters
    ----------
    params
        :class:`SpectroradiometerParameters`.
    seed
        Seed of the measurement noise (each :meth:`measure` call draws new noise).
    """

    def __init__(self, params: SpectroradiometerParameters | None = None, *, seed: int = 0):
        self.params = params if params is not None else SpectroradiometerParameters()
        p = self.params
        count = int(np.floor((p.wavelength_max_nm - p.wavelength_min_nm) / p.step_nm + 1e-9)) + 1
        self.wavelengths = p.wavelength_min_nm + p.step_nm * np.arange(count)
        self._rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5BEC]))

    def response_matrix(self, wavelengths: ArrayLike) -> np.ndarray:
        """(samples, grid) weights: each sample is the bandpass-weighted mean of a spectrum on ``wavelengths``."""
        wl = check_array("wavelengths", wavelengths, ndim=1)
        if wl.size < 2 or np.any(np.diff(wl) <= 0):
            raise ValueError("wavelengths must be strictly increasing with at least 2 samples")
        fwhm = self.params.bandwidth_nm
        if fwhm == 0:
            eye = np.eye(wl.size)
            return np.stack([np.interp(self.wavelengths, wl, eye[i], left=0.0, right=0.0) for i in range(wl.size)], 1)
        # Triangle of base 2 * FWHM, integrated with trapezoid weights of the source grid.
        d = np.abs(self.wavelengths[:, None] - wl[None, :])
        tri = np.clip(1.0 - d / fwhm, 0.0, None)
        dw = np.gradient(wl)
        w = tri * dw[None, :]
        return w / fwhm  # a triangle of unit peak has area fwhm: a flat spectrum reads back unchanged

    def measure(self, spectrum: ArrayLike, wavelengths: ArrayLike,
                rng: np.random.Generator | None = None) -> np.ndarray:
        """Measure a spectral irradiance (W m^-2 nm^-1) given on ``wavelengths``; returns values on
        :attr:`wavelengths` with bandpass, noise and scale error applied (never negative)."""
        s = check_array("spectrum", spectrum, ndim=1, low=0.0)
        wl = np.asarray(wavelengths, dtype=np.float64)
        if wl.shape != s.shape:
            raise ValueError(f"wavelengths must have shape {s.shape}, got {wl.shape}")
        p = self.params
        clean = self.response_matrix(wl) @ s * (1.0 + p.scale_error)
        gen = self._rng if rng is None else rng
        sigma = np.sqrt((p.noise_rms * clean) ** 2 + p.noise_floor**2)
        return np.maximum(clean + sigma * gen.standard_normal(clean.shape), 0.0)
