"""The DLPC900 controller (DLP LightCrafter 6500 / 9000) as a device: one method per TI command.

Each method's docstring names the command it sends (TI name and USB opcode, DLPU018). :meth:`DLPC900.upload_sequence`
is the pattern-on-the-fly recipe of DLPU018's example ("Image On-The-Fly Pattern Mode", steps 1-19): stop, select
pattern-on-the-fly mode, define every LUT entry, configure the LUT, load the images, then (separately) start.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from specgpu.hardware.dlpc900.images import BITS_PER_IMAGE, DMDGeometry, encode_image, geometry, split_controllers
from specgpu.hardware.dlpc900.protocol import Protocol
from specgpu.hardware.dlpc900.transport import Transport, UsbTransport
from specgpu.hardware.errors import HardwareError

__all__ = ["DLPC900", "LutEntry", "HardwareStatus", "MainStatus", "DISPLAY_MODES", "COLORS", "MAX_LUT_ENTRIES",
           "BMP_BLOCK", "MIN_TRIGGER_IN1_DELAY_US"]

#: Display Mode Selection (0x1A1B) values.
DISPLAY_MODES = {"video": 0, "pre-stored": 1, "video-pattern": 2, "on-the-fly": 3}
#: LUT entry colour (LED enables), byte 5 bits 6:4 of Pattern Display LUT Definition.
COLORS = {"none": 0, "red": 1, "green": 2, "yellow": 3, "blue": 4, "magenta": 5, "cyan": 6, "white": 7}
#: Pattern Display LUT Configuration: at most 400 entries (960 on the DLP5500), Table 2-136.
MAX_LUT_ENTRIES = 400
#: Data bytes per Pattern BMP Load command: 512-byte buffer less header (4), command (2) and length (2).
BMP_BLOCK = 504
#: Trigger In 1 (0x1A35): the shortest delay from TRIG_IN_1 to the pattern's display the controller accepts, us.
MIN_TRIGGER_IN1_DELAY_US = 104
_START_STOP = {"stop": 0, "pause": 1, "start": 2}


@dataclass(frozen=True)
class LutEntry:
    """One entry of the pattern display LUT (Pattern Display LUT Definition, 0x1A34).

    Attributes
    ----------
    index : int
        Position in the LUT, [0, 399].
    exposure_us : int
        Display time of the pattern, us (24 bits).
    image_index : int
        Which uploaded 24-bit image holds the pattern, [0, 255] (11 bits on the wire).
    bit_position : int
        Which bit-plane of that image, [0, 23].
    bit_depth : int
        1 to 8 (1 for the binary patterns of this light).
    color : str
        LED enables (:data:`COLORS`); ``"white"`` enables all outputs.
    wait_for_trigger : bool
        Wait for TRIG_IN before showing the pattern (the camera is the master).
    dark_us : int
        Dark time after the exposure, us (24 bits). TRIG_OUT_1 falls only in a dark time: with zero dark time it
        stays high from one pattern to the next, so a camera triggered by it sees one edge for the whole sequence.
    clear_after_exposure : bool
        Clear the DMD after the exposure (on by default, as in every public driver): otherwise the pattern stays on
        until the next one is shown and lights the start of the next exposure.
    trigger_out2 : bool
        Emit TRIG_OUT_2 for this pattern.
    """

    index: int
    exposure_us: int
    image_index: int = 0
    bit_position: int = 0
    bit_depth: int = 1
    color: str = "white"
    wait_for_trigger: bool = True
    dark_us: int = 0
    clear_after_exposure: bool = True
    trigger_out2: bool = True

    def fields(self) -> dict:
        """The command's fields (see ``COMMANDS["Pattern Display LUT Definition"].layout``)."""
        if not 0 <= self.index < MAX_LUT_ENTRIES:
            raise ValueError(f"LUT index must lie in [0, {MAX_LUT_ENTRIES - 1}], got {self.index}")
        if not 1 <= self.bit_depth <= 8:
            raise ValueError(f"bit_depth must lie in [1, 8], got {self.bit_depth}")
        if self.color not in COLORS:
            raise ValueError(f"unknown colour {self.color!r}; valid: {', '.join(COLORS)}")
        if not 0 <= self.image_index < 256 or not 0 <= self.bit_position < BITS_PER_IMAGE:
            raise ValueError(f"image index must lie in [0, 255] and bit position in [0, 23], got "
                             f"{self.image_index}, {self.bit_position}")
        options = (int(self.clear_after_exposure) | (self.bit_depth - 1) << 1 | COLORS[self.color] << 4
                   | int(self.wait_for_trigger) << 7)
        return {"pattern_index": self.index, "exposure_us": int(self.exposure_us), "options": options,
                "dark_us": int(self.dark_us), "trigger_out2": 0 if self.trigger_out2 else 1,
                "image": self.image_index | self.bit_position << 11}

    @classmethod
    def from_fields(cls, f: dict) -> LutEntry:
        o = f["options"]
        color = {v: k for k, v in COLORS.items()}[(o >> 4) & 7]
        return cls(f["pattern_index"], f["exposure_us"], f["image"] & 0x7FF, f["image"] >> 11, ((o >> 1) & 7) + 1,
                   color, bool(o >> 7), f["dark_us"], bool(o & 1), not f["trigger_out2"] & 1)


