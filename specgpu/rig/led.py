"""An LED array as the programmable light: each LED a primary, its PWM duty the level.

Every programmable light of the twin emits ``P . w``: ``P`` (grid x channels) the spectra of its primaries at full
level, ``w`` in ``[0, 1]`` their levels. For the DMD (:mod:`specgpu.rig.light`) the primaries are the columns and
``w`` the share of mirrors on; here they are the LEDs and ``w`` their PWM duty. A **pattern** is still a vector of
integer levels, one per channel, in ``[0, rows]``: ``rows = 2**pwm_bits - 1`` duty steps, so plans, captures
and calibration bundles speak of LEDs exactly as of columns.

What the model holds, beyond ``P . w`` (all off by default except the duty quantisation, which is the pattern):

- each LED's spectrum: a CSV of measured spectra (``spectra``: wavelength, then one column per LED), or a
  data-sheet shape from its peak and FWHM: Ohno's LED model ``(g + 2 g**5) / 3``, ``g`` a Gaussian in
  wavelength (Ohno, Opt. Eng. 44, 2005), which has the steep flanks and broad foot of a real die;
- PWM at ``pwm_frequency_hz``: the duty is exact only over whole PWM periods. The pulse starts with the exposure
  (the controller restarts PWM on the trigger), so an exposure of ``N`` periods with a fraction ``phi`` over
  ``floor(N)`` gives the level ``(floor(N) w + min(w, phi)) / N``; ``pwm_mismatch`` says whether such an exposure
  is refused or accepted with a one-line warning;
- rise and fall time (first order): each pulse loses ``rise`` and gains ``fall`` of light, so a duty strictly
  between 0 and 1 shifts by ``(fall - rise) * pwm_frequency_hz``; the light needs ``settle_s + 5 max(rise, fall)``
  to switch patterns (its switch time);
- thermal droop and peak shift: the junction of LED ``c`` warms by ``junction_K_per_duty`` times its mean duty
  over the loaded sequence (the sequence is far shorter than the junction's thermal time), reached with the time
  constant ``thermal_time_constant_s`` on the light's clock (0: at once); the LED's output falls by ``droop_per_K``
  per kelvin and its spectrum moves by ``peak_shift_nm_per_K``. Calibration measures each LED at full duty, so a
  design at low duty sees less droop than the model: the non-linearity a lab meets;
- channel cross-talk: a fraction ``crosstalk`` of each channel's drive leaks into its neighbours on the board
  (channels in order of peak wavelength).

Presets (``preset = "led6" | "led12" | "led16"``) place narrowband LEDs across 400-700 nm at wavelengths commercial
dies are sold at, with data-sheet widths and relative powers (:data:`LED_PRESETS`, :func:`typical_fwhm_nm`,
:func:`typical_power`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, fields
from functools import lru_cache
from pathlib import Path

import numpy as np

from specgpu.core.validate import check_number
from specgpu.rig.light import K_M, ProgrammableLight, photopic_y
from specgpu.rig.realism import Drift, Realism

__all__ = ["LED_PRESETS", "LEDLight", "LEDParameters", "led_shape", "period_levels", "read_led_spectra",
           "typical_fwhm_nm", "typical_power"]

#: Peak wavelengths (nm) of the presets, each LED's light within 400-700 nm: the designs leave out a primary that
#: puts over 1 % of the camera's signal outside the prior's range (a 405 nm violet die puts 23 % below 400 nm; a
#: 670 nm deep red about 2 % above 700), so the peaks lie in 430-660 nm, at wavelengths dies are sold at.
#: ``led12``: twelve narrowband LEDs across the visible about 20 nm apart, as a 12-band LED illuminator
#: (Lumosaic-like): royal blue 430 and 450, blue 470, cyan 490 and 505, green 525, 545 and lime 565 (the "green
#: gap" 540-580 nm has only weak dies), amber 590, orange 610, red 630, deep red 660 (the reddest within, for the
#: reflectance up to 700 nm). ``led16``: every 15 nm from 430 to 640 nm, and 660; ``led6``: about every 45 nm.
LED_PRESETS = {
    "led6": (435.0, 480.0, 525.0, 570.0, 615.0, 660.0),
    "led12": (430.0, 450.0, 470.0, 490.0, 505.0, 525.0, 545.0, 565.0, 590.0, 610.0, 630.0, 660.0),
    "led16": tuple(430.0 + 15.0 * i for i in range(15)) + (660.0,),
}

# Data-sheet FWHM (nm) by peak: InGaN dies widen from violet to green, AlInGaP (amber to deep red) are narrow.
_FWHM_TABLE = ((380.0, 12.0), (400.0, 14.0), (450.0, 20.0), (500.0, 28.0), (530.0, 33.0), (565.0, 35.0),
               (580.0, 16.0), (630.0, 18.0), (670.0, 22.0), (780.0, 30.0))
# Relative radiant power at a common drive: blue dies are the strongest, the green gap the weakest.
_POWER_TABLE = ((380.0, 0.8), (400.0, 1.0), (450.0, 1.0), (500.0, 0.6), (530.0, 0.45), (560.0, 0.3),
                (590.0, 0.4), (620.0, 0.7), (660.0, 0.8), (700.0, 0.6), (780.0, 0.5))

PWM_MISMATCH = ("refuse", "warn")


def typical_fwhm_nm(peak_nm) -> np.ndarray:
    """Data-sheet FWHM (nm) of a narrowband LED peaking at ``peak_nm`` (piecewise linear over typical dies)."""
    x, y = zip(*_FWHM_TABLE)
    return np.interp(np.asarray(peak_nm, np.float64), x, y)


def typical_power(peak_nm) -> np.ndarray:
    """Relative radiant power of an LED peaking at ``peak_nm`` at a common drive (piecewise linear)."""
    x, y = zip(*_POWER_TABLE)
    return np.interp(np.asarray(peak_nm, np.float64), x, y)


@lru_cache(maxsize=1)
def _ohno_half() -> float:
    """The x > 0 where ``(exp(-x**2) + 2 exp(-5 x**2)) / 3`` is 1/2 (bisection)."""
    lo, hi = 0.0, 2.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if (math.exp(-mid * mid) + 2 * math.exp(-5 * mid * mid)) / 3 > 0.5:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def led_shape(wavelengths, peak_nm: float, fwhm_nm: float) -> np.ndarray:
    """Ohno's LED spectrum ``(g + 2 g**5) / 3`` at ``wavelengths`` (nm), peak 1 at ``peak_nm``, FWHM ``fwhm_nm``."""
    width = fwhm_nm / (2.0 * _ohno_half())
    g = np.exp(-(((np.asarray(wavelengths, np.float64) - peak_nm) / width) ** 2))
    return (g + 2.0 * g**5) / 3.0


