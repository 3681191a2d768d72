"""A simulated LED controller board that follows the serial protocol exactly as the firmware does.

:class:`SimulatedLedBoard` is the firmware's state machine in Python: it answers protocol lines
(:meth:`~SimulatedLedBoard.handle`) and takes trigger edges (:meth:`~SimulatedLedBoard.trigger`, what the camera's
strobe does to the board's interrupt pin), so the driver runs in CI against the same protocol the board speaks.
It is reached either in process through :class:`SimulatedSerial` (a serial-port-like object) or, through pyserial
itself, over a TCP socket (:func:`serve`, whose ``socket://`` URL ``serial.serial_for_url`` opens).

Faults a test can inject: ``mute`` (the board never answers), ``corrupt_replies`` (the next N replies carry a
wrong checksum), ``drop_pulses`` (pulse numbers the board counts as missed, as an edge inside the hold-off is) and
``lose_pulses`` (pulse numbers that never reach the board: a trigger lost on the wiring), and any identity
(``protocol``, ``firmware``) to play a board flashed with another firmware.
"""

from __future__ import annotations

import socket
import threading

import numpy as np

from specgpu.hardware.led.protocol import ERRORS, IDENTITY, MAX_LINE, PROTOCOL_VERSION, crc8, frame

__all__ = ["SimulatedLedBoard", "SimulatedSerial", "serve", "FIRMWARE_VERSION"]

#: The firmware version in the repository (``tools/firmware/led_controller/led_controller.ino``).
FIRMWARE_VERSION = "1.0.0"


