"""A simulated DLPC900 behind the :class:`Transport` interface: reports in, reports out, a controller model between.

It reassembles requests from their reports (as the controller does, by the header's length), executes the commands
of :data:`~specgpu.hardware.dlpc900.protocol.COMMANDS` on a model of the controller's state (display mode, LUT,
uploaded images decoded back from the wire format, sequencer) and answers like the controller: same sequence byte,
error flag and error code on a rejected command. A trigger input advances the LUT the way TRIG_IN_1 does, and the
mirror image on display can be read back, so a camera model can be lit by what was really uploaded.

Faults for drills: ``absent`` (open fails as with no device), ``fail_after`` (after that many reports the transport
times out or disconnects), ``stop_after_triggers`` (the sequencer stops, as after a controller reset).
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from specgpu.hardware.dlpc900.images import BITS_PER_IMAGE, decode_image, geometry, join_controllers
from specgpu.hardware.dlpc900.protocol import (COMMANDS, FLAG_ERROR, FLAG_READ, FLAG_REPLY, HEADER_SIZE,
                                               REPORT_SIZE, decode_fields, encode_fields, reply_length,
                                               split_reports)
from specgpu.hardware.dlpc900.transport import Transport
from specgpu.hardware.errors import DeviceDisconnected, DeviceNotFound, DeviceTimeout

__all__ = ["SimulatedDLPC900"]

_BY_OPCODE = {c.opcode: c for c in COMMANDS.values()}


class SimulatedDLPC900(Transport):
    """A DLPC900 simulated at the level of its USB reports.

    Parameters
    ----------
    dmd
        DMD name or geometry.
    absent
        Behave as if no device were connected.
    fail_after
        After this many reports written, every transfer fails with ``fail_mode``.
    fail_mode
        ``"disconnect"`` or ``"timeout"``.
    """

    def __init__(self, dmd="lightcrafter-6500", *, absent: bool = False, fail_after: int | None = None,
                 fail_mode: str = "disconnect"):
        if fail_mode not in ("disconnect", "timeout"):
            raise ValueError(f"fail_mode must be 'disconnect' or 'timeout', got {fail_mode!r}")
        self.geometry = geometry(dmd)
        self.absent, self.fail_after, self.fail_mode = absent, fail_after, fail_mode
        self.stop_after_triggers: int | None = None
        self.log: list[tuple[str, bytes]] = []  # ("out" | "in", report): every report, for inspection
        self.commands: list[tuple[str, dict | bytes]] = []  # (TI name, fields) of every executed command
        self._open = False
        self._pending = bytearray()
        self._replies: deque[bytes] = deque()
        self._lock = threading.Lock()
        self.reset()

    # ---- controller state --------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Power-on state."""
        self.mode = 0
        self.lut: dict[int, dict] = {}
        self.lut_entries, self.lut_repeat = 0, 0
        self.images: dict[tuple[int, int], np.ndarray] = {}  # (image index, controller) -> (H, W/n) uint32
        self._loading: dict[int, tuple[int, int, bytearray]] = {}
        self.running = False
        self.error_code, self.error_text = 0, ""
        self.position = -1  # LUT entry on display, -1 before the first trigger
        self.triggers = 0
        self.trigger_out1 = (0, 0, 0)
        self.trigger_in1_delay = 105
        self.curtain = (0, 0, 0)

    # ---- transport ---------------------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        if self.absent:
            raise DeviceNotFound("DLPC900 (USB 0451:c900) not found: is the controller connected, powered and "
                                 "readable by this user (udev rule)?")
        self._open = True

    def close(self) -> None:
        self._open = False

    def _check_link(self) -> None:
        if not self._open:
            raise DeviceDisconnected("DLPC900 (USB 0451:c900) is not open")
        if self.fail_after is not None and sum(1 for d, _ in self.log if d == "out") >= self.fail_after:
            if self.fail_mode == "timeout":
                raise DeviceTimeout("DLPC900 (USB 0451:c900): transfer timed out after 1000 ms")
            self._open = False
            raise DeviceDisconnected("DLPC900 (USB 0451:c900) disconnected during transfer")

    def write(self, report: bytes) -> None:
        with self._lock:
            self._check_link()
            if len(report) != REPORT_SIZE:
                raise ValueError(f"a HID report is {REPORT_SIZE} bytes, got {len(report)}")
            self.log.append(("out", bytes(report)))
            self._pending += report
            total = reply_length(self._pending)  # same header layout for requests
            if len(self._pending) >= total:
                message = bytes(self._pending[:total])
                self._pending.clear()  # the rest of the last report is padding
                self._execute(message)

    def read(self, timeout_ms: int | None = None) -> bytes:
        with self._lock:
            self._check_link()
            if not self._replies:
                raise DeviceTimeout("DLPC900 (USB 0451:c900): read timed out (no reply pending)")
            report = self._replies.popleft()
            self.log.append(("in", report))
            return report

    # ---- command execution -------------------------------------------------------------------------------------
    def _execute(self, message: bytes) -> None:
        flags, seq = message[0], message[1]
        opcode = int.from_bytes(message[4:6], "little")
        data = message[HEADER_SIZE + 2:]
        read = bool(flags & FLAG_READ)
        cmd = _BY_OPCODE.get(opcode)
        payload, ok = b"", True
        if cmd is None or ("r" if read else "w") not in cmd.access:
            ok, self.error_code, self.error_text = False, 3, "Invalid command number"
        else:
            try:
                if read:
                    payload = self._read(cmd.name, data)
                    self.commands.append((cmd.name + " (read)", {}))
                else:
                    fields = decode_fields(cmd.layout, data)
                    self.commands.append((cmd.name, fields))
                    code = self._write(cmd.name, fields)
                    if code:
                        ok, self.error_code = False, code
                        self.error_text = f"{cmd.name} failed"
            except Exception as exc:  # a malformed parameter block is an invalid parameter, as on the controller
                ok, self.error_code, self.error_text = False, 6, f"Invalid command parameter ({exc})"
        if ok and cmd is not None and cmd.name not in ("Read Error Code", "Read Error Description"):
            self.error_code, self.error_text = 0, ""
        if read or flags & FLAG_REPLY:
            reply_flags = (flags & (FLAG_READ | FLAG_REPLY)) | (0 if ok else FLAG_ERROR)
            body = bytes((reply_flags, seq)) + len(payload).to_bytes(2, "little") + payload
            self._replies.extend(split_reports(body))

    def _read(self, name: str, data: bytes) -> bytes:
        if name == "Read Error Code":
            return bytes((self.error_code,))
        if name == "Read Error Description":
            return self.error_text.encode("ascii")[:127].ljust(128, b"\0")
        if name == "Hardware Status":
            return b"\x01"  # initialized, no errors
        if name == "System Status":
            return b"\x01"
        if name == "Main Status":
            return bytes((0x02 if self.running else 0x00,))
        if name == "Retrieve Firmware Version":
            return (0x06000000).to_bytes(4, "little") * 4
        if name == "Display Mode Selection":
            return bytes((self.mode,))
        if name == "Pattern Display LUT Configuration":
            return encode_fields(COMMANDS[name].layout, {"entries": self.lut_entries, "repeat": self.lut_repeat})
        if name == "Pattern Display Start/Stop":
            return bytes((2 if self.running else 0,))
        if name == "Curtain Color":
            r, g, b = self.curtain
            return encode_fields(COMMANDS[name].layout, {"red": r, "green": g, "blue": b})
        if name == "Trigger Out 1":
            inv, rise, fall = self.trigger_out1
            return encode_fields(COMMANDS[name].layout, {"invert": inv, "rising_delay_us": rise,
                                                         "falling_delay_us": fall})
        if name == "Trigger In 1":
            return self.trigger_in1_delay.to_bytes(2, "little") + b"\x00"
        if name == "Power Mode":
            return b"\x00"
        raise ValueError(f"no read model for {name}")

    def _write(self, name: str, f: dict) -> int:
        """Execute a write; return the controller's error code (0: success)."""
        g = self.geometry
        if name == "Display Mode Selection":
            if self.running:
                return 5
            if f["mode"] > 3:
                return 6
            self.mode = f["mode"]
        elif name == "Pattern Display Start/Stop":
            if f["action"] == 2:
                if self.mode not in (1, 3) or self.lut_entries == 0:
                    return 5
                for i in range(self.lut_entries):
                    e = self.lut.get(i)
                    if e is None:
                        return 16
                    img = e["image"] & 0x7FF
                    if any((img, c) not in self.images for c in range(g.controllers)):
                        return 7
                self.running, self.position, self.triggers = True, -1, 0
                if not self.lut[0]["options"] >> 7:  # entry 0 runs on the controller's clock: shown at once
                    self.position = 0
            elif f["action"] in (0, 1):
                self.running = False
            else:
                return 6
        elif name == "Pattern Display LUT Definition":
            if self.running:
                return 5
            if f["pattern_index"] >= 400:
                return 15
            if f["exposure_us"] < g.min_exposure_us:
                return 14
            if (f["image"] >> 11) >= BITS_PER_IMAGE:
                return 10
            self.lut[f["pattern_index"]] = f
        elif name == "Pattern Display LUT Configuration":
            if self.running:
                return 5
            if not 1 <= f["entries"] <= 400:
                return 6
            self.lut_entries, self.lut_repeat = f["entries"], f["repeat"]
        elif name in ("Initialize Pattern BMP Load", "Initialize Pattern BMP Load Secondary"):
            if self.running or self.mode != 3:
                return 5
            self._loading[int(name.endswith("Secondary"))] = (f["image_index"], f["size"], bytearray())
        elif name in ("Pattern BMP Load", "Pattern BMP Load Secondary"):
            c = int(name.endswith("Secondary"))
            if c not in self._loading:
                return 5
            index, size, buf = self._loading[c]
            if f["length"] != len(f["data"]) and len(f["data"]) < f["length"]:
                return 6
            buf += f["data"][:f["length"]]
            if len(buf) > size:
                return 6
            if len(buf) == size:
                del self._loading[c]
                try:
                    img = decode_image(bytes(buf))
                except ValueError:
                    return 9
                if img.shape != (g.height, g.width // g.controllers):
                    return 6
                self.images[(index, c)] = img
        elif name == "Trigger Out 1":
            self.trigger_out1 = (f["invert"], f["rising_delay_us"], f["falling_delay_us"])
        elif name == "Trigger In 1":
            self.trigger_in1_delay = f["delay_us"]
        elif name == "Curtain Color":
            self.curtain = (f["red"], f["green"], f["blue"])
        elif name == "Power Mode":
            if f["mode"] == 2:
                self.reset()
        return 0

    # ---- the optical side --------------------------------------------------------------------------------------
    def trigger_in(self) -> int:
        """A TRIG_IN_1 edge: the next LUT entry is shown. Returns its index, -1 if the sequencer is stopped."""
        with self._lock:
            if not self.running:
                return -1
            if self.stop_after_triggers is not None and self.triggers >= self.stop_after_triggers:
                self.running = False  # as after a controller reset: the DMD goes dark
                return -1
            self.triggers += 1
            self.position = (self.position + 1) % self.lut_entries
            return self.position

    def image(self, index: int) -> np.ndarray:
        """The full-DMD 24-bit image ``index`` as uploaded (controllers joined)."""
        return join_controllers(self.images[(index, c)] for c in range(self.geometry.controllers))

    def entry_mask(self, position: int) -> np.ndarray:
        """(H, W) bool mirrors of LUT entry ``position``."""
        e = self.lut[position]
        return ((self.image(e["image"] & 0x7FF) >> np.uint32(e["image"] >> 11)) & 1).astype(bool)

    def displayed_mask(self) -> np.ndarray:
        """The mirrors on display now (all off when stopped or before the first trigger)."""
        with self._lock:
            pos, running = self.position, self.running
        if not running or pos < 0:
            return np.zeros((self.geometry.height, self.geometry.width), bool)
        return self.entry_mask(pos)
