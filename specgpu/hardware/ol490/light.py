"""The OL490 as a :class:`~specgpu.capture.driver.LightSource`.

Patterns are what a plan makes for the DMD light: (K, columns) mirror counts in [0, rows] of the light's model
(:class:`~specgpu.rig.light.ProgrammableLight`: 1024 columns by 768 rows by default, the OL490's own DMD). Each is
sent as a grey level per DMD column, ``round(count / rows * (2**bits - 1))`` at the grey depth chosen (1 to 6 bit),
a model of fewer columns spread evenly over the unit's 1024. The deeper the grey, the finer the levels and the
lower the highest frame rate the unit reports (:attr:`OL490Light.max_frame_rate_hz`): an exposure is at least one
frame of it. :meth:`OL490Light.emitted_spectrum` gives the model's spectrum of the levels actually shown.

The camera is the master: the sequence is loaded into the unit's memory and each edge of its trigger input (the
camera's exposure-active output) shows the next pattern, so exposure ``n`` is lit by pattern ``n mod K``.
:meth:`OL490Light.check` refuses a frame when the sequence stopped or the unit counted fewer steps than the camera
made exposures (a trigger that never reached it), so nothing is mislabelled.
"""

from __future__ import annotations

import numpy as np

from specgpu.capture.driver import LightSource
from specgpu.core.validate import check_number
from specgpu.hardware.errors import LightFault
from specgpu.hardware.ol490.sdk import COLUMNS, GREY_BITS, SLITS, OL490Unit
from specgpu.hardware.stepping import TriggerStepped
from specgpu.rig.light import ProgrammableLight

__all__ = ["OL490Light"]


class OL490Light(TriggerStepped, LightSource):
    """An OL490 through its SDK (:class:`~specgpu.hardware.ol490.sdk.OL490Unit`).

    Parameters
    ----------
    unit : OL490Unit
        The connected unit.
    model : ProgrammableLight, optional
        Columns, rows and the emitted spectra (default: the nominal light).
    calibration : CalibrationBundle, optional
        Its forward model gives :meth:`emitted_spectrum` when given.
    slit : int
        Stored calibration to load, 1 to 4.
    grey_bits : int
        Grey depth, 1 to 6 bit.
    """

    def __init__(self, unit: OL490Unit, *, model=None, calibration=None, slit: int = 1, grey_bits: int = 6):
        self.unit = unit
        self.model = model if model is not None else ProgrammableLight()
        self.calibration = calibration
        p = self.model.params
        if COLUMNS % p.columns:
            raise ValueError(f"OL490 light: the model's {p.columns} columns do not divide the unit's {COLUMNS}")
        self.slit = int(check_number("slit", slit, low=1, high=len(SLITS), integer=True))
        self.grey_bits = int(check_number("grey_bits", grey_bits, low=GREY_BITS[0], high=GREY_BITS[-1], integer=True))
        unit.call("load_calibration", self.slit)
        unit.call("set_grey_depth", self.grey_bits)
        self.max_frame_rate_hz = float(unit.call("max_frame_rate", self.grey_bits))
        self._sequence: np.ndarray | None = None
        self._requested: np.ndarray | None = None
        self._restart()

    # ---- patterns -------------------------------------------------------------------------------------------------
    @property
    def params(self):
        return self.model.params

    @property
    def levels(self) -> int:
        """Grey levels above zero at the grey depth, ``2**bits - 1``."""
        return 2 ** self.grey_bits - 1

    def to_levels(self, patterns) -> np.ndarray:
        """(K, columns) mirror counts -> (K, 1024) grey levels the unit shows."""
        n = np.atleast_2d(self.model.check_pattern(patterns))
        levels = np.rint(n / self.model.params.rows * self.levels).astype(np.int64)
        return np.repeat(levels, COLUMNS // n.shape[1], axis=1)

    def _shown_counts(self, levels: np.ndarray) -> np.ndarray:
        """The mirror counts of the model nearest to what ``levels`` shows (one per model column)."""
        per = COLUMNS // self.model.params.columns
        return np.rint(levels[:, ::per] / self.levels * self.model.params.rows).astype(np.int32)

    # ---- LightSource -----------------------------------------------------------------------------------------------
    @property
    def wavelengths(self) -> np.ndarray:
        return self.calibration.wavelengths if self.calibration is not None else self.model.wavelengths

    @property
    def minimum_exposure_s(self) -> float:
        return 1.0 / self.max_frame_rate_hz

    @property
    def sequence(self) -> np.ndarray:
        """The loaded sequence as mirror counts of what the unit shows (quantized to the grey depth)."""
        if self._sequence is None:
            raise RuntimeError("OL490 light: no sequence loaded (or the last upload failed)")
        return self._sequence

    @property
    def requested(self) -> np.ndarray:
        if self._requested is None:
            raise RuntimeError("OL490 light: no sequence was ever loaded")
        return self._requested

    def load_sequence(self, patterns) -> None:
        """Load a (K, columns) sequence into the unit's memory; a failure leaves none marked as loaded."""
        levels = self.to_levels(patterns)
        self._sequence = None
        self._requested = np.atleast_2d(np.asarray(patterns))
        self.unit.call("load_sequence", levels)
        self._sequence = self._shown_counts(levels)
        self._index = 0

    def start(self) -> None:
        """Run the sequence stepped by the trigger input (the first edge shows pattern 0)."""
        self.sequence  # noqa: B018 - refuse to start without a sequence
        self._restart()
        self.unit.call("start_sequence", True)

    def stop(self) -> None:
        self.unit.call("stop_sequence")

    def close(self) -> None:
        self.unit.close()

    def check(self) -> None:
        """:class:`LightFault` if the sequence stopped or the unit stepped fewer times than the camera exposed."""
        who = self.unit.who
        if not self.unit.call("sequence_running"):
            raise LightFault(f"{who}: the sequence stopped (unit reset or stopped); frames from here on are not lit "
                             f"by the sequence")
        steps = int(self.unit.call("sequence_steps"))
        if steps < self._frame + 1:
            raise LightFault(f"{who} stepped {steps} times for {self._frame + 1} camera exposures: a trigger was "
                             f"missed, so exposures from here on are not lit by their pattern")

    def emitted_spectrum(self, index: int | None = None) -> np.ndarray:
        k = self._index if index is None else int(index)
        pattern = self.sequence[k]
        if self.calibration is not None:
            return self.calibration.emitted(pattern)
        return self.model.pattern_to_spectrum(pattern)

    def show(self, pattern) -> None:
        """Show one pattern steadily (the spectrometer loop)."""
        levels = self.to_levels(pattern)[:1]
        self._sequence = None
        self.unit.call("send_pattern", levels[0])
        self._sequence, self._index = self._shown_counts(levels), 0