class SimulatedLedBoard:
    """The firmware's state machine (module docstring).

    Parameters
    ----------
    max_channels, pwm_bits, pwm_hz, max_steps
        What the board reports in its identity (a Teensy 4 with 13 PWM pins at 12 bit by default).
    protocol, firmware
        Protocol version and firmware version it reports.
    holdoff_us
        Initial hold-off: an edge sooner than this after the previous step is counted as missed.
    """

    def __init__(self, *, max_channels: int = 13, pwm_bits: int = 12, pwm_hz: float = 36621.0, max_steps: int = 256,
                 protocol: int = PROTOCOL_VERSION, firmware: str = FIRMWARE_VERSION, holdoff_us: int = 20):
        self.max_channels, self.pwm_bits, self.pwm_hz, self.max_steps = max_channels, pwm_bits, pwm_hz, max_steps
        self.protocol, self.firmware = protocol, firmware
        self.holdoff_us = holdoff_us
        self.channels = max_channels
        self.table: list = []  # per step: a tuple of duty counts, or None for the dark frame
        self.filled: list[bool] = []
        self.complete = False
        self.armed = False
        self.pulses = self.steps = self.missed = 0
        self.first_missed = -1
        self.step = -1
        self.clock_us = 0.0
        self._last_step_us = None
        self._edges = 0
        self.outputs = np.zeros(max_channels, np.int64)  # duty count on each channel's pin now
        self.mute = False
        self.corrupt_replies = 0
        self.drop_pulses: set[int] = set()
        self.lose_pulses: set[int] = set()
        self.received: list[str] = []  # command words, for checks
        self.lock = threading.Lock()

    # ---- the trigger input ---------------------------------------------------------------------------------------
    def trigger(self, at_us: float | None = None) -> int:
        """One rising edge sent to the trigger pin at ``at_us`` (default: 1 ms after the last); return the step shown
        after it (-1 when the board is not armed or the edge never reached it)."""
        with self.lock:
            self.clock_us = self.clock_us + 1000.0 if at_us is None else float(at_us)
            if not self.armed:
                return -1
            edge, self._edges = self._edges, self._edges + 1  # edges the camera sent since ARM
            if edge in self.lose_pulses:
                return -1
            n = self.pulses
            self.pulses += 1
            too_soon = (self._last_step_us is not None and self.clock_us - self._last_step_us < self.holdoff_us)
            if too_soon or n in self.drop_pulses:
                self.missed += 1
                if self.first_missed < 0:
                    self.first_missed = n
                return self.step
            self._last_step_us = self.clock_us
            self.step = self.steps % len(self.table)
            self.steps += 1
            self._show(self.step)
            return self.step

    def _show(self, k: int | None) -> None:
        self.outputs[:] = 0
        if k is not None and self.table[k] is not None:
            self.outputs[:self.channels] = self.table[k]

    def duty(self) -> np.ndarray:
        """Duty of each channel now, as a fraction of full scale, shape (channels,)."""
        return self.outputs[:self.channels] / float((1 << self.pwm_bits) - 1)

    # ---- the serial side ------------------------------------------------------------------------------------------
    def handle(self, line: bytes) -> bytes:
        """The reply line to one received line (``b""`` when muted)."""
        with self.lock:
            reply = self._reply(line)
        if self.mute:
            return b""
        if self.corrupt_replies > 0:
            self.corrupt_replies -= 1
            body, _, cc = reply.rstrip(b"\n").rpartition(b"*")
            reply = body + b"*%02X\n" % (int(cc, 16) ^ 0x5A)
        return reply

    def _reply(self, line: bytes) -> bytes:
        if len(line) > MAX_LINE:
            return self._err(6, "line too long")
        text = line.rstrip(b"\r\n")
        body, star, cc = text.rpartition(b"*")
        try:
            if not star or len(cc) != 2 or int(cc, 16) != crc8(body):
                return self._err(1, "checksum mismatch")
        except ValueError:
            return self._err(1, "checksum mismatch")
        fields = body.decode("ascii", "replace").split(" ")
        word, args = fields[0], fields[1:]
        self.received.append(word)
        try:
            values = [int(a) for a in args]
        except ValueError:
            return self._err(3, "arguments must be integers")
        handler = getattr(self, f"_cmd_{word.lower()}", None) if word.isalpha() and word.isupper() else None
        if handler is None:
            return self._err(2, f"unknown command {word[:16]}")
        return handler(values)

    @staticmethod
    def _err(code: int, text: str) -> bytes:
        return frame("ERR", code, text or ERRORS[code])

    def _count(self, values, n, name):
        return None if len(values) == n else self._err(3, f"{name} takes {n} argument{'s' * (n != 1)}")

    def _cmd_id(self, values):
        return self._count(values, 0, "ID") or frame("OK", IDENTITY, self.protocol, self.firmware, self.max_channels,
                                                     self.pwm_bits, int(round(self.pwm_hz)), self.max_steps)

    def _cmd_ch(self, values):
        if bad := self._count(values, 1, "CH"):
            return bad
        if self.armed:
            return self._err(4, "stop before changing the channel count")
        if not 1 <= values[0] <= self.max_channels:
            return self._err(3, f"channel count must be 1 to {self.max_channels}")
        self.channels, self.table, self.filled, self.complete = values[0], [], [], False
        return frame("OK", self.channels)

    def _cmd_seq(self, values):
        if bad := self._count(values, 1, "SEQ"):
            return bad
        if self.armed:
            return self._err(4, "stop before uploading")
        if not 1 <= values[0] <= self.max_steps:
            return self._err(3, f"step count must be 1 to {self.max_steps}")
        self.table, self.filled, self.complete = [None] * values[0], [False] * values[0], False
        return frame("OK", values[0])

    def _check_step(self, i):
        if self.armed:
            return self._err(4, "stop before uploading")
        if not self.table:
            return self._err(5, "send SEQ first")
        if not 0 <= i < len(self.table):
            return self._err(3, f"step must be 0 to {len(self.table) - 1}")
        return None

    def _cmd_step(self, values):
        if bad := self._count(values, 1 + self.channels, "STEP"):
            return bad
        if bad := self._check_step(values[0]):
            return bad
        top = (1 << self.pwm_bits) - 1
        if any(not 0 <= d <= top for d in values[1:]):
            return self._err(3, f"duty out of range 0 to {top}")
        self.table[values[0]], self.filled[values[0]] = tuple(values[1:]), True
        return frame("OK", values[0])

    def _cmd_dark(self, values):
        if bad := self._count(values, 1, "DARK") or self._check_step(values[0] if values else -1):
            return bad
        self.table[values[0]], self.filled[values[0]] = None, True
        return frame("OK", values[0])

    def _cmd_end(self, values):
        if bad := self._count(values, 0, "END"):
            return bad
        if not self.table:
            return self._err(5, "send SEQ first")
        missing = [i for i, f in enumerate(self.filled) if not f]
        if missing:
            return self._err(3, f"step {missing[0]} not uploaded")
        self.complete = True
        return frame("OK", len(self.table))

    def _cmd_hold(self, values):
        if bad := self._count(values, 1, "HOLD"):
            return bad
        if not 0 <= values[0] <= 1_000_000:
            return self._err(3, "hold-off must be 0 to 1000000 us")
        self.holdoff_us = values[0]
        return frame("OK", values[0])

    def _cmd_arm(self, values):
        if bad := self._count(values, 0, "ARM"):
            return bad
        if not self.complete:
            return self._err(5, "upload a sequence first")
        self.armed, self.pulses, self.steps, self.missed, self.first_missed = True, 0, 0, 0, -1
        self.step, self._last_step_us, self._edges = -1, None, 0
        self._show(None)
        return frame("OK", len(self.table))

    def _cmd_stat(self, values):
        return self._count(values, 0, "STAT") or frame("OK", int(self.armed), self.pulses, self.steps, self.missed,
                                                       self.first_missed, self.step)

    def _cmd_stop(self, values):
        if bad := self._count(values, 0, "STOP"):
            return bad
        self.armed = False
        self._show(None)
        return frame("OK", self.pulses, self.steps, self.missed)

    def _cmd_show(self, values):
        if bad := self._count(values, 1, "SHOW") or self._check_step(values[0] if values else -1):
            return bad
        if not self.complete:
            return self._err(5, "upload a sequence first")
        self.step = values[0]
        self._show(values[0])
        return frame("OK", values[0])


