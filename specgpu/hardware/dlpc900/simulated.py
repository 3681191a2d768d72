"""A simulated DLPC900 behind the :class:`Transport` interface: reports in, reports out, a controller model between.

It reassembles requests from their reports (as the controller does, by the header's length), executes the commands
of :data:`~specgpu.hardware.dlpc900.protocol.COMMANDS` on a model of the controller's state (display mode, LUT,
uploaded images decoded back from the wire format, sequencer) and answers like the controller: same sequence byte,
error flag and error code on a rejected command. A trigger input advances the LUT the way TRIG_IN_1 does, and the
mirror image on display can be read back, so a camera model can be lit by what was really uploaded.

Timing follows the controller where a capture depends on it (DLPU018, Pattern Display LUT Definition, Trigger Out 1):

- the model has a clock (``clock_us``): each report moved over USB costs ``report_us``, and a camera model spends
  its own time with :meth:`elapse`;
- entries that wait for TRIG_IN_1 advance on :meth:`trigger_in` edges only; TRIG_IN_1 edges are ignored by entries
  that run on the controller's own clock and by a stopped sequencer (an edge before Start is lost);
- entries that do not wait run on the controller's clock from the Start command on, each for its exposure then its
  dark time, whether or not anyone watches (:meth:`next_trigger_out1`); TRIG_OUT_1 rises at the start of a pattern
  only when it fell before, i.e. after a pattern with non-zero dark time (or at Start): with zero dark time it stays
  high over the whole sequence and a camera triggered by it sees one edge;
- after a pattern's exposure the mirrors are cleared only if its LUT entry has clear-after-exposure set; otherwise
  the pattern stays on until the next one is shown, and a camera exposure that opens at the trigger sees it during
  the Trigger In 1 delay (:meth:`exposure_light`);
- Power Mode "reset" reboots the controller: it sends no reply; Trigger In 1 delays under 104 us are refused
  (error 13); Hardware Status reports the secondary controller of a two-controller DMD (LightCrafter 9000) present
  unless ``secondary_present`` is false.

Faults for drills: ``absent`` (open fails as with no device), ``fail_after`` (after that many reports the transport
times out or disconnects), ``stop_after_triggers`` (the sequencer stops, as after a controller reset),
``no_reply_to`` (TI names of commands the controller leaves unanswered, so their read times out).
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from specgpu.hardware.dlpc900.images import BITS_PER_IMAGE, decode_image, geometry, join_controllers
from specgpu.hardware.dlpc900.protocol import (
    COMMANDS,
    FLAG_ERROR,
    FLAG_READ,
    FLAG_REPLY,
    HEADER_SIZE,
    REPORT_SIZE,
    decode_fields,
    encode_fields,
    reply_length,
    split_reports,
)
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
    report_us
        Simulated time one USB report transfer takes, us.
    secondary_present
        Whether the secondary controller of a two-controller DMD answers (Hardware Status bit 4).
    """

    def __init__(self, dmd="lightcrafter-6500", *, absent: bool = False, fail_after: int | None = None,
                 fail_mode: str = "disconnect", report_us: float = 125.0, secondary_present: bool = True):
        if fail_mode not in ("disconnect", "timeout"):
            raise ValueError(f"fail_mode must be 'disconnect' or 'timeout', got {fail_mode!r}")
        self.geometry = geometry(dmd)
        self.absent, self.fail_after, self.fail_mode = absent, fail_after, fail_mode
        self.report_us, self.secondary_present = float(report_us), bool(secondary_present)
        self.clock_us = 0.0
        self.stop_after_triggers: int | None = None
        self.no_reply_to: set[str] = set()
        self.reports_out = 0
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
        self.previous = -1  # the entry shown before it (its mirrors stay up unless it clears after exposure)
        self.triggers = 0
        self.started_us: float | None = None  # clock at the last Start command
        self._free_run = False  # the sequence runs on the controller's own clock
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
        if self.fail_after is not None and self.reports_out >= self.fail_after:
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
            self.reports_out += 1
            self.clock_us += self.report_us
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
            self.clock_us += self.report_us
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
        rebooting = ok and cmd is not None and cmd.name == "Power Mode" and not read and data[:1] == b"\x02"
        if cmd is not None and cmd.name in self.no_reply_to or rebooting:
            return  # the controller leaves it unanswered (a reset controller is rebooting)
        if read or flags & FLAG_REPLY:
            reply_flags = (flags & (FLAG_READ | FLAG_REPLY)) | (0 if ok else FLAG_ERROR)
            body = bytes((reply_flags, seq)) + len(payload).to_bytes(2, "little") + payload
            self._replies.extend(split_reports(body))

    def _read(self, name: str, data: bytes) -> bytes:
        if name == "Read Error Code":
            return bytes((self.error_code,))
        if name == "Read Error Description":
            return self.error_text.encode("ascii")[:127].ljust(128, b"\0")
        if name == "Hardware Status":  # initialized, no errors; bit 4: secondary controller present
            return bytes((0x01 | (0x10 if self.geometry.controllers == 2 and self.secondary_present else 0),))
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
                self.running, self.position, self.previous, self.triggers = True, -1, -1, 0
                self.started_us = self.clock_us
                self._free_run = not any(self.lut[i]["options"] >> 7 for i in range(self.lut_entries))
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
            if f["delay_us"] < 104:
                return 13  # signal delay parameter is out of range
            self.trigger_in1_delay = f["delay_us"]
        elif name == "Curtain Color":
            self.curtain = (f["red"], f["green"], f["blue"])
        elif name == "Power Mode":
            if f["mode"] == 2:
                self.reset()
        return 0

    # ---- the optical side --------------------------------------------------------------------------------------
    def elapse(self, us: float) -> None:
        """Let ``us`` of simulated time pass (a camera exposing, arming, waiting)."""
        with self._lock:
            self.clock_us += float(us)

    def _waits(self, position: int) -> bool:
        return bool(self.lut[position]["options"] >> 7)

    def trigger_in(self, at_us: float | None = None) -> int:
        """A TRIG_IN_1 edge (at clock ``at_us``, default now): the next LUT entry is shown if it waits for the
        trigger. Returns the entry on display, -1 if the sequencer was stopped at the edge (the edge is lost)."""
        with self._lock:
            if at_us is not None:
                self.clock_us = max(self.clock_us, float(at_us))
            t = self.clock_us if at_us is None else float(at_us)
            if not self.running or self.started_us is None or t < self.started_us:
                return -1
            if self._free_run:
                return self._free_position(t)  # entries on the controller's clock ignore TRIG_IN_1
            nxt = (self.position + 1) % self.lut_entries
            if not self._waits(nxt):
                return self.position
            if self.stop_after_triggers is not None and self.triggers >= self.stop_after_triggers:
                self.running = False  # as after a controller reset: the DMD goes dark
                return -1
            self.triggers += 1
            self.previous, self.position = self.position, nxt
            return self.position

    # controller-clocked sequences (no entry waits for a trigger)
    def _cycle(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        exp = np.array([self.lut[i]["exposure_us"] for i in range(self.lut_entries)], np.float64)
        dark = np.array([self.lut[i]["dark_us"] for i in range(self.lut_entries)], np.float64)
        return np.concatenate(([0.0], np.cumsum(exp + dark)))[:-1], exp, dark

    def _free_position(self, t: float) -> int:
        starts, exp, dark = self._cycle()
        period = float(exp.sum() + dark.sum())
        rel = (t - self.started_us) % period
        return int(np.searchsorted(starts, rel, side="right") - 1)

    def next_trigger_out1(self, after_us: float) -> tuple[float, int] | None:
        """(clock, LUT entry) of the first TRIG_OUT_1 rising edge at or after ``after_us`` of a sequence running on
        the controller's clock; ``None`` if there is none (stopped, trigger-driven, or zero dark time everywhere
        and the single edge at Start already past). The edge opens the pattern's exposure."""
        with self._lock:
            if not self.running or not self._free_run or self.started_us is None:
                return None
            starts, exp, dark = self._cycle()
            period = float(exp.sum() + dark.sum())
            t0 = self.started_us
            if after_us <= t0:
                return t0, 0
            rises = np.flatnonzero(np.roll(dark, 1) > 0)  # entry j rises if entry j-1 went dark
            if rises.size == 0:
                return None
            cycle, rel = divmod(after_us - t0, period)
            later = rises[starts[rises] >= rel]
            if later.size:
                j = int(later[0])
            else:
                cycle, j = cycle + 1, int(rises[0])
            return t0 + cycle * period + float(starts[j]), j

    def image(self, index: int) -> np.ndarray:
        """The full-DMD 24-bit image ``index`` as uploaded (controllers joined)."""
        return join_controllers(self.images[(index, c)] for c in range(self.geometry.controllers))

    def entry_mask(self, position: int) -> np.ndarray:
        """(H, W) bool mirrors of LUT entry ``position``."""
        e = self.lut[position]
        return ((self.image(e["image"] & 0x7FF) >> np.uint32(e["image"] >> 11)) & 1).astype(bool)

    def displayed_mask(self) -> np.ndarray:
        """The mirrors on display now (all off when stopped or before the first trigger; on the controller's
        clock, off in a pattern's dark time when it clears after its exposure)."""
        with self._lock:
            pos, running, free, t = self.position, self.running, self._free_run, self.clock_us
            if running and free:
                pos = self._free_position(t)
                starts, exp, dark = self._cycle()
                period = float(exp.sum() + dark.sum())
                in_dark = (t - self.started_us) % period - starts[pos] >= exp[pos]
                if in_dark and self.lut[pos]["options"] & 1:
                    pos = -1
        if not running or pos < 0:
            return np.zeros((self.geometry.height, self.geometry.width), bool)
        return self.entry_mask(pos)

    def exposure_light(self, exposure_us: float) -> np.ndarray:
        """(H, W) light a camera exposure of ``exposure_us`` opened at the last TRIG_IN_1 edge integrates, in units
        of one full exposure of a mirror: the entry on display (1) plus, during the Trigger In 1 delay, the entry
        before it if that one did not clear after its exposure (delay / exposure)."""
        with self._lock:
            pos, prev, running = self.position, self.previous, self.running
        light = self.displayed_mask().astype(np.float64)
        if running and pos >= 0 and prev >= 0 and not self.lut[prev]["options"] & 1:
            light += self.entry_mask(prev) * (min(self.trigger_in1_delay, exposure_us) / float(exposure_us))
        return light
