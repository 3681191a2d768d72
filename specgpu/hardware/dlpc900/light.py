"""The DLPC900-based programmable light as a :class:`~specgpu.capture.driver.LightSource`.

``load_sequence`` turns the (K, C) mirror-count patterns into DMD bit-planes (:class:`DMDLayout`), packs them 24 to
an image and uploads them with one LUT entry per pattern (1 bit, wait for trigger, ``dark_s`` of dark time, cleared
after its exposure): the controller then shows pattern k on the k-th TRIG_IN_1 edge of a pass. The trigger itself is
hardware (the camera's strobe, or the controller is the master and triggers the camera through TRIG_OUT); this
object only keeps count of which pattern lit which exposure: exposure ``n`` of the stream (the camera's frame
counter, which also counts frames the host never received) was lit by pattern ``n mod K`` (:meth:`at_frame`).
:meth:`check` reads the controller's Main Status so a capture stops at the first sign that the sequencer is no
longer following, instead of labelling frames it did not light.

Timing in strobe-master mode: the camera's exposure-active rising edge triggers pattern n, which the controller
shows after its Trigger In 1 delay (105 us by default) for ``exposure_s``; so the exposure must exceed the switch
time (as the twin's minimum exposure says) and the frame period must exceed ``exposure_s`` plus that delay, or the
next trigger arrives while a pattern is still shown and is missed. Each entry clears the mirrors after its exposure
(clear-after-exposure, 0x1A34 byte 5 bit 0): otherwise the pattern stays up through the next trigger's delay and
lights the start of the next exposure.

Timing in hardware-trigger mode (controller master): the controller shows each pattern for ``exposure_s`` then
``dark_s`` dark and TRIG_OUT_1 is high while a pattern is shown; it falls only in a dark time, so the dark time must
be non-zero (and long enough for the camera's trigger input) or the camera sees one rising edge for the whole
sequence. The controller runs from Start on, watched or not: the camera must be armed before the light starts.

What the light emits is the model's (a calibration bundle's forward model, or the nominal
:class:`~specgpu.rig.light.ProgrammableLight`): a real light cannot measure itself.
"""

from __future__ import annotations

import numpy as np

from specgpu.capture.driver import LightSource
from specgpu.core.validate import check_number
from specgpu.hardware.dlpc900.device import DLPC900, LutEntry
from specgpu.hardware.dlpc900.images import BITS_PER_IMAGE, DMDLayout
from specgpu.hardware.errors import LightFault
from specgpu.hardware.stepping import TriggerStepped
from specgpu.rig.light import ProgrammableLight

__all__ = ["DLPC900Light", "DEFAULT_DARK_S"]

#: Default dark time after each pattern, s: TRIG_OUT_1 low long enough for a camera's trigger input (a few us) and
#: the controller's own clear of the mirrors.
DEFAULT_DARK_S = 100e-6


