"""The host side of the LED controller's serial protocol: one :class:`LedController` per board.

The port is opened with pyserial's ``serial_for_url``, so a device path (``/dev/ttyACM0``, ``COM3``) and pyserial's
URLs (``socket://host:port``, ``loop://``) are all ports; an already open serial-port-like object can be passed
instead (tests, :class:`~specgpu.hardware.led.simulated.SimulatedSerial`). pyserial is imported only when a port is
opened by name.

Every error is one line naming the port: a board that does not answer (:class:`DeviceTimeout`), a port that cannot
be opened (:class:`DeviceNotFound`), a reply with a bad checksum or out of protocol (:class:`ProtocolError`), a
refused command (:class:`CommandRejected`), a board that speaks another protocol version or is not a specgpu LED
controller at all (:class:`HardwareError`).
"""

from __future__ import annotations

import numpy as np

from specgpu.core.validate import check_number
from specgpu.hardware.errors import (
    BackendMissing,
    DeviceDisconnected,
    DeviceNotFound,
    DeviceTimeout,
    HardwareError,
    ProtocolError,
)
from specgpu.hardware.led.protocol import (
    PROTOCOL_VERSION,
    Identity,
    Status,
    frame,
    parse_identity,
    parse_reply,
    parse_status,
    unframe,
)

__all__ = ["LedController", "open_serial", "FIRMWARE_PATH"]

#: Where the firmware that speaks :data:`PROTOCOL_VERSION` lives in the repository.
FIRMWARE_PATH = "tools/firmware/led_controller/led_controller.ino"


def open_serial(port: str, *, baudrate: int = 115200, timeout_s: float = 1.0):
    """Open ``port`` (a device path or a pyserial URL) with pyserial.

    Raises
    ------
    BackendMissing
        pyserial is not installed.
    DeviceNotFound
        The port cannot be opened (no such device, in use, no permission).
    """
    try:
        import serial
    except ImportError:
        raise BackendMissing("the LED controller needs pyserial: pip install pyserial") from None
    try:
        return serial.serial_for_url(port, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s)
    except (serial.SerialException, OSError, ValueError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DeviceNotFound(f"LED controller port {port} cannot be opened ({why}): is the board connected?") from None


class LedController:
    """An LED controller board on a serial port, speaking protocol :data:`PROTOCOL_VERSION`.

    Opening identifies the board (``ID``) and refuses one that does not answer, is not a specgpu LED controller or
    speaks another protocol version.

    Parameters
    ----------
    port : str or serial-port-like
        Device path or pyserial URL, or an open object with ``write``, ``readline`` and ``close``.
    timeout_s : float
        Longest wait for a reply line.
    baudrate : int
        Line rate (USB CDC boards ignore it).
    """

    def __init__(self, port, *, timeout_s: float = 1.0, baudrate: int = 115200):
        self.timeout_s = check_number("timeout_s", timeout_s, low=0, low_open=True, high=60)
        if isinstance(port, str):
            self.port = port
            self._serial = open_serial(port, baudrate=baudrate, timeout_s=self.timeout_s)
        else:
            self.port = str(getattr(port, "port", None) or getattr(port, "name", None) or "serial")
            self._serial = port
        self.who = f"LED controller on {self.port}"
        self.channels = 0
        try:
            self.identity = self.identify()
            self.channels = self.identity.max_channels  # the board's default until set_channels
        except BaseException:
            self.close()
            raise

    # ---- one exchange -------------------------------------------------------------------------------------------
    def command(self, word: str, *args) -> list[str]:
        """Send one command line and return the values of its ``OK`` reply (errors: module docstring)."""
        if self._serial is None:
            raise DeviceDisconnected(f"{self.who} is closed")
        flush = getattr(self._serial, "reset_input_buffer", None)
        try:
            if flush is not None:
                flush()  # a late reply to an earlier, timed-out command must not pass for this one's
            self._serial.write(frame(word, *args))
            line = self._serial.readline()
        except OSError as exc:  # pyserial's SerialException is an OSError
            raise DeviceDisconnected(f"{self.who} failed during {word} ({exc})") from None
        if not line:
            raise DeviceTimeout(f"{self.who} did not answer {word} within {self.timeout_s:g} s: is the board "
                                f"connected, powered and running the specgpu LED firmware?")
        try:
            fields = unframe(line)
        except ProtocolError as exc:
            raise ProtocolError(f"{self.who}: reply to {word}: {exc}") from None
        return parse_reply(fields, self.who, word)

    # ---- the protocol's commands --------------------------------------------------------------------------------
    def identify(self) -> Identity:
        """``ID``: what the board is; :class:`HardwareError` for another protocol version."""
        values = self.command("ID")
        try:
            ident = parse_identity(values)
        except ProtocolError as exc:
            raise ProtocolError(f"{self.who}: {exc}; is it running {FIRMWARE_PATH}?") from None
        if ident.protocol != PROTOCOL_VERSION:
            raise HardwareError(f"{self.who} runs firmware {ident.firmware} speaking protocol {ident.protocol}; this "
                                f"driver speaks protocol {PROTOCOL_VERSION}: flash {FIRMWARE_PATH}")
        return ident

    def set_channels(self, n: int) -> None:
        """``CH n``: drive the first ``n`` channels (clears the sequence)."""
        check_number("channels", n, low=1, high=self.identity.max_channels, integer=True)
        self.command("CH", int(n))
        self.channels = int(n)

    def set_holdoff(self, holdoff_us: int) -> None:
        """``HOLD us``: an edge sooner than this after the previous step is not a step but a missed trigger."""
        self.command("HOLD", int(check_number("holdoff_us", holdoff_us, low=0, high=1_000_000, integer=True)))

    def upload(self, duties: np.ndarray) -> None:
        """Upload a (K, channels) sequence of duty counts; a row of zeros becomes the all-off dark frame (``DARK``)."""
        d = np.asarray(duties)
        if d.ndim != 2 or d.shape[0] > self.identity.max_steps:
            raise ValueError(f"{self.who}: sequence must be (K <= {self.identity.max_steps}, channels), got "
                             f"{d.shape}")
        self.command("SEQ", d.shape[0])
        for i, row in enumerate(d):
            if not row.any():
                self.command("DARK", i)
            else:
                self.command("STEP", i, *(int(v) for v in row))
        self.command("END")

    def arm(self) -> None:
        """``ARM``: outputs off, counters cleared; each trigger edge from now on shows the next step."""
        self.command("ARM")

    def status(self) -> Status:
        """``STAT``: armed, pulses, steps, missed edges, the first missed pulse, the step shown."""
        values = self.command("STAT")
        try:
            return parse_status(values)
        except ProtocolError as exc:
            raise ProtocolError(f"{self.who}: {exc}") from None

    def stop(self) -> tuple[int, int, int]:
        """``STOP``: disarm, outputs off; returns (pulses, steps, missed)."""
        values = self.command("STOP")
        try:
            return tuple(int(v) for v in values)
        except ValueError:
            raise ProtocolError(f"{self.who}: STOP reply with a non-integer field: {' '.join(values)!r}") from None

    def show(self, step: int) -> None:
        """``SHOW i``: show uploaded step ``i`` steadily (disarmed)."""
        self.command("SHOW", int(step))

    def close(self) -> None:
        """Release the port."""
        if self._serial is not None:
            try:
                self._serial.close()
            finally:
                self._serial = None
