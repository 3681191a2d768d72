"""The programmable light source: xenon lamp -> grating -> DMD -> liquid light guide (paper Section 2.A, Fig. 2).

The grating spreads the lamp's light across the DMD's 1024 columns, so each column carries a narrow band
centred at a wavelength that grows linearly from 380 to 780 nm; the 768 rows set the level: the light leaving
a column is proportional to the number of mirrors switched on in it. A **pattern** is therefore the vector of
per-column mirror counts, shape (1024,), integers in [0, 768]. This module maps both ways:

- :meth:`ProgrammableLight.pattern_to_spectrum`: the spectral irradiance a pattern puts on the object;
- :meth:`ProgrammableLight.spectrum_to_pattern`: the quantized pattern for a target spectrum, with the error
  that the mirror quantization, the slit function and the lamp's limits leave (:class:`PatternFit`).

It also holds a pre-loaded pattern sequence that a trigger advances (time-varying mode) or a single pattern
(steady-state mode), the 62 us pattern load plus 18 us mirror settling that make exposures under 80 us
impossible, the field profile of the lit spot (paper Figs. 4, 5), and, off by default, second-order diffraction
leakage, lamp drift and mains flicker. The frame-to-frame fluctuation of the light is on by default: together
with the camera noise it gives the paper's 39.1 dB temporal SNR.

The default lamp is an analytic model, because the paper's Fig. 3 is not tabulated: a 6000 K Planck continuum
(the colour temperature of a xenon short arc) plus the visible Xe I lines at 462.4, 467.1 and 473.4 nm, times
the transmittance edge of a liquid light guide (which cuts the violet, hence the paper's weak short-wavelength
end) and a scalar-theory blaze efficiency of the grating. ``lamp = "kinoton-75p"`` uses colour-science's
measured xenon projector lamp instead (it is filtered above about 690 nm), and a CSV path uses a measured curve.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import colour
import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.validate import check_array, check_number, normalised_to_peak
from specgpu.io.npz import curve_on_grid
from specgpu.rig.realism import Drift, Realism

__all__ = ["LightParameters", "ProgrammableLight", "PatternFit", "lamp_spd", "photopic_y"]

#: Luminous efficacy of radiation at 555 nm, lm/W (CIE).
K_M = 683.002

_XENON_LINES_NM = (462.4, 467.1, 473.4)
_XENON_LINE_STRENGTH = (0.06, 0.10, 0.07)  # peak height relative to the continuum at 560 nm
_XENON_LINE_FWHM_NM = 2.0


@dataclass(frozen=True)
class LightParameters:
    """Physical parameters of the programmable light source; defaults are the paper's OL490 rig.

    Every field is a key of the ``[light]`` table of a rig TOML.

    Attributes
    ----------
    lamp : str
        Lamp spectral power distribution: ``"xenon"`` (analytic model, see module docstring),
        ``"kinoton-75p"`` (colour-science's measured xenon projector lamp) or a path to a two-column CSV
        (wavelength nm, relative power). Only the shape matters; the level is set by ``illuminance_lux``.
    lamp_colour_temperature_k : float
        Colour temperature of the xenon continuum, K, in [2000, 20000]. Default 6000.
    light_guide_cutoff_nm : float
        Wavelength (nm) at which the liquid light guide transmits half its maximum; [300, 500]. Default 410.
    light_guide_edge_nm : float
        Width (nm) of the light guide's logistic transmittance edge; (0, 100]. Default 12.
    grating_blaze_nm : float
        First-order blaze wavelength of the grating, nm, in [300, 900]. Default 500.
    columns : int
        DMD columns along the wavelength axis. Default 1024.
    rows : int
        DMD rows along the intensity axis: the number of intensity levels is ``rows + 1``. Default 768.
    wavelength_min_nm, wavelength_max_nm : float
        Wavelengths (nm) at the outer edges of the first and last column. Defaults 380 and 780.
    line_fwhm_nm : float
        Full width at half maximum (nm) of the Gaussian slit function: the band one column emits.
        (0, 50]. Default 5.
    illuminance_lux : float
        Illuminance (lux) at the centre of the lit spot with every mirror on, for a spot of
        ``spot_diameter_mm``; > 0. Default 15000 (the paper asks for > 10000 lux for accurate estimation).
    spot_diameter_mm : float
        Full width at half maximum (mm) of the lit spot on the object. The centre illuminance scales as
        ``1 / diameter**2`` (the same flux spread wider, paper Fig. 5). > 0. Default 80.
    spot_flatness : float
        Order ``p`` of the super-Gaussian spot profile ``2 ** -((2 r / d) ** (2 p))``: 1 is Gaussian, large is
        flat-top. [0.5, 20]. Default 2 (about 4 % fall-off at the corners of the default field, paper Fig. 4).
    spot_centre_mm : tuple of float
        (x, y) offset (mm) of the spot centre from the centre of the camera's field. Default (0, 0).
    pattern_load_s : float
        Time (s) from trigger to the new pattern being loaded on the DMD. Default 62e-6.
    mirror_settle_s : float
        Mirror reset and settling time (s). Default 18e-6. ``pattern_load_s + mirror_settle_s`` is the minimum
        exposure: shorter exposures are refused.
    fluctuation_rms : float
        Relative RMS frame-to-frame fluctuation of the emitted power for an exposure of
        ``fluctuation_reference_exposure_s``, in [0, 0.5]. It averages down as ``sqrt(t_ref / t)`` for longer
        exposures (white intensity noise). Default 0.00922: with the camera's 44.2 dB this gives the paper's
        39.1 dB temporal SNR at 90 fps.
    fluctuation_reference_exposure_s : float
        Exposure (s) at which ``fluctuation_rms`` holds. Default 0.0110 (the exposure of the 90 fps test).
    second_order_leakage : float
        Fraction of the second diffraction order (light at lambda/2 landing on the column for lambda) that
        leaks into the output, in [0, 1]. Off (0) by default.
    drift_per_hour : float
        Relative linear drift of the lamp power per hour, in [-1, 1]. Off (0) by default.
    flicker_amplitude : float
        Relative amplitude of the sinusoidal mains ripple of the lamp power, in [0, 1]. Off (0) by default.
    flicker_frequency_hz : float
        Frequency of the ripple, Hz, > 0. Default 100.
    """

    lamp: str = "xenon"
    lamp_colour_temperature_k: float = 6000.0
    light_guide_cutoff_nm: float = 410.0
    light_guide_edge_nm: float = 12.0
    grating_blaze_nm: float = 500.0
    columns: int = 1024
    rows: int = 768
    wavelength_min_nm: float = 380.0
    wavelength_max_nm: float = 780.0
    line_fwhm_nm: float = 5.0
    illuminance_lux: float = 15000.0
    spot_diameter_mm: float = 80.0
    spot_flatness: float = 2.0
    spot_centre_mm: tuple[float, float] = (0.0, 0.0)
    pattern_load_s: float = 62e-6
    mirror_settle_s: float = 18e-6
    fluctuation_rms: float = 0.00922
    fluctuation_reference_exposure_s: float = 0.0110
    second_order_leakage: float = 0.0
    drift_per_hour: float = 0.0
    flicker_amplitude: float = 0.0
    flicker_frequency_hz: float = 100.0

    def __post_init__(self):
        n = "light."
        if not isinstance(self.lamp, (str, Path)):
            raise ValueError(f"{n}lamp must be 'xenon', 'kinoton-75p' or a CSV path, got {self.lamp!r}")
        check_number(n + "lamp_colour_temperature_k", self.lamp_colour_temperature_k, low=2000, high=20000)
        check_number(n + "light_guide_cutoff_nm", self.light_guide_cutoff_nm, low=300, high=500)
        check_number(n + "light_guide_edge_nm", self.light_guide_edge_nm, low=0, low_open=True, high=100)
        check_number(n + "grating_blaze_nm", self.grating_blaze_nm, low=300, high=900)
        check_number(n + "columns", self.columns, low=2, high=65536, integer=True)
        check_number(n + "rows", self.rows, low=1, high=65535, integer=True)
        lo = check_number(n + "wavelength_min_nm", self.wavelength_min_nm, low=200, high=2000)
        hi = check_number(n + "wavelength_max_nm", self.wavelength_max_nm, low=200, high=2000)
        if hi - lo < 10:
            raise ValueError(f"{n}wavelength_max_nm ({hi:g}) must exceed wavelength_min_nm ({lo:g}) by >= 10 nm")
        check_number(n + "line_fwhm_nm", self.line_fwhm_nm, low=0, low_open=True, high=50)
        check_number(n + "illuminance_lux", self.illuminance_lux, low=0, low_open=True, high=1e7)
        check_number(n + "spot_diameter_mm", self.spot_diameter_mm, low=0, low_open=True, high=1e4)
        check_number(n + "spot_flatness", self.spot_flatness, low=0.5, high=20)
        if len(tuple(self.spot_centre_mm)) != 2:
            raise ValueError(f"{n}spot_centre_mm must be two numbers (x, y) in mm, got {self.spot_centre_mm!r}")
        for v in self.spot_centre_mm:
            check_number(n + "spot_centre_mm", v)
        check_number(n + "pattern_load_s", self.pattern_load_s, low=0, high=1)
        check_number(n + "mirror_settle_s", self.mirror_settle_s, low=0, high=1)
        check_number(n + "fluctuation_rms", self.fluctuation_rms, low=0, high=0.5)
        check_number(n + "fluctuation_reference_exposure_s", self.fluctuation_reference_exposure_s,
                     low=0, low_open=True, high=10)
        check_number(n + "second_order_leakage", self.second_order_leakage, low=0, high=1)
        check_number(n + "drift_per_hour", self.drift_per_hour, low=-1, high=1)
        check_number(n + "flicker_amplitude", self.flicker_amplitude, low=0, high=1)
        check_number(n + "flicker_frequency_hz", self.flicker_frequency_hz, low=0, low_open=True, high=1e6)

    @property
    def switch_time_s(self) -> float:
        """Pattern load plus mirror settling (s): the minimum exposure the light can follow."""
        return self.pattern_load_s + self.mirror_settle_s

    @property
    def exposure_quantum_s(self) -> float:
        """The exposure is exact only in whole multiples of this (s): 0, the DMD's mirrors hold their state."""
        return 0.0

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


def photopic_y(wavelengths: np.ndarray) -> np.ndarray:
    """CIE 1931 2-degree y-bar colour-matching function sampled at ``wavelengths`` (nm); 0 outside 360-830."""
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    return np.interp(wavelengths, cmfs.wavelengths, cmfs.values[:, 1], left=0.0, right=0.0)


def _planck(wavelengths_nm: np.ndarray, temperature_k: float) -> np.ndarray:
    c2 = 1.438776877e-2  # m K
    lam = wavelengths_nm * 1e-9
    return 1.0 / (lam**5 * np.expm1(c2 / (lam * temperature_k)))


def lamp_spd(params: LightParameters, wavelengths: np.ndarray) -> np.ndarray:
    """Relative spectral power (peak-free scale) the lamp delivers through guide and grating, at ``wavelengths``.

    Parameters
    ----------
    params
        Light parameters (``lamp``, colour temperature, light-guide edge, blaze wavelength).
    wavelengths
        Wavelengths in nm.

    Returns
    -------
    numpy.ndarray
        Non-negative relative power, normalized to 1 at its maximum over ``wavelengths``.
    """
    wl = np.asarray(wavelengths, dtype=np.float64)
    lamp = str(params.lamp)
    zero = f"light.lamp {lamp!r} emits nothing"
    if lamp == "xenon":
        spd = _planck(wl, params.lamp_colour_temperature_k)
        spd = spd / float(_planck(np.array([560.0]), params.lamp_colour_temperature_k)[0])
        sigma = _XENON_LINE_FWHM_NM / (2 * math.sqrt(2 * math.log(2)))
        for centre, strength in zip(_XENON_LINES_NM, _XENON_LINE_STRENGTH):
            spd = spd + strength * np.exp(-0.5 * ((wl - centre) / sigma) ** 2)
        guide = 1.0 / (1.0 + np.exp(-(wl - params.light_guide_cutoff_nm) / params.light_guide_edge_nm))
        x = 1.0 - params.grating_blaze_nm / wl  # scalar blaze efficiency, first order: sinc^2(1 - lambda_b/lambda)
        blaze = np.sinc(x) ** 2
        spd = spd * guide * blaze
    elif lamp == "kinoton-75p":

        sd = colour.SDS_LIGHT_SOURCES["Kinoton 75P"]
        spd = np.interp(wl, sd.wavelengths, sd.values, left=0.0, right=0.0)
    else:
        return curve_on_grid(lamp, wl, "lamp power", zero)
    return normalised_to_peak(spd, wl, zero)


def lamp_change(params: LightParameters, wavelengths, cct_change_K: float, cut_on_change_nm: float) -> np.ndarray:
    """Relative spectral change of the lamp through the guide when its colour temperature changes by
    ``cct_change_K`` and the guide's cut-on edge moves by ``cut_on_change_nm``: the ratio of the Planck continua
    (each normalised at 560 nm, so the visible level stays about the same) times the ratio of the guide's edges."""
    wl = np.asarray(wavelengths, np.float64)
    t0 = params.lamp_colour_temperature_k
    t1 = check_number("lamp colour temperature after drift", t0 + cct_change_K, low=1000, high=30000)
    ref = np.array([560.0])
    ratio = (_planck(wl, t1) / _planck(ref, t1)) / (_planck(wl, t0) / _planck(ref, t0))
    if cut_on_change_nm:
        c, e = params.light_guide_cutoff_nm, params.light_guide_edge_nm
        ratio = ratio * (1.0 + np.exp(-(wl - c) / e)) / (1.0 + np.exp(-(wl - c - cut_on_change_nm) / e))
    return ratio


def _slit_matrix(grid, centres, fwhm_nm: float, flat_top: float, slope_per_100nm: float) -> np.ndarray:
    """(grid, columns) unit-area slit functions: a box of ``flat_top * FWHM`` convolved with a Gaussian (the image
    of a rectangular slit through imperfect optics), the FWHM growing by ``slope_per_100nm`` per 100 nm from 580 nm
    (the grating's dispersion changes with the diffraction angle). The Gaussian is narrowed as the box grows so
    the FWHM stays close to the local value."""
    from scipy.special import erf

    fwhm = fwhm_nm * np.maximum(0.2, 1.0 + slope_per_100nm * (centres - 580.0) / 100.0)
    box = flat_top * fwhm
    sigma = fwhm * (1.0 - 0.55 * flat_top) / (2 * math.sqrt(2 * math.log(2)))
    x = grid[:, None] - centres[None, :]
    if flat_top <= 0:
        return np.exp(-0.5 * (x / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
    s2 = sigma * math.sqrt(2.0)
    return (erf((x + box / 2) / s2) - erf((x - box / 2) / s2)) / (2.0 * box)


@dataclass(frozen=True)
class PatternFit:
    """Result of :meth:`ProgrammableLight.spectrum_to_pattern`.

    Attributes
    ----------
    pattern : numpy.ndarray
        (columns,) int32 mirror counts in [0, rows].
    target : numpy.ndarray
        The target spectral irradiance on the light's grid (W m^-2 nm^-1), after scaling.
    emitted : numpy.ndarray
        What the quantized pattern emits, same grid and units.
    scale : float
        Factor applied to the requested target (1 unless ``fit="scale"``).
    rmse : float
        Root-mean-square of ``emitted - target`` over the grid, W m^-2 nm^-1.
    relative_rmse : float
        ``rmse`` divided by the maximum of ``target`` (0 for a zero target).
    clipped : float
        Fraction of the grid where the target exceeds what every mirror on can give (the lamp's limit).
    """

    pattern: np.ndarray
    target: np.ndarray
    emitted: np.ndarray
    scale: float
    rmse: float
    relative_rmse: float
    clipped: float


class ProgrammableLight:
    """The OL490-like programmable light source of the twin.

    It implements :class:`specgpu.capture.driver.LightSource` (registered as a virtual subclass by
    :mod:`specgpu.capture.twin_driver`: the rig model never imports the capture package).

    Parameters
    ----------
    params
        :class:`LightParameters`; the paper's rig by default.
    seed
        Seed of the light's own fluctuation (frame-to-frame power noise).

    Notes
    -----
    Internal grid: 1 nm from ``wavelength_min_nm`` to ``wavelength_max_nm``. The column matrix ``M`` (grid x
    columns) holds, for column ``c`` at centre ``lambda_c``, ``lamp(lambda_c) * dlambda_col * g(lambda - lambda_c)``
    with ``g`` the unit-area Gaussian slit function, scaled so that every mirror on gives ``illuminance_lux``; the
    emitted spectrum of a pattern ``n`` is ``M @ (n / rows)``.
    """

    #: Whether the lamp's colour temperature drifts on the clock (``[realism] lamp_cct_drift_K_per_hour``).
    lamp_colour_drifts = True

    def __init__(self, params: LightParameters | None = None, *, seed: int = 0, realism=None, drift=None,
                 clock_s: float = 0.0):

        self.params = params if params is not None else LightParameters()
        self.realism = r = realism if realism is not None else Realism()
        self.drift = dr = drift if drift is not None else Drift()
        self.clock_s = check_number("clock_s", clock_s, low=0)
        p = self.params
        self._wl = np.arange(p.wavelength_min_nm, p.wavelength_max_nm + 0.5, 1.0)
        dcol = (p.wavelength_max_nm - p.wavelength_min_nm) / p.columns
        self._column_nm = p.wavelength_min_nm + (np.arange(p.columns) + 0.5) * dcol
        if r.column_bow_nm:  # bowed column-wavelength map: zero at both ends, column_bow_nm at mid range
            u = (np.arange(p.columns) + 0.5) / p.columns
            self._column_nm = self._column_nm + r.column_bow_nm * 4.0 * u * (1.0 - u)
        sigma = p.line_fwhm_nm / (2 * math.sqrt(2 * math.log(2)))
        lamp_at_col = lamp_spd(p, self._column_nm)
        if r.grating_ripple:
            lamp_at_col = lamp_at_col * (1.0 + r.grating_ripple * np.sin(2 * math.pi * self._column_nm
                                                                        / r.grating_ripple_period_nm))
        if r.slit_flat_top or r.slit_fwhm_slope:
            g = _slit_matrix(self._wl, self._column_nm, p.line_fwhm_nm, r.slit_flat_top, r.slit_fwhm_slope)
        else:
            offset = self._wl[:, None] - self._column_nm[None, :]
            g = np.exp(-0.5 * (offset / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
        m = g * (lamp_at_col * dcol)[None, :]
        if p.second_order_leakage > 0:
            # Second order: the column for lambda_c also passes lambda_c / 2, at half the bandwidth.
            half = self._column_nm / 2.0
            lamp_half = lamp_spd(p, np.clip(half, self._wl[0], None)) * (half >= self._wl[0] - 3 * sigma)
            s2 = sigma / 2.0
            g2 = np.exp(-0.5 * ((self._wl[:, None] - half[None, :]) / s2) ** 2) / (s2 * math.sqrt(2 * math.pi))
            m = m + p.second_order_leakage * g2 * (lamp_half * dcol)[None, :]
        full = m.sum(axis=1)
        lux_per_unit = K_M * float(np.sum(full * photopic_y(self._wl)))  # 1 nm grid
        if not lux_per_unit > 0:
            raise ValueError("light: the lamp emits no visible light, cannot scale to light.illuminance_lux")
        self._m = m * (p.illuminance_lux / lux_per_unit)
        # The lamp's state now (explicit drift since calibration, plus the clock's drift) relative to nominal; the
        # illuminance scale above stays that of the nominal lamp, so a dimmer or redder lamp gives less light.
        cct_change = dr.lamp_cct_K + r.lamp_cct_drift_K_per_hour * self.clock_s / 3600.0
        if cct_change or dr.cut_on_nm or dr.lamp_output:
            ratio = lamp_change(p, self._wl, cct_change, dr.cut_on_nm) * (1.0 + dr.lamp_output)
            self._m = self._m * ratio[:, None]
        self._offset = None
        if r.stray_light_fraction or r.dmd_off_state:
            full = self._m.sum(axis=1)
            # Broadband stray light: a fraction of each column's power scattered with the lamp's whole spectrum.
            stray = r.stray_light_fraction * np.outer(full / full.sum(), self._m.sum(axis=0))
            # DMD off-state and diffraction background: every column gives dmd_off_state of its light with its
            # mirrors off, so a mirror on adds (1 - dmd_off_state) and all-off still lights the object.
            self._offset = r.dmd_off_state * full
            self._m = self._m * (1.0 - r.dmd_off_state) + stray
        self._m_max = self._m.sum(axis=1) + (0.0 if self._offset is None else self._offset)
        self._sequence = np.zeros((1, p.columns), dtype=np.int32)
        self._spectra = self._m @ np.zeros(p.columns)
        self._spectra = self._spectra[None, :]
        self._index = 0
        self.sequence_version = 0
        self._rng = np.random.default_rng(seed)

    # ---- geometry of the DMD ---------------------------------------------------------------------------
    @property
    def wavelengths(self) -> np.ndarray:
        """The light's 1 nm wavelength grid (nm)."""
        return self._wl

    @property
    def column_wavelengths(self) -> np.ndarray:
        """Centre wavelength (nm) of each DMD column, shape (columns,)."""
        return self._column_nm

    @property
    def column_matrix(self) -> np.ndarray:
        """(grid, columns) spectral irradiance (W m^-2 nm^-1) of each column with all its mirrors on."""
        return self._m

    @property
    def max_spectrum(self) -> np.ndarray:
        """Spectral irradiance (W m^-2 nm^-1) with every mirror on: the lamp's limit at each wavelength."""
        return self._m_max

    @property
    def minimum_exposure_s(self) -> float:
        return self.params.switch_time_s

    def check_exposure(self, exposure_s: float, name: str = "exposure_s") -> float:
        """Refuse an exposure shorter than pattern load plus mirror settling (80 us by default)."""
        t = check_number(name, exposure_s, low=0, low_open=True)
        if t < self.params.switch_time_s - 1e-12:
            raise ValueError(
                f"{name} = {t * 1e6:.1f} us is shorter than the light source's pattern switch time "
                f"{self.params.switch_time_s * 1e6:.0f} us ({self.params.pattern_load_s * 1e6:.0f} us load + "
                f"{self.params.mirror_settle_s * 1e6:.0f} us mirror settling)")
        return t

    # ---- pattern <-> spectrum --------------------------------------------------------------------------
    def check_pattern(self, pattern: ArrayLike, name: str = "pattern") -> np.ndarray:
        """Validate mirror counts: integers in [0, rows] with ``columns`` entries on the last axis."""
        arr = np.asarray(pattern)
        if arr.ndim < 1 or arr.shape[-1] != self.params.columns:
            raise ValueError(f"{name} must have {self.params.columns} columns on its last axis, got shape {arr.shape}")
        if not np.issubdtype(arr.dtype, np.integer):
            farr = check_array(name, arr)
            if np.any(farr != np.round(farr)):
                raise ValueError(f"{name} must hold integer mirror counts")
            arr = farr
        if arr.size and (arr.min() < 0 or arr.max() > self.params.rows):
            raise ValueError(f"{name} mirror counts must lie in [0, {self.params.rows}], "
                             f"got [{int(arr.min())}, {int(arr.max())}]")
        return arr.astype(np.int32)

    def pattern_to_spectrum(self, pattern: ArrayLike) -> np.ndarray:
        """Spectral irradiance (W m^-2 nm^-1, on :attr:`wavelengths`) emitted for mirror counts ``pattern``.

        ``pattern`` may be (columns,) or (K, columns); the result has the grid on the last axis.
        """
        n = self.check_pattern(pattern)
        out = (n / self.params.rows) @ self._m.T
        return out if self._offset is None else out + self._offset

    @property
    def offset_spectrum(self) -> np.ndarray:
        """Spectral irradiance with every mirror off (DMD off-state background; zeros on an ideal light)."""
        return np.zeros_like(self._wl) if self._offset is None else self._offset

    def illuminance(self, pattern: ArrayLike) -> np.ndarray:
        """Illuminance (lux) at the spot centre for mirror counts ``pattern`` ((columns,) or (K, columns)).

        ``683 lm/W * integral E(lambda) ybar(lambda) dlambda`` with the CIE 1931 2-degree ybar.
        """
        return K_M * self.pattern_to_spectrum(pattern) @ photopic_y(self._wl)

    def pattern_to_mirrors(self, pattern: ArrayLike) -> np.ndarray:
        """The (rows, columns) boolean mirror image of a pattern: in each column, its count of mirrors on,
        centred on the column (where the vertically spread beam is strongest is irrelevant in this model)."""
        n = self.check_pattern(pattern, "pattern")
        if n.ndim != 1:
            raise ValueError(f"pattern must be 1-D (columns,), got shape {n.shape}")
        rows = np.arange(self.params.rows)[:, None]
        start = (self.params.rows - n) // 2
        return (rows >= start[None, :]) & (rows < (start + n)[None, :])

    def spectrum_to_pattern(self, target, wavelengths: ArrayLike | None = None, *, fit: str = "clip") -> PatternFit:
        """Quantized pattern whose emission best matches ``target`` (bounded least squares, then rounding).

        Parameters
        ----------
        target
            Spectral irradiance, W m^-2 nm^-1, >= 0, finite; or an object with ``wavelengths`` and ``values``
            (e.g. a ``colour.SpectralDistribution``), whose wavelengths are then used.
        wavelengths
            Wavelengths (nm) of ``target``; default the light's own grid. The target is linearly interpolated
            onto the grid and taken as 0 outside its range.
        fit
            ``"clip"``: aim at the target as given; where it exceeds the lamp, the mirrors saturate and the
            excess is reported as ``clipped``. ``"scale"``: first scale the target down (or up) to the largest
            multiple every wavelength can reach.

        Returns
        -------
        PatternFit
        """
        if fit not in ("clip", "scale"):
            raise ValueError(f"fit must be one of 'clip', 'scale', got {fit!r}")
        if hasattr(target, "wavelengths") and hasattr(target, "values"):
            if wavelengths is not None:
                raise ValueError("wavelengths must not be given with a spectral distribution object")
            target, wavelengths = np.asarray(target.values), np.asarray(target.wavelengths)
        t = check_array("target", target, ndim=1, low=0.0)
        if wavelengths is None:
            if t.shape != self._wl.shape:
                raise ValueError(f"target must have shape {self._wl.shape} on the light's grid, got {t.shape}")
            tg = t.copy()
        else:
            wl = check_array("wavelengths", wavelengths, shape=(t.size,))
            if np.any(np.diff(wl) <= 0):
                raise ValueError("wavelengths must be strictly increasing")
            tg = np.interp(self._wl, wl, t, left=0.0, right=0.0)
        scale = 1.0
        if fit == "scale":
            pos = tg > 0
            if not np.any(pos):
                raise ValueError("target is zero everywhere; fit='scale' needs a positive target")
            # Keep a 0.5 % margin so the slit tails of neighbouring columns can still fill the band edges.
            with np.errstate(over="ignore", divide="ignore"):
                scale = 0.995 * float(np.min(self._m_max[pos] / tg[pos]))
            tg = tg * scale
        f = self._solve_levels(tg)
        counts = np.clip(np.rint(f * self.params.rows), 0, self.params.rows).astype(np.int32)
        emitted = self.pattern_to_spectrum(counts)
        err = emitted - tg
        rmse = float(np.sqrt(np.mean(err**2)))
        peak = float(tg.max())
        clipped = float(np.mean(tg > self._m_max * (1 + 1e-9)))
        return PatternFit(counts, tg, emitted, scale, rmse, rmse / peak if peak > 0 else 0.0, clipped)

    def _solve_levels(self, target: np.ndarray) -> np.ndarray:
        """Column levels in [0, 1] minimizing ||M f - target||: a first guess from the column centres,
        refined by projected gradient with Nesterov momentum (M is narrow-banded, so this converges fast)."""
        m = self._m
        lamp_at_col = np.interp(self._column_nm, self._wl, self._m_max)
        t_at_col = np.interp(self._column_nm, self._wl, target)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(lamp_at_col > 0, t_at_col / lamp_at_col, 0.0)
        f = np.clip(f, 0.0, 1.0)
        lipschitz = float(np.linalg.norm(m, 2) ** 2)
        step = 1.0 / lipschitz
        mt = m.T
        y = f.copy()
        tk = 1.0
        for _ in range(300):
            grad = mt @ (m @ y - target)
            f_new = np.clip(y - step * grad, 0.0, 1.0)
            tk_new = 0.5 * (1 + math.sqrt(1 + 4 * tk * tk))
            y = f_new + ((tk - 1) / tk_new) * (f_new - f)
            f, tk = f_new, tk_new
        return f

    # ---- the sequence and the trigger ------------------------------------------------------------------
    def load_sequence(self, patterns: ArrayLike) -> None:
        """Load a (K, columns) sequence of mirror-count patterns (time-varying mode); pattern 0 is shown."""
        n = self.check_pattern(patterns, "patterns")
        if n.ndim != 2 or n.shape[0] < 1:
            raise ValueError(f"patterns must have shape (K, {self.params.columns}) with K >= 1, got {n.shape}")
        self._sequence = n.copy()
        self._spectra = self.pattern_to_spectrum(n)
        self._index = 0
        self.sequence_version += 1  # lets a renderer know its cached per-pattern frames are stale

    def set_steady(self, pattern: ArrayLike) -> None:
        """Steady-state mode: the same pattern for every frame (a sequence of length 1)."""
        n = self.check_pattern(pattern, "pattern")
        if n.ndim != 1:
            raise ValueError(f"pattern must be 1-D ({self.params.columns},), got shape {n.shape}")
        self.load_sequence(n[None, :])

    @property
    def sequence(self) -> np.ndarray:
        """The loaded (K, columns) pattern sequence."""
        return self._sequence

    @property
    def sequence_spectra(self) -> np.ndarray:
        """(K, grid) spectral irradiance of each loaded pattern at the spot centre, W m^-2 nm^-1."""
        return self._spectra

    @property
    def pattern_index(self) -> int:
        return self._index

    def reset(self) -> None:
        """Show pattern 0 again (the state right after :meth:`load_sequence`)."""
        self._index = 0

    def trigger(self) -> int:
        self._index = (self._index + 1) % self._sequence.shape[0]
        return self._index

    def emitted_spectrum(self, index: int | None = None) -> np.ndarray:
        k = self._index if index is None else int(index)
        if not 0 <= k < self._spectra.shape[0]:
            raise ValueError(f"index must lie in [0, {self._spectra.shape[0] - 1}], got {index}")
        return self._spectra[k]

    # ---- time behaviour --------------------------------------------------------------------------------
    def fluctuation_std(self, exposure_s: float) -> float:
        """Relative RMS of the frame-to-frame power fluctuation for an exposure (s)."""
        p = self.params
        return p.fluctuation_rms * math.sqrt(p.fluctuation_reference_exposure_s / exposure_s)

    def power_factors(self, timestamps_s: ArrayLike, exposure_s: float,
                      rng: np.random.Generator | None = None) -> np.ndarray:
        """Relative emitted power averaged over each exposure starting at ``timestamps_s`` (s).

        ``1 + drift * t / 3600 + flicker averaged over the exposure + fluctuation``; the fluctuation is drawn from
        ``rng`` (the light's own generator by default), the rest is deterministic.
        """
        p = self.params
        t = np.asarray(timestamps_s, dtype=np.float64)
        factor = 1.0 + (p.drift_per_hour + self.realism.lamp_output_drift_per_hour) * t / 3600.0
        if p.flicker_amplitude > 0:
            w = 2 * math.pi * p.flicker_frequency_hz
            factor = factor + p.flicker_amplitude * (np.cos(w * t) - np.cos(w * (t + exposure_s))) / (w * exposure_s)
        if p.fluctuation_rms > 0:
            gen = self._rng if rng is None else rng
            factor = factor + self.fluctuation_std(exposure_s) * gen.standard_normal(t.shape)
        return np.maximum(factor, 0.0)

    # ---- the lit spot (paper Figs. 4, 5) ----------------------------------------------------------------
    def centre_illuminance(self, spot_diameter_mm: float | None = None) -> float:
        """Illuminance (lux) at the spot centre with every mirror on, for a spot diameter (mm).

        The light guide delivers a fixed flux, so the centre illuminance scales as ``1 / d**2`` (paper Fig. 5).
        """
        d = self.params.spot_diameter_mm if spot_diameter_mm is None else check_number(
            "spot_diameter_mm", spot_diameter_mm, low=0, low_open=True)
        return self.params.illuminance_lux * (self.params.spot_diameter_mm / d) ** 2

    def field_profile(self, height: int, width: int, pixel_mm: float) -> np.ndarray:
        """Relative irradiance (1 at the spot centre) over a (height, width) field of ``pixel_mm`` pixels.

        Super-Gaussian spot ``2 ** -((2 r / d) ** (2 p))`` with ``d = spot_diameter_mm``, ``p = spot_flatness``.
        Returns float32, values in (0, 1].
        """
        p = self.params
        y = (np.arange(height) - (height - 1) / 2.0) * pixel_mm - p.spot_centre_mm[1]
        x = (np.arange(width) - (width - 1) / 2.0) * pixel_mm - p.spot_centre_mm[0]
        r2 = (x[None, :] ** 2 + y[:, None] ** 2) * (4.0 / p.spot_diameter_mm**2)
        return np.power(2.0, -np.power(r2, p.spot_flatness)).astype(np.float32)
