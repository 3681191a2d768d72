"""Ocean (Ocean Insight / Ocean Optics) spectrometers through python-seabreeze, for calibration loop (b).

:class:`OceanSpectrometer` offers what the calibration reads from the twin's
:class:`~specgpu.rig.spectroradiometer.Spectroradiometer`: ``wavelengths`` (a uniform output grid), ``params``
(range, step, bandwidth), ``response_matrix`` (the nominal bandpass, for planning) and ``measure``, which here reads
the instrument instead of simulating it. Counts become spectral irradiance (W m^-2 nm^-1) through an irradiance
calibration (per pixel, W m^-2 nm^-1 per count/s, from a calibration lamp) after dark subtraction, then are sampled
on the output grid.

python-seabreeze is optional (``pip install seabreeze``; on Linux ``seabreeze_os_setup`` installs the udev rules)
and imported only when an instrument is opened without an injected device.
"""

from __future__ import annotations

import numpy as np

from specgpu.core.validate import check_number
from specgpu.hardware.errors import BackendMissing, DeviceNotFound, HardwareError
from specgpu.io.npz import read_spectrum_csv
from specgpu.rig.spectroradiometer import Spectroradiometer, SpectroradiometerParameters

__all__ = ["OceanSpectrometer", "open_seabreeze"]


def open_seabreeze(serial: str | None = None):
    """A ``seabreeze.spectrometers.Spectrometer`` (the first one, or the one with ``serial``)."""
    try:
        from seabreeze.spectrometers import Spectrometer, list_devices
    except ImportError:
        raise BackendMissing("Ocean spectrometers need the optional 'seabreeze' package: pip install seabreeze "
                             "(Linux: then run seabreeze_os_setup for the udev rules)") from None
    if not list_devices():
        raise DeviceNotFound("no Ocean spectrometer found: is it connected, and readable by this user (udev "
                             "rules: seabreeze_os_setup)?")
    try:
        return Spectrometer.from_serial_number(serial) if serial else Spectrometer.from_first_available()
    except Exception as exc:  # seabreeze's SeaBreezeError: busy or not found
        raise DeviceNotFound(f"Ocean spectrometer {serial or '(first)'} cannot be opened ({exc})") from None


