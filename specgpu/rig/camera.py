"""The high-speed monochrome CMOS camera (paper Section 2.C: Epix SV643M, 640 x 480, 10 bit, about 200 fps).

Signal chain, per pixel and exposure ``t`` (all in electrons until the ADC)::

    e_signal = t * integral R(lambda) E(lambda) r(lambda) dlambda * field * prnu
    r(lambda) = QE(lambda) * lambda / (h c) * A_pixel * T_lens / (4 N^2 (1 + m)^2)     (camera equation)
    DN = round((e_signal + e_dark + e_pedestal + dsnu + noise) / gain), clipped to [0, 2^bits - 1]

with ``R`` the reflectance, ``E`` the spectral irradiance on the object (W m^-2 nm^-1), ``QE`` the quantum
efficiency (the paper's spectral sensitivity V(lambda), Fig. 6, up to scale), ``m`` the magnification
(pixel pitch over the 48 um the paper images per pixel) and ``gain`` the conversion gain (e-/DN) that maps the
full well onto the top code. Temporal noise: photon shot noise (variance = e_signal), dark-current shot noise
(variance = e_dark), read noise; fixed-pattern noise: gain (PRNU) and offset (DSNU) maps drawn once per camera
from its seed; quantization by rounding. The response is linear up to saturation, as the paper measured.

Frame-rate rule (stated, since the paper only gives end points): the sensor reads its region of interest at a
fixed pixel clock, so the shortest frame period is ``frame_overhead_s + roi_width * roi_height / pixel_clock_hz``.
The defaults (62 MHz, 45 us) give 200.0 fps at 640 x 480 and 779 fps at 320 x 240, the paper's figures.

Default sensitivity ``"cmos"``: the paper's Fig. 6 is not tabulated, so the default is a documented smooth model
of a front-illuminated monochrome CMOS, a skewed Gaussian peaking at 560 nm (half maximum near 420 and 745 nm),
times ``quantum_efficiency_peak``. A two-column CSV (wavelength nm, relative sensitivity) replaces the shape.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.validate import check_array, check_number, normalised_to_peak
from specgpu.io.npz import curve_on_grid

__all__ = ["CameraParameters", "Camera", "sensitivity_curve", "standard_normal_fill"]

PLANCK_H = 6.62607015e-34  # J s
LIGHT_C = 299792458.0  # m / s

SENSOR_WIDTH = 640
SENSOR_HEIGHT = 480
MIN_ROI = (320, 240)
MAX_SENSOR = 16384
BIT_DEPTHS = (8, 10, 12)


@dataclass(frozen=True)
class CameraParameters:
    """Physical parameters of the monochrome camera; every field is a key of the rig TOML's ``[camera]`` table.

    Attributes
    ----------
    sensitivity : str
        Relative spectral sensitivity shape: ``"cmos"`` (documented default model) or a CSV path
        (wavelength nm, relative value >= 0). Normalized to peak 1.
    quantum_efficiency_peak : float
        Quantum efficiency at the sensitivity peak, electrons per photon, in (0, 1]. Default 0.40.
    roi_width, roi_height : int
        Region of interest read out, pixels, centred on the sensor; from 320 x 240 to the sensor's size.
    bit_depth : int
        ADC resolution: 8, 10 or 12 bits. Default 10. Frames are delivered as uint16.
    full_well_e : float
        Electrons mapped to the top code (saturation), > 0. Default 35500.
    read_noise_e : float
        RMS read noise, electrons, >= 0. Default 14.
    dark_current_e_per_s : float
        Mean dark current, electrons per second, >= 0 (sensor at the lab's 20 C). Default 300.
    pedestal_e : float
        Black-level offset added before the ADC, in electrons (so it keeps its meaning at any bit depth), >= 0.
        Default 550 (about 16 DN at 10 bit), which keeps the noise of dark pixels from clipping at code 0.
    prnu_rms : float
        Relative RMS of the per-pixel gain (photo-response non-uniformity), in [0, 0.5]. Default 0.008.
    dsnu_rms_e : float
        RMS of the per-pixel offset (dark-signal non-uniformity), electrons, >= 0. Default 20.
    pixel_pitch_um : float
        Pixel pitch, micrometres, > 0. Default 9.9 (assumed; typical of 640 x 480 high-speed CMOS).
    object_pixel_um : float
        Size of one pixel projected on the object, micrometres, > 0. Default 48 (paper Section 5: object at
        120 mm). Sets the magnification ``m = pixel_pitch / object_pixel`` and the field of view.
    f_number : float
        Working f-number of the lens, >= 0.5. Default 8 (assumed: with it, each of the 100 nm wide R, G, B bands
        of the paper's SNR test can bring a white plate to 3/4 of the full well at 90 fps; blue, the weakest,
        reaches 0.86).
    lens_transmittance : float
        Transmittance of the lens, in (0, 1]. Default 0.9.
    exposure_s : float
        Exposure time, s, > 0. Default 0.0110 (for 90 fps with room for the light to switch).
    frame_rate_hz : float
        Frame rate, Hz, > 0; at most the rate the ROI allows. Default 90 (the paper's temporal SNR test).
    pixel_clock_hz : float
        Pixel read-out rate, pixels per second, > 0. Default 62e6.
    frame_overhead_s : float
        Fixed per-frame read-out overhead, s, >= 0. Default 45e-6.
    sensor_width, sensor_height : int
        Pixels of the whole sensor (the ROI is centred on it), from 320 x 240 to 16384 x 16384. Default 640 x 480,
        the paper's; :mod:`specgpu.rig.sensors` has presets of machine-vision sensors (``preset`` in the TOML).

    Notes
    -----
    The paper gives the sensor's SNR, not its noise parameters. The defaults for full well, read noise, dark
    current and fixed-pattern noise are typical of a high-speed CMOS of the period and were set, together with
    the light's ``fluctuation_rms``, so that :func:`specgpu.rig.twin.measure_snr` reproduces the paper's 44.2 dB
    (camera) and 39.1 dB (camera and light) on a reference white at 90 fps.
    """

    sensitivity: str = "cmos"
    quantum_efficiency_peak: float = 0.40
    roi_width: int = 640
    roi_height: int = 480
    bit_depth: int = 10
    full_well_e: float = 35500.0
    read_noise_e: float = 14.0
    dark_current_e_per_s: float = 300.0
    pedestal_e: float = 550.0
    prnu_rms: float = 0.008
    dsnu_rms_e: float = 20.0
    pixel_pitch_um: float = 9.9
    object_pixel_um: float = 48.0
    f_number: float = 8.0
    lens_transmittance: float = 0.9
    exposure_s: float = 0.0110
    frame_rate_hz: float = 90.0
    pixel_clock_hz: float = 62e6
    frame_overhead_s: float = 45e-6
    sensor_width: int = SENSOR_WIDTH
    sensor_height: int = SENSOR_HEIGHT

    def __post_init__(self):
        n = "camera."
        if not isinstance(self.sensitivity, str):
            raise ValueError(f"{n}sensitivity must be 'cmos' or a CSV path, got {self.sensitivity!r}")
        check_number(n + "quantum_efficiency_peak", self.quantum_efficiency_peak, low=0, low_open=True, high=1)
        w = check_number(n + "roi_width", self.roi_width, integer=True)
        h = check_number(n + "roi_height", self.roi_height, integer=True)
        sw = check_number(n + "sensor_width", self.sensor_width, integer=True, low=MIN_ROI[0], high=MAX_SENSOR)
        sh = check_number(n + "sensor_height", self.sensor_height, integer=True, low=MIN_ROI[1], high=MAX_SENSOR)
        if not (MIN_ROI[0] <= w <= sw and MIN_ROI[1] <= h <= sh):
            raise ValueError(f"{n}roi must be between {MIN_ROI[0]} x {MIN_ROI[1]} and {sw} x {sh} pixels (the "
                             f"sensor; set camera.sensor_width / sensor_height or a camera.preset), got {w} x {h}")
        if check_number(n + "bit_depth", self.bit_depth, integer=True) not in BIT_DEPTHS:
            raise ValueError(f"{n}bit_depth must be one of {BIT_DEPTHS}, got {self.bit_depth}")
        check_number(n + "full_well_e", self.full_well_e, low=0, low_open=True, high=1e9)
        check_number(n + "read_noise_e", self.read_noise_e, low=0, high=1e6)
        check_number(n + "dark_current_e_per_s", self.dark_current_e_per_s, low=0, high=1e12)
        check_number(n + "pedestal_e", self.pedestal_e, low=0, high=self.full_well_e)
        check_number(n + "prnu_rms", self.prnu_rms, low=0, high=0.5)
        check_number(n + "dsnu_rms_e", self.dsnu_rms_e, low=0, high=1e6)
        check_number(n + "pixel_pitch_um", self.pixel_pitch_um, low=0, low_open=True, high=1e4)
        check_number(n + "object_pixel_um", self.object_pixel_um, low=0, low_open=True, high=1e7)
        check_number(n + "f_number", self.f_number, low=0.5, high=1000)
        check_number(n + "lens_transmittance", self.lens_transmittance, low=0, low_open=True, high=1)
        check_number(n + "exposure_s", self.exposure_s, low=0, low_open=True, high=100)
        fr = check_number(n + "frame_rate_hz", self.frame_rate_hz, low=0, low_open=True)
        check_number(n + "pixel_clock_hz", self.pixel_clock_hz, low=0, low_open=True)
        check_number(n + "frame_overhead_s", self.frame_overhead_s, low=0, high=1)
        if fr > self.max_frame_rate_hz * (1 + 1e-9):
            raise ValueError(f"{n}frame_rate_hz = {fr:g} exceeds the {self.max_frame_rate_hz:.1f} fps that a "
                             f"{w} x {h} ROI allows (overhead + pixels / pixel clock)")
        if self.exposure_s > 1.0 / fr:
            raise ValueError(f"{n}exposure_s = {self.exposure_s:g} s is longer than the frame period "
                             f"{1.0 / fr:g} s at {fr:g} fps")

    @property
    def min_frame_period_s(self) -> float:
        """Shortest frame period (s) for the ROI: overhead + pixels / pixel clock."""
        return self.frame_overhead_s + self.roi_width * self.roi_height / self.pixel_clock_hz

    @property
    def max_frame_rate_hz(self) -> float:
        """Highest frame rate (fps) the ROI allows."""
        return 1.0 / self.min_frame_period_s

    @property
    def max_code(self) -> int:
        """Top ADC code, ``2 ** bit_depth - 1``."""
        return (1 << self.bit_depth) - 1

    @property
    def gain_e_per_dn(self) -> float:
        """Conversion gain, electrons per DN: the full well maps to the top code."""
        return self.full_well_e / self.max_code

    @property
    def magnification(self) -> float:
        """Image-to-object magnification, ``pixel_pitch / object_pixel``."""
        return self.pixel_pitch_um / self.object_pixel_um

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


def sensitivity_curve(name: str, wavelengths) -> np.ndarray:
    """Relative spectral sensitivity (peak 1 over ``wavelengths``) of the named model or CSV file."""
    wl = np.asarray(wavelengths, dtype=np.float64)
    zero = f"camera.sensitivity {name!r} is zero"
    if name == "cmos":
        sigma = np.where(wl < 560.0, 120.0, 155.0)
        return normalised_to_peak(np.exp(-0.5 * ((wl - 560.0) / sigma) ** 2), wl, zero)
    return curve_on_grid(name, wl, "camera sensitivity", zero)


# Inverse-CDF table of the standard normal at 2^16 equally likely midpoints: drawing 16 random bits per sample
# and looking the value up is about 5x faster than numpy's ziggurat on this kind of machine, which is what lets
# the twin render full frames faster than the camera's 780 fps. The table has unit variance to 1e-5 and tails
# to +-4.3 sigma (probability 1.5e-5 per sample beyond), which no frame statistic here can resolve.
def _normal_table() -> np.ndarray:
    from scipy.special import ndtri

    return ndtri((np.arange(65536) + 0.5) / 65536.0).astype(np.float32)


_NORMAL_TABLE = _normal_table()


def standard_normal_fill(rng: np.random.Generator, out: np.ndarray) -> np.ndarray:
    """Fill float32 ``out`` with standard normal samples (table method, see module notes); return ``out``."""
    n = out.size
    raw = rng.bit_generator.random_raw((n + 3) // 4)
    idx = raw.view(np.uint16)[:n]
    np.take(_NORMAL_TABLE, idx, out=out.reshape(-1))
    return out


class Camera:
    """The simulated camera: responsivity, fixed-pattern maps and the noise model.

    Parameters
    ----------
    params
        :class:`CameraParameters`; the paper's camera by default.
    seed
        Seed of the fixed-pattern (PRNU, DSNU) maps: the same seed is the same camera.
    """

    def __init__(self, params: CameraParameters | None = None, *, seed: int = 0, realism=None):
        self.params = params if params is not None else CameraParameters()
        #: The bench's imperfections (:class:`specgpu.rig.realism.Realism`): the sensor's QE ripple and its
        #: non-linearity near full well are the camera's; None is the ideal camera.
        self.realism = realism
        p = self.params
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xCA3E]))
        prnu = 1.0 + p.prnu_rms * rng.standard_normal((p.sensor_height, p.sensor_width))
        dsnu = p.dsnu_rms_e * rng.standard_normal((p.sensor_height, p.sensor_width))
        y0 = (p.sensor_height - p.roi_height) // 2
        x0 = (p.sensor_width - p.roi_width) // 2
        self.prnu = np.ascontiguousarray(prnu[y0:y0 + p.roi_height, x0:x0 + p.roi_width], dtype=np.float32)
        self.dsnu_e = np.ascontiguousarray(dsnu[y0:y0 + p.roi_height, x0:x0 + p.roi_width], dtype=np.float32)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the frames."""
        return (self.params.roi_height, self.params.roi_width)

    @property
    def pixel_mm(self) -> float:
        """Size of one pixel on the object, mm."""
        return self.params.object_pixel_um * 1e-3

    def responsivity(self, wavelengths: ArrayLike) -> np.ndarray:
        """Electrons per second per nm, per (W m^-2 nm^-1) of object irradiance, for reflectance 1.

        ``QE(lambda) lambda / (h c) * A_pixel * T / (4 N^2 (1 + m)^2)`` for a Lambertian object.
        """
        p = self.params
        wl = np.asarray(wavelengths, dtype=np.float64)
        qe = p.quantum_efficiency_peak * sensitivity_curve(p.sensitivity, wl)
        r = self.realism
        if r is not None and r.sensor_ripple:  # thin-film interference of the cover glass / micro-lens stack
            qe = qe * (1.0 + r.sensor_ripple * np.sin(2 * math.pi * wl / r.sensor_ripple_period_nm + 1.0))
        area = (p.pixel_pitch_um * 1e-6) ** 2
        optics = p.lens_transmittance / (4.0 * p.f_number**2 * (1.0 + p.magnification) ** 2)
        return qe * (wl * 1e-9) / (PLANCK_H * LIGHT_C) * area * optics

    def signal_electrons(self, irradiance, wavelengths: ArrayLike, reflectance: float = 1.0,
                         exposure_s: float | None = None) -> np.ndarray:
        """Mean photo-electrons for a spectral irradiance on an object of the given reflectance (no PRNU, no field).

        Parameters
        ----------
        irradiance
            (..., grid) spectral irradiance on the object, W m^-2 nm^-1, on a uniform ``wavelengths`` grid.
        wavelengths
            Uniformly spaced wavelengths (nm) of ``irradiance``.
        reflectance
            Scalar or (..., grid) reflectance in [0, 1] on the same grid.
        exposure_s
            Exposure (s); the camera's by default.

        Returns
        -------
        numpy.ndarray
            ``t * sum(R E r) * dlambda`` in electrons.
        """
        wl = np.asarray(wavelengths, dtype=np.float64)
        t = self.params.exposure_s if exposure_s is None else exposure_s
        dl = float(wl[1] - wl[0]) if wl.size > 1 else 1.0
        return t * np.sum(np.asarray(reflectance) * np.asarray(irradiance) * self.responsivity(wl), axis=-1) * dl

    def dark_electrons(self, exposure_s: float | None = None) -> float:
        """Mean dark-current electrons in one exposure."""
        t = self.params.exposure_s if exposure_s is None else exposure_s
        return self.params.dark_current_e_per_s * t

    def expected_dn(self, signal_e: ArrayLike, exposure_s: float | None = None, *,
                    fixed_pattern: bool = True) -> np.ndarray:
        """Expected raw output (DN, before rounding and clipping) for a signal in electrons.

        With ``fixed_pattern`` the PRNU and DSNU maps are applied (``signal_e`` must broadcast to the frame).
        """
        p = self.params
        s = np.asarray(signal_e, dtype=np.float64)
        offset = p.pedestal_e + self.dark_electrons(exposure_s)
        if fixed_pattern:
            return (s * self.prnu + offset + self.dsnu_e) / p.gain_e_per_dn
        return (s + offset) / p.gain_e_per_dn

    def temporal_variance_dn(self, signal_e: ArrayLike, exposure_s: float | None = None, *,
                             quantization: bool = True) -> np.ndarray:
        """Temporal variance (DN^2) of one pixel per the noise model: shot + dark shot + read (+ 1/12 quantization)."""
        p = self.params
        var_e = np.asarray(signal_e, dtype=np.float64) + self.dark_electrons(exposure_s) + p.read_noise_e**2
        return var_e / p.gain_e_per_dn**2 + (1.0 / 12.0 if quantization else 0.0)

    def expose(self, signal_e: ArrayLike, rng: np.random.Generator, *, exposure_s: float | None = None,
               out: np.ndarray | None = None) -> np.ndarray:
        """One noisy frame (uint16 DN) for a per-pixel mean signal in electrons (PRNU applied here).

        Shot and dark noise use the Gaussian approximation of the Poisson law (exact in mean and variance; the
        signals that matter here are hundreds to tens of thousands of electrons).
        """
        p = self.params
        s = check_array("signal_e", signal_e, low=0.0, dtype=np.float32)
        s = np.broadcast_to(s, self.shape)
        signal = s * self.prnu
        var = signal + np.float32(self.dark_electrons(exposure_s) + p.read_noise_e**2)
        z = standard_normal_fill(rng, np.empty(self.shape, np.float32))
        e = signal + np.float32(p.pedestal_e + self.dark_electrons(exposure_s)) + self.dsnu_e + z * np.sqrt(var)
        return quantize(e / np.float32(p.gain_e_per_dn), p.max_code, out)


def quantize(dn: np.ndarray, max_code: int, out: np.ndarray | None = None) -> np.ndarray:
    """Round half up and clip to [0, max_code]; write into uint16 ``out`` (allocated if None). ``dn`` is clobbered."""
    np.clip(dn, 0.0, float(max_code), out=dn)
    dn += np.float32(0.5)
    if out is None:
        out = np.empty(dn.shape, np.uint16)
    np.copyto(out, dn, casting="unsafe")
    return out
