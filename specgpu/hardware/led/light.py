"""An LED array on a :class:`~specgpu.hardware.led.controller.LedController` as a
:class:`~specgpu.capture.driver.LightSource`.

A pattern is one duty per channel, a fraction of full scale in [0, 1]; a sequence is (K, channels). It is quantized
to the board's PWM counts and uploaded, a row of zeros as the board's all-off dark frame. The camera is the master:
its exposure-active output drives the board's trigger input, and the board shows step ``p mod K`` from the rising
edge of pulse ``p`` (the first pulse after ``ARM`` is 0). Exposure ``n`` of the stream is therefore lit by pattern
``n mod K`` (:meth:`LedLight.at_frame`) as long as every edge advanced the board by one step.

:meth:`LedLight.check` (called by the camera before it hands over each frame) reads the board's counters and
refuses a frame the board may not have lit with its labelled pattern, so the sequence holding it is left
incomplete and nothing is mislabelled:

- an edge the board saw but did not step on (it came within the hold-off after the previous step) is counted as
  missed with its pulse number: exposures from that pulse on are refused, those before it are kept;
- an edge that never reached the board (lost on the wiring) shows as fewer pulses than the camera's exposures:
  found exactly when the host keeps up with the camera (the frame checked is the last exposure), otherwise as soon
  as the lost edges outnumber the exposures still in flight.
"""

from __future__ import annotations

import numpy as np

from specgpu.capture.driver import LightSource
from specgpu.hardware.errors import HardwareError, LightFault
from specgpu.hardware.led.controller import LedController
from specgpu.hardware.stepping import TriggerStepped

__all__ = ["LedLight", "PWM_PERIODS_PER_EXPOSURE"]

#: An exposure spans at least this many PWM periods, so the light it integrates is within 1 % of the duty.
PWM_PERIODS_PER_EXPOSURE = 100


