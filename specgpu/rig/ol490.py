"""The Optronic Laboratories OL490 as the programmable light: the paper's instrument, with its own DMD controller.

The OL490 is the lamp, grating and DMD of :mod:`specgpu.rig.light` (1024 columns across 380-780 nm), driven by its
controller in grey-level mode: each column's level is ``grey_bits`` deep (1-6 bits, ``2**grey_bits - 1`` steps,
the pattern's ``rows``), shown as binary-weighted bit planes. The model of the trade between grey depth and
frame rate: the DMD shows ``binary_rate_hz`` bit planes per second, so one grey pattern takes
``(2**grey_bits - 1) / binary_rate_hz`` (its **grey period**) and the light gives at most
``1 / (grey period + switch time)`` spectra per second: at the default 9600 planes/s, 152 spectra/s at 6 bits,
about 9.6 thousand at 1 bit. A grey level is exact only over whole grey periods: an exposure shorter than one is
refused, and one that is not a whole number of them is warned about (the level it gives is modelled as for
PWM: :func:`specgpu.rig.led.period_levels`).

The four slits of its calibrations set the column's band (FWHM): ``slit = 1 | 2 | 3 | 4`` for 2.5, 5, 10 and 20
nm (:data:`SLIT_FWHM_NM`; a model of four slit calibrations, the paper's rig at 5 nm, not a data sheet's values).
The binary rate is likewise a model value, of the order of a DLP controller's bit-plane rate.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from specgpu.core.validate import check_number
from specgpu.rig.led import period_levels
from specgpu.rig.light import LightParameters, ProgrammableLight

__all__ = ["OL490Light", "OL490Parameters", "SLIT_FWHM_NM"]

#: Band (FWHM, nm) of one column for each of the OL490's four slit calibrations.
SLIT_FWHM_NM = {1: 2.5, 2: 5.0, 3: 10.0, 4: 20.0}

_BASE = LightParameters()


@dataclass(frozen=True)
class OL490Parameters(LightParameters):
    """The OL490 (``[light] kind = "ol490"``): the DMD light's keys, plus its controller's.

    Attributes
    ----------
    kind : str
        ``"ol490"``.
    grey_bits : int
        Grey depth, 1-6 bits. Default 6. Sets ``rows = 2**grey_bits - 1``.
    slit : int
        Slit calibration 1-4 (:data:`SLIT_FWHM_NM`). Default 2 (5 nm). Sets ``line_fwhm_nm``.
    binary_rate_hz : float
        Bit planes per second. Default 9600.

    ``rows`` and ``line_fwhm_nm`` follow ``grey_bits`` and ``slit``: giving them another value is an error.
    """

    kind: str = "ol490"
    grey_bits: int = 6
    slit: int = 2
    binary_rate_hz: float = 9600.0

    def __post_init__(self):
        n = "light."
        if self.kind != "ol490":
            raise ValueError(f"{n}kind must be 'ol490' for OL490Parameters, got {self.kind!r}")
        bits = check_number(n + "grey_bits", self.grey_bits, low=1, high=6, integer=True)
        if self.slit not in SLIT_FWHM_NM or isinstance(self.slit, bool):
            raise ValueError(f"{n}slit must be one of 1, 2, 3, 4 (FWHM "
                             f"{', '.join(f'{v:g}' for v in SLIT_FWHM_NM.values())} nm), got {self.slit!r}")
        check_number(n + "binary_rate_hz", self.binary_rate_hz, low=1, high=1e6)
        for key, value in (("rows", 2**bits - 1), ("line_fwhm_nm", SLIT_FWHM_NM[self.slit])):
            given = getattr(self, key)
            if given != getattr(_BASE, key) and given != value:
                raise ValueError(f"{n}{key} = {given!r} contradicts the OL490's grey_bits / slit (which give "
                                 f"{value!r}); leave it out")
            object.__setattr__(self, key, value)
        super().__post_init__()

    @property
    def grey_period_s(self) -> float:
        """Time (s) the DMD takes to show one grey pattern: ``(2**grey_bits - 1) / binary_rate_hz``."""
        return (2**self.grey_bits - 1) / self.binary_rate_hz

    @property
    def exposure_quantum_s(self) -> float:
        """One grey period (s): an exposure of whole periods sees each column's grey level exactly."""
        return self.grey_period_s

    @property
    def max_spectra_per_s(self) -> float:
        """The most patterns per second at this grey depth: ``1 / (grey period + switch time)``."""
        return 1.0 / (self.grey_period_s + self.switch_time_s)


class OL490Light(ProgrammableLight):
    """The OL490 of the twin: the DMD light with its grey-level controller (see the module docstring)."""

    def __init__(self, params: OL490Parameters | None = None, *, exposure_s: float | None = None, **kwargs):
        super().__init__(params if params is not None else OL490Parameters(), **kwargs)
        self.exposure_s = exposure_s

    def check_exposure(self, exposure_s: float, name: str = "exposure_s") -> float:
        """The DMD's switch time, then whole grey periods: shorter than one is refused, a fraction warned about."""
        t = super().check_exposure(exposure_s, name)
        p = self.params
        periods = t / p.grey_period_s
        if periods < 1 - 1e-9:
            raise ValueError(f"{name} = {t * 1e6:.1f} us is shorter than the OL490's grey period "
                             f"{p.grey_period_s * 1e6:.0f} us at light.grey_bits = {p.grey_bits} (at most "
                             f"{p.max_spectra_per_s:.0f} spectra/s); use fewer grey bits or a longer exposure")
        part = periods - math.floor(periods + 1e-9)
        if part > 1e-6:
            warnings.warn(f"{name} = {t * 1e3:g} ms is not a whole number of the OL490's grey periods "
                          f"({p.grey_period_s * 1e6:.0f} us at light.grey_bits = {p.grey_bits}): levels err by up to "
                          f"{100 * part / periods:.2g} %", stacklevel=2)
        return t

    def pattern_to_spectrum(self, pattern) -> np.ndarray:
        """As the DMD's, the levels averaged over the whole grey periods the exposure holds."""
        n = self.check_pattern(pattern)
        w = n / self.params.rows
        if self.exposure_s is not None:
            w = period_levels(w, self.exposure_s / self.params.grey_period_s)
        out = w @ self._m.T
        return out if self._offset is None else out + self._offset
