r"""The LED controller's serial protocol (version 1): line framing, the checksum, commands and replies.

Every exchange is one ASCII line from the host and one line back (``docs/guide/led-controller.md`` is the
specification; ``tools/firmware/led_controller/led_controller.ino`` the board's side)::

    host:  WORD [ARG ...]*CC\\n          e.g.  "STEP 3 4095 0 120*5A\\n"
    board: OK [VALUE ...]*CC\\n                 "OK 3*B1\\n"
           ERR CODE TEXT*CC\\n                  "ERR 3 duty out of range*1F\\n"

``CC`` is the CRC-8 (polynomial 0x07, initial value 0, no reflection: CRC-8/SMBUS) of every byte before the ``*``,
as two upper-case hex digits. Fields are separated by one space; a line is at most :data:`MAX_LINE` bytes with its
newline. This module is pure: it builds and checks lines, the transport is the caller's.
"""

from __future__ import annotations

from dataclasses import dataclass

from specgpu.hardware.errors import CommandRejected, ProtocolError

__all__ = ["PROTOCOL_VERSION", "IDENTITY", "MAX_LINE", "ERRORS", "crc8", "frame", "unframe", "Identity", "Status",
           "parse_reply", "parse_identity", "parse_status"]

#: The protocol version this driver and the firmware in the repository speak.
PROTOCOL_VERSION = 1
#: First field of the ``ID`` reply: what the board is.
IDENTITY = "SPECGPU-LED"
#: Longest line, newline included (a ``STEP`` of 13 channels at 16 bit needs 13 * 6 + 20 bytes).
MAX_LINE = 128

#: Error codes of an ``ERR`` reply -> their meaning (the board's text names the detail).
ERRORS = {
    1: "checksum mismatch",
    2: "unknown command",
    3: "bad argument",
    4: "busy: the sequence is armed",
    5: "no sequence loaded",
    6: "line too long",
}


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS (polynomial 0x07, initial 0, no reflection, no final XOR) of ``data``.

    >>> f"{crc8(b'123456789'):02X}"
    'F4'
    """
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def frame(*fields) -> bytes:
    """One line on the wire: the fields joined by spaces, ``*``, the CRC-8 in hex and a newline."""
    body = " ".join(str(f) for f in fields).encode("ascii")
    line = body + b"*%02X\n" % crc8(body)
    if len(line) > MAX_LINE:
        raise ValueError(f"LED controller line of {len(line)} bytes exceeds the protocol's {MAX_LINE}")
    return line


def unframe(line: bytes) -> list[str]:
    """The fields of one received line, its checksum checked.

    Raises
    ------
    ProtocolError
        An empty or unterminated line, no ``*CC`` trailer, or a checksum that does not match.
    """
    if not line.endswith(b"\n"):
        raise ProtocolError(f"unterminated line {line[:40]!r}")
    text = line.rstrip(b"\r\n")
    body, star, cc = text.rpartition(b"*")
    if not star or len(cc) != 2:
        raise ProtocolError(f"line without a checksum: {text[:40]!r}")
    try:
        want = int(cc, 16)
    except ValueError:
        raise ProtocolError(f"line with a malformed checksum: {text[:40]!r}") from None
    got = crc8(body)
    if got != want:
        raise ProtocolError(f"checksum mismatch (line says {want:02X}, content gives {got:02X}): {text[:40]!r}")
    try:
        return body.decode("ascii").split(" ")
    except UnicodeDecodeError:
        raise ProtocolError(f"line that is not ASCII: {text[:40]!r}") from None


@dataclass(frozen=True)
class Identity:
    """The ``ID`` reply: ``OK SPECGPU-LED PROTOCOL FIRMWARE MAX_CHANNELS PWM_BITS PWM_HZ MAX_STEPS``."""

    protocol: int
    firmware: str
    max_channels: int
    pwm_bits: int
    pwm_hz: float
    max_steps: int

    @property
    def full_scale(self) -> int:
        """The duty count of a channel fully on."""
        return (1 << self.pwm_bits) - 1


@dataclass(frozen=True)
class Status:
    """The ``STAT`` reply: ``OK ARMED PULSES STEPS MISSED FIRST_MISSED STEP``.

    Attributes
    ----------
    armed : bool
        The trigger input advances the sequence.
    pulses : int
        Trigger edges seen since ``ARM`` (the camera's exposures, as the board counts them).
    steps : int
        Edges that advanced the sequence.
    missed : int
        Edges that came within the hold-off after the previous step and did not advance it.
    first_missed : int
        Pulse number (0 for the first pulse after ``ARM``) of the first missed edge; -1 if none.
    step : int
        Step of the sequence shown now (-1: nothing yet, the outputs are off until the first edge).
    """

    armed: bool
    pulses: int
    steps: int
    missed: int
    first_missed: int
    step: int


def _ints(fields, n, what):
    if len(fields) != n:
        raise ProtocolError(f"{what} reply has {len(fields)} fields, expected {n}: {' '.join(fields)!r}")
    try:
        return [int(f) for f in fields]
    except ValueError:
        raise ProtocolError(f"{what} reply with a non-integer field: {' '.join(fields)!r}") from None


def parse_reply(fields: list[str], who: str, command: str) -> list[str]:
    """The values of an ``OK`` reply to ``command``.

    Raises
    ------
    CommandRejected
        An ``ERR CODE TEXT`` reply: one line naming ``who``, the command, the code and the board's text.
    ProtocolError
        Anything else.
    """
    if fields and fields[0] == "OK":
        return fields[1:]
    if len(fields) >= 2 and fields[0] == "ERR" and fields[1].isdigit():
        code, text = int(fields[1]), " ".join(fields[2:]) or ERRORS.get(int(fields[1]), "")
        raise CommandRejected(f"{who} refused {command}: error {code} ({text})", code, text)
    raise ProtocolError(f"{who}: reply to {command} is neither OK nor ERR: {' '.join(fields)[:60]!r}")


def parse_identity(values: list[str]) -> Identity:
    """:class:`Identity` from the values of an ``ID`` reply (after ``OK``)."""
    if len(values) != 7 or values[0] != IDENTITY:
        raise ProtocolError(f"ID reply does not identify a specgpu LED controller: {' '.join(values)[:60]!r}")
    protocol, max_channels, bits, hz, steps = _ints([values[1], values[3], values[4], values[5], values[6]], 5, "ID")
    return Identity(protocol, values[2], max_channels, bits, float(hz), steps)


def parse_status(values: list[str]) -> Status:
    """:class:`Status` from the values of a ``STAT`` reply (after ``OK``)."""
    armed, pulses, steps, missed, first, step = _ints(values, 6, "STAT")
    return Status(bool(armed), pulses, steps, missed, first, step)