class OceanSpectrometer:
    """An Ocean spectrometer measuring the light's spectral irradiance.

    Parameters
    ----------
    device
        A seabreeze ``Spectrometer`` (or anything with ``wavelengths()``, ``intensities(correct_dark_counts,
        correct_nonlinearity)``, ``integration_time_micros(us)``, ``close()``); default: opened by ``serial``.
    irradiance_calibration
        (pixels,) W m^-2 nm^-1 per count/s at each pixel, or a two-column CSV (wavelength nm, value) interpolated
        onto the pixels. Required by :meth:`measure`.
    integration_time_s
        Integration time, s.
    averages
        Readings averaged per measurement.
    params
        Output grid and nominal bandwidth (:class:`SpectroradiometerParameters`); default 380-780 nm by 1 nm
        within the instrument's range, 5 nm bandwidth (set it to the instrument's optical resolution).
    """

    def __init__(self, device=None, *, serial: str | None = None, irradiance_calibration=None,
                 integration_time_s: float = 0.1, averages: int = 1,
                 params: SpectroradiometerParameters | None = None):
        self.device = device if device is not None else open_seabreeze(serial)
        self.pixel_wavelengths = np.asarray(self.device.wavelengths(), np.float64)
        if self.pixel_wavelengths.ndim != 1 or self.pixel_wavelengths.size < 2:
            raise HardwareError("spectrometer reported no wavelength calibration")
        lo, hi = float(self.pixel_wavelengths.min()), float(self.pixel_wavelengths.max())
        if params is None:
            params = SpectroradiometerParameters(wavelength_min_nm=max(380.0, np.ceil(lo)),
                                                 wavelength_max_nm=min(780.0, np.floor(hi)))
        if params.wavelength_min_nm < lo or params.wavelength_max_nm > hi:
            raise ValueError(f"output range {params.wavelength_min_nm:g}-{params.wavelength_max_nm:g} nm exceeds "
                             f"the instrument's {lo:g}-{hi:g} nm")
        self.params = params
        self._model = Spectroradiometer(params)  # nominal bandpass for response_matrix
        self.wavelengths = self._model.wavelengths
        self.averages = check_number("averages", averages, low=1, high=10000, integer=True)
        #: (dark, non-linearity) corrections applied to readings; found on the first reading
        self.corrections: tuple[bool, bool] | None = None
        self.set_integration_time(integration_time_s)
        self.calibration = None if irradiance_calibration is None else self._load_calibration(irradiance_calibration)
        self.dark_counts: np.ndarray | None = None

    def _load_calibration(self, cal) -> np.ndarray:
        if isinstance(cal, (str, bytes)) or hasattr(cal, "__fspath__"):
            wl, val = read_spectrum_csv(cal)
            cal = np.interp(self.pixel_wavelengths, wl, val)
        cal = np.asarray(cal, np.float64)
        if cal.shape != self.pixel_wavelengths.shape or not np.all(np.isfinite(cal)) or np.any(cal < 0):
            raise ValueError(f"irradiance calibration must be {self.pixel_wavelengths.shape} finite, non-negative "
                             f"values, got shape {cal.shape}")
        return cal

    def set_integration_time(self, seconds: float) -> None:
        """Integration time (s) of the next readings."""
        self.integration_time_s = check_number("integration_time_s", seconds, low=0, low_open=True, high=600)
        self.device.integration_time_micros(int(round(self.integration_time_s * 1e6)))

    def read_counts(self) -> np.ndarray:
        """Mean of ``averages`` readings, counts per pixel (electric dark and non-linearity corrected where the
        instrument supports them, each on its own: ``corrections``)."""
        total = np.zeros(self.pixel_wavelengths.shape)
        for _ in range(self.averages):
            total += np.asarray(self._intensities(), np.float64)
        return total / self.averages

    def _intensities(self):
        """One reading with every correction the instrument supports: both, else whichever one it does (seabreeze
        raises for a correction a model lacks), else none; the combination that worked is kept in
        ``corrections``."""
        if self.corrections is not None:
            dark, nonlinear = self.corrections
            return self.device.intensities(correct_dark_counts=dark, correct_nonlinearity=nonlinear)
        error = None
        for dark, nonlinear in ((True, True), (True, False), (False, True), (False, False)):
            try:
                counts = self.device.intensities(correct_dark_counts=dark, correct_nonlinearity=nonlinear)
            except Exception as exc:  # seabreeze's SeaBreezeError: this model lacks that correction
                error = exc
                continue
            self.corrections = (dark, nonlinear)
            return counts
        raise HardwareError(f"Ocean spectrometer gives no reading, even uncorrected ({error})")

    def set_dark(self, counts=None) -> None:
        """Record the dark reading (take it with the light off) subtracted from later measurements."""
        self.dark_counts = self.read_counts() if counts is None else np.asarray(counts, np.float64)

    def response_matrix(self, wavelengths) -> np.ndarray:
        """Nominal (samples, grid) bandpass weights, as the model's (the instrument's own slit does the rest)."""
        return self._model.response_matrix(wavelengths)

    def measure_spectrum(self) -> tuple[np.ndarray, np.ndarray]:
        """(wavelengths nm, spectral irradiance W m^-2 nm^-1 >= 0) of the light now shining on the instrument."""
        if self.calibration is None:
            raise HardwareError("Ocean spectrometer has no irradiance calibration: pass irradiance_calibration= "
                                "(W m^-2 nm^-1 per count/s per pixel, or a CSV of wavelength nm, value)")
        counts = self.read_counts()
        if self.dark_counts is not None:
            counts = counts - self.dark_counts
        irradiance = counts / self.integration_time_s * self.calibration
        order = np.argsort(self.pixel_wavelengths)
        grid = np.interp(self.wavelengths, self.pixel_wavelengths[order], irradiance[order])
        return self.wavelengths, np.maximum(grid, 0.0)

    def measure(self, spectrum=None, wavelengths=None, rng=None) -> np.ndarray:
        """The model's ``measure`` for a real instrument: it reads the light, so no spectrum may be given."""
        if spectrum is not None or wavelengths is not None:
            raise TypeError("a real spectrometer measures the light itself: call measure() without a spectrum")
        return self.measure_spectrum()[1]

    def close(self) -> None:
        self.device.close()