class SimulatedSerial:
    """A serial-port-like object (``write``, ``readline``, ``close``) in front of a :class:`SimulatedLedBoard`.

    ``readline`` returns ``b""`` when the board has not answered (as pyserial's does at its timeout).
    """

    def __init__(self, board: SimulatedLedBoard | None = None, port: str = "sim://led", timeout: float = 1.0):
        self.board = board if board is not None else SimulatedLedBoard()
        self.port, self.timeout = port, timeout
        self.is_open = True
        self._pending = bytearray()
        self._replies = bytearray()

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise OSError(f"{self.port} is closed")
        self._pending += data
        while b"\n" in self._pending:
            line, _, rest = bytes(self._pending).partition(b"\n")
            self._pending = bytearray(rest)
            self._replies += self.board.handle(line + b"\n")
        return len(data)

    def readline(self) -> bytes:
        if b"\n" not in self._replies:
            return b""
        line, _, rest = bytes(self._replies).partition(b"\n")
        self._replies = bytearray(rest)
        return line + b"\n"

    def reset_input_buffer(self) -> None:
        self._replies.clear()

    def close(self) -> None:
        self.is_open = False


def serve(board: SimulatedLedBoard, host: str = "127.0.0.1"):
    """Serve ``board`` on a local TCP port, one connection at a time, on a daemon thread.

    Returns
    -------
    url : str
        ``socket://host:port``, which ``serial.serial_for_url`` opens as a serial port.
    stop : callable
        Closes the listening socket.
    """
    listener = socket.create_server((host, 0))
    listener.settimeout(0.2)
    url = f"socket://{host}:{listener.getsockname()[1]}"
    done = threading.Event()

    def run():
        while not done.is_set():
            try:
                conn, _ = listener.accept()
            except (TimeoutError, OSError):
                continue
            with conn:
                conn.settimeout(0.2)
                buf = b""
                while not done.is_set():
                    try:
                        data = conn.recv(4096)
                    except TimeoutError:
                        continue
                    except OSError:
                        break
                    if not data:
                        break
                    buf += data
                    while b"\n" in buf:
                        line, _, buf = buf.partition(b"\n")
                        reply = board.handle(line + b"\n")
                        if reply:
                            conn.sendall(reply)

    thread = threading.Thread(target=run, name="specgpu-simulated-led", daemon=True)
    thread.start()

    def stop():
        done.set()
        listener.close()
        thread.join(2)

    return url, stop