class DLPC900Light(TriggerStepped, LightSource):
    """A lamp -> grating -> DLPC900 DMD light source.

    Parameters
    ----------
    device
        The controller (:class:`DLPC900`); by default the first one on USB.
    layout
        Where patterns go on the DMD; by default from ``calibration`` or from ``model``'s columns and rows,
        centred on the device's DMD.
    model
        A :class:`~specgpu.rig.light.ProgrammableLight` for the wavelength grid and the emitted spectra
        (the paper's nominal light by default).
    calibration
        Optional :class:`~specgpu.calibration.bundle.CalibrationBundle`: its column map sets the pattern width and its
        forward model gives :meth:`emitted_spectrum`.
    exposure_s
        How long each pattern is shown after its trigger (LUT exposure), s; at least the DMD's minimum
        (105 us for 1-bit patterns).
    wait_for_trigger
        LUT entries wait for TRIG_IN_1 (camera master, the paper's arrangement). ``False``: the controller runs
        the sequence on its own clock and triggers the camera (TRIG_OUT_1).
    compression
        Image encoding for the upload: ``"erle"`` (default), ``"rle"`` or ``"none"``.
    dark_s
        Dark time after each pattern (LUT dark time), s; must be > 0 when the controller is the master
        (``wait_for_trigger=False``), as TRIG_OUT_1 falls only in it.
    """

    def __init__(self, device: DLPC900 | None = None, *, layout: DMDLayout | None = None, model=None,
                 calibration=None, exposure_s: float = 0.010, wait_for_trigger: bool = True,
                 compression: str = "erle", dark_s: float = DEFAULT_DARK_S):

        self.device = device if device is not None else DLPC900()
        self.model = model if model is not None else ProgrammableLight()
        self.calibration = calibration
        mp = self.model.params
        if calibration is not None and (calibration.columns, calibration.rows) != (mp.columns, mp.rows):
            raise ValueError(f"calibration has {calibration.columns} columns x {calibration.rows} rows, the light "
                             f"model {mp.columns} x {mp.rows}; pass the model of the calibrated rig")
        if layout is None:
            if calibration is not None:
                layout = DMDLayout.from_calibration(calibration, self.device.geometry)
            else:
                layout = DMDLayout(self.device.geometry, self.model.params.columns, self.model.params.rows)
        if layout.geometry != self.device.geometry:
            raise ValueError(f"layout is for a {layout.geometry.name}, the controller drives a "
                             f"{self.device.geometry.name}")
        self.layout = layout
        self.exposure_s = check_number("exposure_s", exposure_s, low=self.minimum_exposure_s, high=16.7)
        self.wait_for_trigger = bool(wait_for_trigger)
        self.dark_s = check_number("dark_s", dark_s, low=0, high=16.7)
        if not self.wait_for_trigger and round(self.dark_s * 1e6) < 1:
            raise ValueError(f"dark_s must be at least 1 us when the controller triggers the camera (TRIG_OUT_1 "
                             f"falls only in the dark time; with none the camera sees one trigger), got {dark_s!r}")
        self.compression = compression
        self._sequence: np.ndarray | None = None
        self._showing: np.ndarray | None = None  # the pattern show() put up, while it stays up
        self._requested: np.ndarray | None = None  # the last sequence asked for
        self._index = 0
        self.bytes_uploaded = 0

    # ---- what loop (b) and the planner read from a light --------------------------------------------------------
    @property
    def params(self):
        """The model's :class:`~specgpu.rig.light.LightParameters` (columns, rows, slit ...)."""
        return self.model.params

    @property
    def column_wavelengths(self) -> np.ndarray:
        cal = self.calibration
        return cal.column_wavelengths if cal is not None else self.model.column_wavelengths

    def check_pattern(self, pattern, name: str = "pattern") -> np.ndarray:
        try:
            return self.layout.check_patterns(pattern)[0]
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None

    # ---- LightSource -------------------------------------------------------------------------------------------
    @property
    def wavelengths(self) -> np.ndarray:
        return self.calibration.wavelengths if self.calibration is not None else self.model.wavelengths

    @property
    def minimum_exposure_s(self) -> float:
        return self.device.geometry.min_exposure_us * 1e-6

    @property
    def sequence(self) -> np.ndarray:
        """The loaded (K, C) sequence; ``RuntimeError`` if none is (or if the last upload failed)."""
        if self._sequence is None:
            raise RuntimeError("DLPC900 light: no sequence loaded (or the last upload failed)")
        return self._sequence

    @property
    def loaded(self) -> bool:
        return self._sequence is not None

    @property
    def requested(self) -> np.ndarray:
        """The last (K, C) sequence asked for by :meth:`load_sequence`, kept through :meth:`show` (which puts one
        pattern up on its own) and through a failed upload; ``RuntimeError`` if none ever was."""
        if self._requested is None:
            raise RuntimeError("DLPC900 light: no sequence was ever loaded")
        return self._requested

    def load_sequence(self, patterns) -> None:
        """Upload a (K, C) sequence (K <= 400) as 1-bit LUT entries; the light then waits to show pattern 0.

        A failure part-way (USB error, rejected command) leaves no sequence marked as loaded, so a capture cannot
        start with half a sequence in the controller.
        """
        p = self.layout.check_patterns(patterns)
        self._sequence = self._showing = None
        self._requested = p  # kept through a failed upload, for recover()
        images = self.layout.patterns_to_images(p)
        self.device.check_hardware()  # e.g. a LightCrafter 9000 whose secondary controller is not running
        exposure_us = int(round(self.exposure_s * 1e6))
        dark_us = int(round(self.dark_s * 1e6))
        entries = [LutEntry(k, exposure_us, k // BITS_PER_IMAGE, k % BITS_PER_IMAGE,
                            wait_for_trigger=self.wait_for_trigger, dark_us=dark_us, clear_after_exposure=True)
                   for k in range(p.shape[0])]
        self.bytes_uploaded = self.device.upload_sequence(images, entries, compression=self.compression)
        if not self.wait_for_trigger:
            # the controller is the master: TRIG_OUT_1 (non-inverted, no delay) triggers each camera exposure;
            # the sequence is stopped now, as Trigger Out 1 requires
            self.device.set_trigger_out1(invert=False, rising_delay_us=0, falling_delay_us=0)
        self._sequence = p
        self._index = 0

    def load_plan(self, plan) -> None:
        """Upload a :class:`~specgpu.planning.plans.Plan`'s sequence: its target spectra, already quantized by the
        planner to mirror counts through the calibration's column map, become DMD images, shown for the plan's exposure.

        The plan must have been made from this light's calibration (when the light has one) and for its rows.
        """
        if self.calibration is not None:
            plan.check_calibration(self.calibration)
        if int(plan.rows) != self.layout.rows:
            raise ValueError(f"plan is for {plan.rows} mirror rows, the light's layout has {self.layout.rows}")
        self.exposure_s = check_number("plan exposure_s", plan.exposure_s, low=self.minimum_exposure_s, high=16.7)
        self.load_sequence(plan.patterns)

    def close(self) -> None:
        """Release the controller's USB link."""
        self.device.close()

    def recover(self, attempts: int = 3, delay_s: float = 0.5) -> None:
        """After a USB fault: reopen the link and upload the last sequence asked for again (the controller may
        have been reset); :class:`DeviceNotFound` if it does not come back."""
        if self._requested is None:
            raise RuntimeError("DLPC900 light: nothing to recover, no sequence was ever loaded")
        self.device.reconnect(attempts, delay_s)
        self.load_sequence(self._requested)

    def start(self) -> None:
        """Pattern Display Start (0x1A24): the controller follows its triggers from pattern 0 (waiting for
        TRIG_IN_1), or runs the sequence on its own clock from now on (``wait_for_trigger=False``: arm the camera
        first)."""
        self.sequence  # noqa: B018 - refuse to start without a sequence
        self._index = 0
        self.device.start()

    def stop(self) -> None:
        """Pattern Display Stop (0x1A24)."""
        self._showing = None
        self.device.stop()

    def reset(self) -> None:
        self._index = 0

    def check(self) -> None:
        """Main Status (0x1A0C): :class:`LightFault` if the sequencer is not running (USB errors propagate)."""
        status = self.device.main_status()
        if not status.sequencer_running:
            raise LightFault("DLPC900 light: the pattern sequencer stopped (controller reset or stopped); "
                             "frames from here on are not lit by the sequence")

    def emitted_spectrum(self, index: int | None = None) -> np.ndarray:
        k = self._index if index is None else int(index)
        pattern = self.sequence[k]
        if self.calibration is not None:
            return self.calibration.emitted(pattern)
        return self.model.pattern_to_spectrum(pattern)

    def show(self, pattern) -> None:
        """Show one pattern continuously (for the spectrometer loop): a 1-entry LUT on the controller's own clock.
        The pattern shown last by ``show`` is not uploaded again."""
        p = self.layout.check_patterns(pattern)
        if self._showing is not None and np.array_equal(self._showing, p):
            return
        self._sequence = self._showing = None
        images = self.layout.patterns_to_images(p)
        # steady display: no dark time, never cleared
        entry = LutEntry(0, int(round(self.exposure_s * 1e6)), 0, 0, wait_for_trigger=False,
                         clear_after_exposure=False)
        self.bytes_uploaded = self.device.upload_sequence(images, [entry], compression=self.compression)
        self._sequence, self._index = p, 0
        self.device.start()
        self._showing = p