class LedLight(TriggerStepped, LightSource):
    """An LED array driven by PWM from a controller board, stepped by the camera's trigger.

    Parameters
    ----------
    controller : LedController
        The board (opened and identified).
    channels : int, optional
        LED channels used (default: all the board has).
    wavelengths : array, optional
        Wavelength grid (nm) of ``spectra``.
    spectra : array, optional
        (channels, B) spectral irradiance (W m^-2 nm^-1) of each channel at full duty; without it the light's
        emitted spectra are unknown (:meth:`emitted_spectrum` says so).
    holdoff_us : int, optional
        Shortest interval between two steps the board accepts; an edge sooner is a missed trigger (default: the
        board's).
    """

    def __init__(self, controller: LedController, *, channels: int | None = None, wavelengths=None, spectra=None,
                 holdoff_us: int | None = None):
        self.controller = controller
        ident = controller.identity
        n = ident.max_channels if channels is None else int(channels)
        controller.set_channels(n)  # always: the board keeps the count an earlier session set
        self.channels = n
        if (spectra is None) != (wavelengths is None):
            raise ValueError("LED light: give both wavelengths and spectra, or neither")
        self._wavelengths = self._spectra = None
        if spectra is not None:
            self._wavelengths = np.asarray(wavelengths, np.float64)
            self._spectra = np.asarray(spectra, np.float64)
            if self._spectra.shape != (n, self._wavelengths.size):
                raise ValueError(f"LED light: spectra must be (channels, wavelengths) = ({n}, "
                                 f"{self._wavelengths.size}), got {self._spectra.shape}")
        if holdoff_us is not None:
            controller.set_holdoff(holdoff_us)
        self._sequence: np.ndarray | None = None
        self._requested: np.ndarray | None = None
        self._restart()

    # ---- patterns -------------------------------------------------------------------------------------------------
    def check_patterns(self, patterns) -> np.ndarray:
        """(K, channels) duty fractions in [0, 1], checked; ``ValueError`` naming what is wrong."""
        p = np.atleast_2d(np.asarray(patterns, np.float64))
        if p.ndim != 2 or p.shape[1] != self.channels or p.shape[0] < 1:
            raise ValueError(f"LED light: patterns must be (K, {self.channels}) duty fractions, got {p.shape}")
        if p.shape[0] > self.controller.identity.max_steps:
            raise ValueError(f"LED light: {p.shape[0]} patterns exceed the board's "
                             f"{self.controller.identity.max_steps} steps")
        if not np.isfinite(p).all() or p.min() < 0 or p.max() > 1:
            raise ValueError("LED light: duties must be finite fractions in [0, 1]")
        return p

    def _counts(self, p: np.ndarray) -> np.ndarray:
        return np.rint(p * self.controller.identity.full_scale).astype(np.int64)

    # ---- LightSource -----------------------------------------------------------------------------------------------
    @property
    def wavelengths(self) -> np.ndarray:
        if self._wavelengths is None:
            raise HardwareError("LED light: no channel spectra given (hardware.light_spectra), so its wavelengths and "
                                "emitted spectra are unknown")
        return self._wavelengths

    @property
    def minimum_exposure_s(self) -> float:
        return PWM_PERIODS_PER_EXPOSURE / self.controller.identity.pwm_hz

    @property
    def sequence(self) -> np.ndarray:
        """The loaded (K, channels) duties as the board shows them (quantized)."""
        if self._sequence is None:
            raise RuntimeError("LED light: no sequence loaded (or the last upload failed)")
        return self._sequence

    @property
    def requested(self) -> np.ndarray:
        """The last sequence asked for, kept through :meth:`show` and a failed upload."""
        if self._requested is None:
            raise RuntimeError("LED light: no sequence was ever loaded")
        return self._requested

    def load_sequence(self, patterns) -> None:
        """Upload a (K, channels) sequence of duty fractions; rows of zeros are the board's dark frame. A failed
        upload leaves no sequence marked as loaded."""
        p = self.check_patterns(patterns)
        self._sequence = None
        self._requested = p
        counts = self._counts(p)
        self.controller.upload(counts)
        self._sequence = counts / float(self.controller.identity.full_scale)
        self._index = 0

    def start(self) -> None:
        """Arm the board: outputs off until the first trigger edge, which shows pattern 0."""
        self.sequence  # noqa: B018 - refuse to start without a sequence
        self._restart()
        self.controller.arm()

    def stop(self) -> None:
        """Disarm the board (outputs off); its last counters stay in :attr:`counts`."""
        self.counts = self.controller.stop()

    def close(self) -> None:
        self.controller.close()

    def check(self) -> None:
        """:class:`LightFault` if the board may not have lit the exposure last asked of :meth:`at_frame` with its
        pattern (module docstring); serial errors propagate."""
        s = self.controller.status()
        who, n = self.controller.who, self._frame
        if not s.armed:
            raise LightFault(f"{who} is no longer armed (reset or stopped): frames from here on are not lit by the "
                             f"sequence")
        if s.missed and 0 <= s.first_missed <= n:
            raise LightFault(f"{who} missed trigger pulse {s.first_missed} ({s.missed} of {s.pulses} pulses came "
                             f"within its hold-off): exposures from {s.first_missed} on are not lit by their pattern, "
                             f"so the sequence holding it is left out")
        if s.pulses < n + 1:
            raise LightFault(f"{who} saw {s.pulses} trigger pulses for {n + 1} camera exposures: a trigger was lost "
                             f"on the wiring, so exposures from here on are not lit by their pattern")

    def emitted_spectrum(self, index: int | None = None) -> np.ndarray:
        k = self._index if index is None else int(index)
        duty = self.sequence[k]
        return duty @ self._channel_spectra()

    def _channel_spectra(self) -> np.ndarray:
        self.wavelengths  # noqa: B018 - the one error when none were given
        return self._spectra

    def show(self, pattern) -> None:
        """Show one pattern steadily (the spectrometer loop): a one-step sequence, shown without triggers."""
        p = self.check_patterns(pattern)
        self._sequence = None
        counts = self._counts(p[:1])
        self.controller.upload(counts)
        self.controller.show(0)
        self._sequence, self._index = counts / float(self.controller.identity.full_scale), 0