def read_led_spectra(path) -> tuple[np.ndarray, np.ndarray]:
    """Measured LED spectra from a CSV: wavelength (nm), then one column of relative power per LED; ``#`` comments
    and one header line skipped. Returns (wavelengths (N,) increasing, spectra (N, C)); errors name the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read LED spectra ({exc.__class__.__name__})") from None
    rows, header = [], False
    for number, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [f for f in s.replace(";", ",").replace("\t", ",").replace(" ", ",").split(",") if f]
        try:
            values = [float(f) for f in parts]
        except ValueError:
            if rows or header:
                raise ValueError(f"{path}:{number}: expected numbers, got {s!r}") from None
            header = True
            continue
        if len(values) < 2 or (rows and len(values) != len(rows[0])):
            raise ValueError(f"{path}:{number}: expected a wavelength and one value per LED "
                             f"({len(rows[0]) if rows else 'two or more'} columns), got {len(values)}")
        if not all(math.isfinite(v) for v in values) or any(v < 0 for v in values[1:]):
            raise ValueError(f"{path}:{number}: NaN, infinite or negative value in {s!r}")
        rows.append(values)
    if len(rows) < 3:
        raise ValueError(f"{path}: LED spectra need at least 3 rows, got {len(rows)}")
    data = np.array(rows)
    data = data[np.argsort(data[:, 0], kind="stable")]
    if np.any(np.diff(data[:, 0]) <= 0):
        raise ValueError(f"{path}: wavelengths must not repeat")
    return data[:, 0], data[:, 1:]


@dataclass(frozen=True)
class LEDParameters:
    """An LED array light (``[light] kind = "led"``): every field is a key of the rig TOML's ``[light]`` table.

    Attributes
    ----------
    kind : str
        ``"led"``.
    preset : str
        ``"led6"``, ``"led12"`` (default) or ``"led16"`` (:data:`LED_PRESETS`), used when neither ``spectra`` nor
        ``peaks_nm`` is given.
    spectra : str
        A CSV of measured spectra (wavelength nm, one column per LED); overrides ``preset`` and ``peaks_nm``.
    peaks_nm, fwhm_nm, relative_power : tuple of float
        Data-sheet LEDs: peak wavelengths (increasing), FWHMs and relative radiant powers (empty: the typical
        values of :func:`typical_fwhm_nm`, :func:`typical_power`; one value: for every LED).
    pwm_bits : int
        Duty resolution: ``2**pwm_bits - 1`` steps (the pattern's ``rows``), 1-16. Default 8.
    pwm_frequency_hz : float
        PWM frequency, Hz. Default 20000.
    pwm_mismatch : str
        An exposure that is not a whole number of PWM periods: ``"refuse"`` or ``"warn"`` (default; the level
        error it causes is modelled). Shorter than one period is always refused.
    rise_time_s, fall_time_s : float
        First-order optical rise and fall times, s. Default 0.
    settle_s : float
        Driver's time to take a new pattern, s. Default 20e-6.
    junction_K_per_duty, droop_per_K, peak_shift_nm_per_K, thermal_time_constant_s : float
        Junction heating at full duty (K), output loss per K, peak shift per K (nm), and the warm-up time
        constant on the light's clock (s; 0: warm at once). Default 0 (no thermal effects).
    crosstalk : float
        Share of each channel's drive leaking into each neighbour, in [0, 0.2]. Default 0.
    illuminance_lux, spot_diameter_mm, spot_flatness, spot_centre_mm : as the DMD's (:class:`LightParameters`).
    fluctuation_rms, fluctuation_reference_exposure_s, drift_per_hour, flicker_amplitude, flicker_frequency_hz :
        as the DMD's; an LED on a constant-current driver fluctuates far less than an arc: default 0.001.
    wavelength_min_nm, wavelength_max_nm : float
        The light's 1 nm grid. Defaults 380 and 780.
    """

    kind: str = "led"
    preset: str = "led12"
    spectra: str = ""
    peaks_nm: tuple = ()
    fwhm_nm: tuple = ()
    relative_power: tuple = ()
    pwm_bits: int = 8
    pwm_frequency_hz: float = 20000.0
    pwm_mismatch: str = "warn"
    rise_time_s: float = 0.0
    fall_time_s: float = 0.0
    settle_s: float = 20e-6
    junction_K_per_duty: float = 0.0
    droop_per_K: float = 0.0
    peak_shift_nm_per_K: float = 0.0
    thermal_time_constant_s: float = 0.0
    crosstalk: float = 0.0
    illuminance_lux: float = 15000.0
    spot_diameter_mm: float = 80.0
    spot_flatness: float = 2.0
    spot_centre_mm: tuple[float, float] = (0.0, 0.0)
    fluctuation_rms: float = 0.001
    fluctuation_reference_exposure_s: float = 0.0110
    drift_per_hour: float = 0.0
    flicker_amplitude: float = 0.0
    flicker_frequency_hz: float = 100.0
    wavelength_min_nm: float = 380.0
    wavelength_max_nm: float = 780.0

    def __post_init__(self):
        n = "light."
        if self.kind != "led":
            raise ValueError(f"{n}kind must be 'led' for LEDParameters, got {self.kind!r}")
        if self.preset not in LED_PRESETS:
            raise ValueError(f"{n}preset must be one of {', '.join(LED_PRESETS)}, got {self.preset!r}")
        if self.pwm_mismatch not in PWM_MISMATCH:
            raise ValueError(f"{n}pwm_mismatch must be one of {', '.join(PWM_MISMATCH)}, got {self.pwm_mismatch!r}")
        for key in ("peaks_nm", "fwhm_nm", "relative_power"):
            v = tuple(getattr(self, key))
            if any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v):
                raise ValueError(f"{n}{key} must be a list of numbers, got {list(v)!r}")
            object.__setattr__(self, key, tuple(float(x) for x in v))
        peaks = self.peaks_nm
        if peaks:
            if len(peaks) < 2 or any(b <= a for a, b in zip(peaks, peaks[1:])):
                raise ValueError(f"{n}peaks_nm must hold two or more increasing wavelengths, got {list(peaks)}")
            for p in peaks:
                check_number(n + "peaks_nm", p, low=300, high=1100)
        for key, low, high in (("fwhm_nm", 1.0, 200.0), ("relative_power", 0.0, 1e6)):
            v = getattr(self, key)
            if v and len(v) not in (1, len(self.peaks_nm) or len(LED_PRESETS[self.preset])):
                count = len(self.peaks_nm or LED_PRESETS[self.preset])
                raise ValueError(f"{n}{key} must hold one value or one per LED ({count}), "
                                 f"got {len(v)}")
            for x in v:
                check_number(n + key, x, low=low, high=high, low_open=key == "relative_power")
        check_number(n + "pwm_bits", self.pwm_bits, low=1, high=16, integer=True)
        check_number(n + "pwm_frequency_hz", self.pwm_frequency_hz, low=0, low_open=True, high=1e8)
        for key in ("rise_time_s", "fall_time_s", "settle_s"):
            check_number(n + key, getattr(self, key), low=0, high=0.1)
        check_number(n + "junction_K_per_duty", self.junction_K_per_duty, low=0, high=200)
        check_number(n + "droop_per_K", self.droop_per_K, low=0, high=0.01)
        check_number(n + "peak_shift_nm_per_K", self.peak_shift_nm_per_K, low=-1, high=1)
        check_number(n + "thermal_time_constant_s", self.thermal_time_constant_s, low=0, high=1e5)
        check_number(n + "crosstalk", self.crosstalk, low=0, high=0.2)
        check_number(n + "illuminance_lux", self.illuminance_lux, low=0, low_open=True, high=1e7)
        check_number(n + "spot_diameter_mm", self.spot_diameter_mm, low=0, low_open=True, high=1e4)
        check_number(n + "spot_flatness", self.spot_flatness, low=0.5, high=20)
        if len(tuple(self.spot_centre_mm)) != 2:
            raise ValueError(f"{n}spot_centre_mm must be two numbers (x, y) in mm, got {self.spot_centre_mm!r}")
        check_number(n + "fluctuation_rms", self.fluctuation_rms, low=0, high=0.5)
        check_number(n + "fluctuation_reference_exposure_s", self.fluctuation_reference_exposure_s,
                     low=0, low_open=True, high=10)
        check_number(n + "drift_per_hour", self.drift_per_hour, low=-1, high=1)
        check_number(n + "flicker_amplitude", self.flicker_amplitude, low=0, high=1)
        check_number(n + "flicker_frequency_hz", self.flicker_frequency_hz, low=0, low_open=True, high=1e6)
        lo = check_number(n + "wavelength_min_nm", self.wavelength_min_nm, low=200, high=2000)
        hi = check_number(n + "wavelength_max_nm", self.wavelength_max_nm, low=200, high=2000)
        if hi - lo < 10:
            raise ValueError(f"{n}wavelength_max_nm ({hi:g}) must exceed wavelength_min_nm ({lo:g}) by >= 10 nm")
        if not self.spectra and self.peaks_nm and (min(self.peaks_nm) < lo or max(self.peaks_nm) > hi):
            raise ValueError(f"{n}peaks_nm must lie within {lo:g}-{hi:g} nm (the light's grid)")

    # What the rest of the twin asks any light's parameters (the DMD's names, the LEDs' meaning).
    @property
    def columns(self) -> int:
        """Number of LEDs (the primaries)."""
        if self.spectra:
            return int(read_led_spectra(self.spectra)[1].shape[1])
        return len(self.peaks_nm or LED_PRESETS[self.preset])

    @property
    def rows(self) -> int:
        """Duty steps: a pattern's levels are integers in [0, rows]."""
        return 2 ** int(self.pwm_bits) - 1

    @property
    def switch_time_s(self) -> float:
        """Time the light needs to take a new pattern: driver settling plus five rise or fall times."""
        return self.settle_s + 5.0 * max(self.rise_time_s, self.fall_time_s)

    @property
    def line_fwhm_nm(self) -> float:
        """The widest LED's FWHM (nm): how far beyond its peaks the light reaches (of measured spectra: the widest
        span above half the peak)."""
        if not self.spectra:
            return float(np.max(self.data_sheet()[1]))
        wl, spectra = read_led_spectra(self.spectra)
        return float(max(_half_width(wl, s) for s in spectra.T))

    second_order_leakage = 0.0

    @property
    def exposure_quantum_s(self) -> float:
        """One PWM period (s): an exposure of whole periods sees each LED's duty exactly."""
        return 1.0 / self.pwm_frequency_hz

    def data_sheet(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(peaks nm, FWHMs nm, relative powers) of the data-sheet LEDs."""
        peaks = np.array(self.peaks_nm or LED_PRESETS[self.preset])
        fwhm = np.broadcast_to(np.array(self.fwhm_nm), peaks.shape) if self.fwhm_nm else typical_fwhm_nm(peaks)
        power = (np.broadcast_to(np.array(self.relative_power), peaks.shape) if self.relative_power
                 else typical_power(peaks))
        return peaks, np.array(fwhm, np.float64), np.array(power, np.float64)

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


def _half_width(wl: np.ndarray, s: np.ndarray) -> float:
    """Span (nm) of a spectrum above half its peak, its edges interpolated between samples."""
    half = 0.5 * float(s.max())
    above = np.flatnonzero(s >= half)
    lo, hi = int(above[0]), int(above[-1])
    left = wl[lo] if lo == 0 else np.interp(half, [s[lo - 1], s[lo]], [wl[lo - 1], wl[lo]])
    right = wl[hi] if hi == s.size - 1 else np.interp(half, [s[hi + 1], s[hi]], [wl[hi + 1], wl[hi]])
    return float(right - left)


def period_levels(levels: np.ndarray, periods: float) -> np.ndarray:
    """Mean level over an exposure of ``periods`` PWM periods (pulse first in each period, the exposure starting
    with a period): ``(floor(N) w + min(w, N - floor(N))) / N``; exact ``w`` for a whole number of periods."""
    whole = math.floor(periods + 1e-9)
    part = max(0.0, periods - whole)
    if part < 1e-6:
        return levels
    return (whole * levels + np.minimum(levels, part)) / periods


class LEDLight(ProgrammableLight):
    """The LED array of the twin: :class:`ProgrammableLight`'s interface (patterns, sequence, trigger, spot,
    fluctuation) over LEDs instead of DMD columns.

    Parameters
    ----------
    params : LEDParameters
    seed : int
        Seed of the light's own fluctuation.
    realism, drift
        The bench's imperfections; the DMD's own (slit, column map, grating, off-state, lamp colour) do not apply
        to LEDs, the lamp output drift does.
    clock_s : float
        The light's clock (s since it was switched on): the LEDs' warm-up.
    exposure_s : float, optional
        The camera's exposure: the PWM periods it holds set the level an exposure sees.
    """

    lamp_colour_drifts = False

    def __init__(self, params: LEDParameters | None = None, *, seed: int = 0, realism=None, drift=None,
                 clock_s: float = 0.0, exposure_s: float | None = None):
        self.params = p = params if params is not None else LEDParameters()
        self.realism = realism if realism is not None else Realism()
        self.drift = drift if drift is not None else Drift()
        self.clock_s = check_number("clock_s", clock_s, low=0)
        self.exposure_s = exposure_s
        self._wl = np.arange(p.wavelength_min_nm, p.wavelength_max_nm + 0.5, 1.0)
        if p.spectra:
            src_wl, src = read_led_spectra(p.spectra)
            shapes = np.stack([np.interp(self._wl, src_wl, src[:, c], left=0.0, right=0.0)
                               for c in range(src.shape[1])], axis=1)
            if np.any(shapes.max(axis=0) <= 0):
                raise ValueError(f"light.spectra {p.spectra}: an LED emits nothing within "
                                 f"{p.wavelength_min_nm:g}-{p.wavelength_max_nm:g} nm")
            centroid = (self._wl @ shapes) / shapes.sum(axis=0)
            order = np.argsort(centroid)
            shapes, centroid = shapes[:, order], centroid[order]
            if np.any(np.diff(centroid) <= 0):
                raise ValueError(f"light.spectra {p.spectra}: two LEDs share a centroid wavelength")
            self._peak = centroid
            self._measured = True
            self._shapes = shapes / shapes.sum(axis=0)[None, :]
            self._power = np.ones(shapes.shape[1])
        else:
            self._peak, self._fwhm, self._power = p.data_sheet()
            self._measured = False
            self._shapes = self._data_sheet_shapes(np.zeros_like(self._peak))
        full = (self._shapes * self._power[None, :]).sum(axis=1)
        lux_per_unit = K_M * float(full @ photopic_y(self._wl))
        if not lux_per_unit > 0:
            raise ValueError("light: the LEDs emit no visible light, cannot scale to light.illuminance_lux")
        self._scale = p.illuminance_lux / lux_per_unit
        self._m = self._shapes * (self._power * self._scale)[None, :]
        self._m_max = self._m.sum(axis=1)
        self._offset = None
        self._column_nm = self._peak
        self._sequence = np.zeros((1, p.columns), dtype=np.int32)
        self._spectra = np.zeros((1, self._wl.size))
        self._index = 0
        self.sequence_version = 0
        self._rng = np.random.default_rng(seed)

    def _data_sheet_shapes(self, shift_nm: np.ndarray) -> np.ndarray:
        shapes = np.stack([led_shape(self._wl, pk + s, fw) for pk, s, fw in zip(self._peak, shift_nm, self._fwhm)],
                          axis=1)
        return shapes / shapes.sum(axis=0)[None, :]  # unit area on the 1 nm grid: W m^-2 per unit power

    @property
    def column_wavelengths(self) -> np.ndarray:
        """Each LED's peak (data sheet) or centroid (measured spectra), nm."""
        return self._column_nm

    def check_exposure(self, exposure_s: float, name: str = "exposure_s") -> float:
        """Refuse an exposure shorter than the switch time or one PWM period; one that is not a whole number of
        PWM periods is refused or warned about (``light.pwm_mismatch``)."""
        p = self.params
        t = check_number(name, exposure_s, low=0, low_open=True)
        if t < p.switch_time_s - 1e-12:
            raise ValueError(f"{name} = {t * 1e6:.1f} us is shorter than the LED light's switch time "
                             f"{p.switch_time_s * 1e6:.0f} us")
        periods = t * p.pwm_frequency_hz
        if periods < 1 - 1e-9:
            raise ValueError(f"{name} = {t * 1e6:.1f} us is shorter than one PWM period of light.pwm_frequency_hz = "
                             f"{p.pwm_frequency_hz:g} Hz")
        part = periods - math.floor(periods + 1e-9)
        if part > 1e-6:
            msg = (f"{name} = {t * 1e3:g} ms is not a whole number of PWM periods at light.pwm_frequency_hz = "
                   f"{p.pwm_frequency_hz:g} Hz ({periods:.3f}): levels err by up to {100 * part / periods:.2g} %")
            if p.pwm_mismatch == "refuse":
                raise ValueError(msg + "; use a multiple of the PWM period or light.pwm_mismatch = \"warn\"")
            warnings.warn(msg, stacklevel=2)
        return t

    def effective_levels(self, levels: np.ndarray) -> np.ndarray:
        """The duty each LED delivers over the exposure for commanded levels (..., C) in [0, 1]: cross-talk, the
        rise and fall of each pulse and the whole PWM periods the exposure holds."""
        p = self.params
        w = np.asarray(levels, np.float64)
        if p.crosstalk:
            nb = np.zeros_like(w)
            nb[..., 1:] += w[..., :-1]
            nb[..., :-1] += w[..., 1:]
            w = np.minimum(1.0, w + p.crosstalk * nb)
        if p.rise_time_s or p.fall_time_s:
            inside = (w > 0) & (w < 1)
            w = np.where(inside, np.clip(w + (p.fall_time_s - p.rise_time_s) * p.pwm_frequency_hz, 0.0, 1.0), w)
        if self.exposure_s is not None:
            w = period_levels(w, self.exposure_s * p.pwm_frequency_hz)
        return w

    def junction_rise_K(self, patterns) -> np.ndarray:
        """(C,) junction temperature rise (K) of each LED running ``patterns`` (K, C) in turn, at the clock."""
        p = self.params
        if not p.junction_K_per_duty:
            return np.zeros(p.columns)
        duty = np.atleast_2d(np.asarray(patterns, np.float64) / p.rows).mean(axis=0)
        warm = 1.0 if not p.thermal_time_constant_s else 1.0 - math.exp(-self.clock_s / p.thermal_time_constant_s)
        return p.junction_K_per_duty * duty * warm

    def pattern_to_spectrum(self, pattern) -> np.ndarray:
        """Spectral irradiance (W m^-2 nm^-1) for duty levels ``pattern`` ((C,) or (K, C) integers in [0, rows]),
        the LEDs' temperatures those patterns give included."""
        n = self.check_pattern(pattern)
        w = self.effective_levels(n / self.params.rows)
        p = self.params
        rise = self.junction_rise_K(n)
        if not rise.any():
            return w @ self._m.T
        shapes = self._shapes
        if p.peak_shift_nm_per_K and not self._measured:
            shapes = self._data_sheet_shapes(p.peak_shift_nm_per_K * rise)
        elif p.peak_shift_nm_per_K:  # measured spectra: moved along the grid
            shapes = np.stack([np.interp(self._wl - s, self._wl, shapes[:, c], left=0.0, right=0.0)
                               for c, s in enumerate(p.peak_shift_nm_per_K * rise)], axis=1)
        m = shapes * (self._power * self._scale * np.maximum(0.0, 1.0 - p.droop_per_K * rise))[None, :]
        return w @ m.T

    def pattern_to_mirrors(self, pattern):
        raise ValueError("an LED light has no mirrors: its pattern is the LEDs' duty levels")