@dataclass(frozen=True)
class HardwareStatus:
    """Hardware Status (0x1A0A), DLPU018 Section 2.1.1."""

    raw: int

    @property
    def initialized(self) -> bool:
        return bool(self.raw & 0x01)

    @property
    def secondary_present(self) -> bool:
        """Bit 4: the secondary controller (of a two-controller DMD, LightCrafter 9000) is present and running."""
        return bool(self.raw & 0x10)

    @property
    def errors(self) -> list[str]:
        bits = {1: "incompatible controller or DMD", 2: "DMD reset controller error", 3: "forced swap error",
                6: "sequencer abort status error", 7: "sequencer error"}
        return [text for bit, text in bits.items() if self.raw >> bit & 1]


@dataclass(frozen=True)
class MainStatus:
    """Main Status (0x1A0C), DLPU018 Section 2.1.3."""

    raw: int

    @property
    def parked(self) -> bool:
        return bool(self.raw & 0x01)

    @property
    def sequencer_running(self) -> bool:
        return bool(self.raw & 0x02)

    @property
    def video_frozen(self) -> bool:
        return bool(self.raw & 0x04)


class DLPC900:
    """A DLPC900 controller behind a :class:`Transport`.

    Parameters
    ----------
    transport
        Default: a :class:`UsbTransport` to the first controller found (opened here).
    dmd
        DMD name or :class:`DMDGeometry` (``"lightcrafter-6500"`` or ``"lightcrafter-9000"``).
    reply_writes
        Ask for (and check) a reply to every write, see :class:`Protocol`.
    """

    def __init__(self, transport: Transport | None = None, *, dmd="lightcrafter-6500", reply_writes: bool = True):
        self.transport = transport if transport is not None else UsbTransport()
        if not self.transport.is_open:
            self.transport.open()
        self.geometry: DMDGeometry = geometry(dmd)
        self.protocol = Protocol(self.transport, reply_writes=reply_writes)

    def close(self) -> None:
        self.transport.close()

    def reconnect(self, attempts: int = 3, delay_s: float = 0.5) -> None:
        """Reopen the USB link after a disconnect (e.g. the controller was reset); its state must be sent again."""
        self.transport.reconnect(attempts, delay_s)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---- status ------------------------------------------------------------------------------------------------
    def hardware_status(self) -> HardwareStatus:
        """Read Hardware Status (0x1A0A)."""
        return HardwareStatus(self.protocol.read("Hardware Status")["status"])

    def check_hardware(self) -> HardwareStatus:
        """Read Hardware Status (0x1A0A); :class:`HardwareError` (one line) if the controller did not initialize,
        reports an error, or (two-controller DMD: LightCrafter 9000) its secondary controller is not present."""
        status = self.hardware_status()
        problems = list(status.errors)
        if not status.initialized:
            problems.insert(0, "not initialized")
        if self.geometry.controllers == 2 and not status.secondary_present:
            problems.append(f"secondary controller not present (a {self.geometry.name} needs both controllers; "
                            "power-cycle the board)")
        if problems:
            raise HardwareError(f"DLPC900 hardware status 0x{status.raw:02X}: {'; '.join(problems)}")
        return status

    def system_status(self) -> int:
        """Read System Status (0x1A0B); bit 0 = internal memory test passed."""
        return self.protocol.read("System Status")["status"]

    def main_status(self) -> MainStatus:
        """Read Main Status (0x1A0C)."""
        return MainStatus(self.protocol.read("Main Status")["status"])

    def firmware_version(self) -> dict:
        """Retrieve Firmware Version (0x0205): application, API, software and sequencer config revisions."""
        return self.protocol.read("Retrieve Firmware Version")

    def error_status(self) -> tuple[int, str]:
        """Read Error Code (0x0100) then Read Error Description (0x0101) of the last command."""
        return self.protocol.error_status()

    # ---- modes -------------------------------------------------------------------------------------------------
    def set_power_mode(self, mode: str) -> None:
        """Power Mode (0x0200): ``"normal"``, ``"standby"`` or ``"reset"`` (software reset).

        A reset controller reboots and answers nothing, so the reset is sent without asking for a reply; its state
        (mode, LUT, images) is gone and the USB link comes back only after :meth:`reconnect`."""
        modes = {"normal": 0, "standby": 1, "reset": 2}
        if mode not in modes:
            raise ValueError(f"unknown power mode {mode!r}; valid: {', '.join(modes)}")
        self.protocol.write("Power Mode", reply=False if mode == "reset" else None, mode=modes[mode])

    def set_display_mode(self, mode: str) -> None:
        """Display Mode Selection (0x1A1B): ``"video"``, ``"pre-stored"``, ``"video-pattern"``, ``"on-the-fly"``."""
        if mode not in DISPLAY_MODES:
            raise ValueError(f"unknown display mode {mode!r}; valid: {', '.join(DISPLAY_MODES)}")
        self.protocol.write("Display Mode Selection", mode=DISPLAY_MODES[mode])

    def display_mode(self) -> str:
        """Read Display Mode Selection (0x1A1B)."""
        value = self.protocol.read("Display Mode Selection")["mode"]
        return {v: k for k, v in DISPLAY_MODES.items()}.get(value, f"unknown ({value})")

    def start(self) -> None:
        """Pattern Display Start/Stop (0x1A24) = 2: start the pattern sequence."""
        self.protocol.write("Pattern Display Start/Stop", action=_START_STOP["start"])

    def pause(self) -> None:
        """Pattern Display Start/Stop (0x1A24) = 1: pause."""
        self.protocol.write("Pattern Display Start/Stop", action=_START_STOP["pause"])

    def stop(self) -> None:
        """Pattern Display Start/Stop (0x1A24) = 0: stop."""
        self.protocol.write("Pattern Display Start/Stop", action=_START_STOP["stop"])

    # ---- LUT ---------------------------------------------------------------------------------------------------
    def define_pattern(self, entry: LutEntry) -> None:
        """Pattern Display LUT Definition (0x1A34): one LUT entry."""
        self.protocol.write("Pattern Display LUT Definition", **entry.fields())

    def configure_lut(self, entries: int, repeat: int = 0) -> None:
        """Pattern Display LUT Configuration (0x1A31): ``entries`` LUT entries, ``repeat`` patterns to display
        (0: repeat the sequence forever)."""
        if not 1 <= entries <= MAX_LUT_ENTRIES:
            raise ValueError(f"LUT entries must lie in [1, {MAX_LUT_ENTRIES}], got {entries}")
        self.protocol.write("Pattern Display LUT Configuration", entries=int(entries), repeat=int(repeat))

    def lut_configuration(self) -> tuple[int, int]:
        """Read Pattern Display LUT Configuration (0x1A31): (entries, repeat)."""
        f = self.protocol.read("Pattern Display LUT Configuration")
        return f["entries"] & 0x7FF, f["repeat"]

    # ---- images ------------------------------------------------------------------------------------------------
    def load_image(self, index: int, blob: bytes, *, controller: int = 0) -> None:
        """Initialize Pattern BMP Load (0x1A2A; 0x1A2C for the secondary controller) with the image's size, then
        Pattern BMP Load (0x1A2B; 0x1A2D) in blocks of 504 bytes. ``blob`` is header + encoded data."""
        suffix = "" if controller == 0 else " Secondary"
        if controller not in (0, 1):
            raise ValueError(f"controller must be 0 (primary) or 1 (secondary), got {controller}")
        self.protocol.write("Initialize Pattern BMP Load" + suffix, image_index=int(index), size=len(blob))
        for start in range(0, len(blob), BMP_BLOCK):
            block = blob[start:start + BMP_BLOCK]
            self.protocol.write("Pattern BMP Load" + suffix, length=len(block), data=block)

    # ---- triggers ----------------------------------------------------------------------------------------------
    def set_trigger_out1(self, *, invert: bool = False, rising_delay_us: int = 0, falling_delay_us: int = 0) -> None:
        """Trigger Out 1 (0x1A1D): TRIG_OUT_1 polarity and edge delays (us, -20 to 20000) from the pattern's display.

        (Trigger Out 2, 0x1A1E, is not sent: its parameter layout could not be confirmed from DLPU018; TRIG_OUT_2 is
        still enabled per pattern by the LUT entry.)
        """
        for name, d in (("rising_delay_us", rising_delay_us), ("falling_delay_us", falling_delay_us)):
            if not -20 <= d <= 20000:
                raise ValueError(f"{name} must lie in [-20, 20000] us, got {d}")
        self.protocol.write("Trigger Out 1", invert=int(bool(invert)), rising_delay_us=int(rising_delay_us),
                            falling_delay_us=int(falling_delay_us))

    def set_trigger_in1(self, delay_us: int = 105) -> None:
        """Trigger In 1 (0x1A35): delay (us) from the TRIG_IN_1 active edge to the pattern's display (bytes 1:0;
        byte 2 at its reset value 0). DLPU018 requires at least 104 us (the DMD's block-load time; reset value 105)."""
        if not MIN_TRIGGER_IN1_DELAY_US <= delay_us <= 0xFFFF:
            raise ValueError(f"trigger in 1 delay must lie in [{MIN_TRIGGER_IN1_DELAY_US}, 65535] us (DLPU018: at "
                             f"least {MIN_TRIGGER_IN1_DELAY_US}), got {delay_us}")
        self.protocol.write("Trigger In 1", delay_us=int(delay_us), byte2=0)

    # ---- the whole upload --------------------------------------------------------------------------------------
    def upload_sequence(self, images: np.ndarray, entries, *, compression: str = "erle",
                        repeat: int = 0) -> int:
        """Put a pattern-on-the-fly sequence in the controller (it is left stopped; :meth:`start` runs it).

        Sends Pattern Display Start/Stop (0x1A24, stop), Display Mode Selection (0x1A1B, on-the-fly), one Pattern
        Display LUT Definition (0x1A34) per entry, Pattern Display LUT Configuration (0x1A31), then each image with
        Initialize Pattern BMP Load and Pattern BMP Load (0x1A2A/0x1A2B; 0x1A2C/0x1A2D for the secondary
        controller), last image first (the order of DLPU018's on-the-fly example and of the public
        drivers; the controller stacks images as they arrive). Returns the bytes of image data sent.
        """
        imgs = np.asarray(images)
        if imgs.ndim != 3 or imgs.shape[1:] != (self.geometry.height, self.geometry.width):
            raise ValueError(f"images must be (N, {self.geometry.height}, {self.geometry.width}), got {imgs.shape}")
        entries = list(entries)
        if not 1 <= len(entries) <= MAX_LUT_ENTRIES:
            raise ValueError(f"a sequence has 1 to {MAX_LUT_ENTRIES} LUT entries, got {len(entries)}")
        self.stop()
        self.set_display_mode("on-the-fly")
        for e in entries:
            self.define_pattern(e)
        self.configure_lut(len(entries), repeat)
        sent = 0
        for i in range(imgs.shape[0] - 1, -1, -1):
            for c, part in enumerate(split_controllers(imgs[i], self.geometry.controllers)):
                blob = encode_image(part, compression)
                self.load_image(i, blob, controller=c)
                sent += len(blob)
        return sent
