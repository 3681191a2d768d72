"""DLPC900 USB HID protocol: the command table, request framing, reply parsing (TI DLPU018, Section 1.2).

A message is a 4-byte header, a 2-byte USB command and the command's data (DLPU018 Section 1.2.1, Figure 1-4):

    flags | sequence | length LSB | length MSB | command LSB (CMD3) | command MSB (CMD2) | data ...

- **flags**: bit 7 = 1 read / 0 write, bit 6 = 1 the host wants a reply, bit 5 = error (set by the controller in a
  reply when the command was not found or failed), bits 2:0 destination (0 for the DLPC900).
- **sequence**: a rolling counter the controller echoes in its reply, so replies are matched to requests.
- **length**: number of payload bytes (command bytes plus data), little-endian; the header is not counted.
- multi-byte parameters are little-endian (LSB first), the command too (Table 1-5: command 0x1100 is sent 00 11).

HID limits a transfer to 64 bytes, so a longer message is cut into 64-byte reports and only the first carries the
header and command; every report is zero padded to 64 bytes. (The HID report ID 0x00 that the guide shows in front of
each transfer is consumed by the host's HID layer; over the interrupt endpoint a report is the 64 bytes after it.)
The controller's command buffer is 512 bytes, shared by requests and replies (Section 1.2.1): a message is at most
512 bytes, hence the 504-byte data blocks of Pattern BMP Load.

The commands are declared as data (:data:`COMMANDS`): TI's name, USB opcode, access and the byte layout of their
parameters, so framing and parsing are generic and each device method just names the command it sends.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from specgpu.hardware.errors import CommandRejected, DeviceTimeout, ProtocolError

__all__ = ["Command", "COMMANDS", "ERROR_CODES", "REPORT_SIZE", "MAX_MESSAGE", "FLAG_READ", "FLAG_REPLY",
           "FLAG_ERROR", "Reply", "encode_fields", "decode_fields", "build_message", "split_reports",
           "parse_reply", "Protocol"]

REPORT_SIZE = 64
HEADER_SIZE = 4
MAX_MESSAGE = 512

FLAG_READ = 0x80
FLAG_REPLY = 0x40
FLAG_ERROR = 0x20
DESTINATION_MASK = 0x07


@dataclass(frozen=True)
class Command:
    """One DLPC900 USB command.

    Attributes
    ----------
    name : str
        TI's name of the command (DLPU018).
    opcode : int
        USB command, CMD2 (high byte) and CMD3 (low byte), e.g. 0x1A34.
    access : str
        ``"r"``, ``"w"`` or ``"rw"``.
    layout : tuple of (str, int)
        Parameters in order: (field name, size in bytes); a negative size is a signed integer of ``-size`` bytes,
        size 0 is a trailing run of raw bytes. All integers are little-endian. Used for writes and for replies
        (read replies carry the same fields as the write, unless ``reply_layout`` says otherwise).
    reply_layout : tuple of (str, int) or None
        Layout of a read reply when it differs from ``layout``.
    section : str
        Where DLPU018 defines it.
    """

    name: str
    opcode: int
    access: str
    layout: tuple = ()
    reply_layout: tuple | None = None
    section: str = ""

    @property
    def reply_fields(self) -> tuple:
        return self.layout if self.reply_layout is None else self.reply_layout


_LUT_ENTRY = (("pattern_index", 2), ("exposure_us", 3), ("options", 1), ("dark_us", 3), ("trigger_out2", 1),
              ("image", 2))
_TRIGGER_OUT = (("invert", 1), ("rising_delay_us", -2), ("falling_delay_us", -2))

#: The commands this driver sends, by TI name. Section numbers refer to DLPU018 (rev. I/J).
COMMANDS: dict[str, Command] = {c.name: c for c in (
    Command("Read Error Code", 0x0100, "r", reply_layout=(("code", 1),), section="2.1.6"),
    Command("Read Error Description", 0x0101, "r", reply_layout=(("text", 0),), section="2.1.7"),
    Command("Power Mode", 0x0200, "rw", (("mode", 1),), section="2.3.1.1"),
    Command("Retrieve Firmware Version", 0x0205, "r",
            reply_layout=(("application", 4), ("api", 4), ("software_config", 4), ("sequencer_config", 4)),
            section="2.1.4"),
    Command("Curtain Color", 0x1100, "rw", (("red", 2), ("green", 2), ("blue", 2)), section="2.3.1.4"),
    Command("Hardware Status", 0x1A0A, "r", reply_layout=(("status", 1),), section="2.1.1"),
    Command("System Status", 0x1A0B, "r", reply_layout=(("status", 1),), section="2.1.2"),
    Command("Main Status", 0x1A0C, "r", reply_layout=(("status", 1),), section="2.1.3"),
    Command("Display Mode Selection", 0x1A1B, "rw", (("mode", 1),), section="2.4.1"),
    Command("Trigger Out 1", 0x1A1D, "rw", _TRIGGER_OUT, section="Trigger Out 1"),
    Command("Pattern Display Start/Stop", 0x1A24, "rw", (("action", 1),), section="Pattern Display Start/Stop"),
    Command("Initialize Pattern BMP Load", 0x1A2A, "w", (("image_index", 2), ("size", 4)),
            section="Initialize Pattern BMP Load (primary controller)"),
    Command("Pattern BMP Load", 0x1A2B, "w", (("length", 2), ("data", 0)),
            section="Pattern BMP Load (primary controller)"),
    Command("Initialize Pattern BMP Load Secondary", 0x1A2C, "w", (("image_index", 2), ("size", 4)),
            section="Initialize Pattern BMP Load (secondary controller)"),
    Command("Pattern BMP Load Secondary", 0x1A2D, "w", (("length", 2), ("data", 0)),
            section="Pattern BMP Load (secondary controller)"),
    Command("Pattern Display LUT Configuration", 0x1A31, "rw", (("entries", 2), ("repeat", 4)),
            section="Tables 2-135, 2-136"),
    Command("Pattern Display LUT Definition", 0x1A34, "w", _LUT_ENTRY, section="Pattern Display LUT Definition"),
    # byte 2 (bit 0) of Trigger In 1 is written at its reset value 0
    Command("Trigger In 1", 0x1A35, "rw", (("delay_us", 2), ("byte2", 1)), section="Trigger In 1"),
)}

_BY_OPCODE = {c.opcode: c for c in COMMANDS.values()}

#: Read Error Code (0x0100) values, DLPU018 Section 2.1.6.
ERROR_CODES = {
    0: "no error", 1: "batch file checksum error", 2: "device failure", 3: "invalid command number",
    4: "incompatible controller and DMD combination", 5: "command not allowed in current mode",
    6: "invalid command parameter", 7: "item referred by the parameter is not present",
    8: "out of resource (RAM or flash)", 9: "invalid BMP compression type", 10: "pattern bit number out of range",
    11: "pattern BMP not present in flash", 12: "pattern dark time is out of range",
    13: "signal delay parameter is out of range", 14: "pattern exposure time is out of range",
    15: "pattern number is out of range", 16: "invalid pattern definition", 17: "pattern image memory address is "
    "out of range", 255: "internal error",
}


def command(name_or_opcode) -> Command:
    """The :class:`Command` named (TI name) or with that opcode; ``ValueError`` listing the names otherwise."""
    cmd = COMMANDS.get(name_or_opcode) if isinstance(name_or_opcode, str) else _BY_OPCODE.get(name_or_opcode)
    if cmd is None:
        raise ValueError(f"unknown DLPC900 command {name_or_opcode!r}; known: {', '.join(COMMANDS)}")
    return cmd


def encode_fields(layout, values: dict) -> bytes:
    """Parameters ``values`` (field name -> int, or bytes for a raw field) packed by ``layout``."""
    missing = [n for n, _ in layout if n not in values]
    extra = sorted(set(values) - {n for n, _ in layout})
    if missing or extra:
        raise ValueError(f"fields {', '.join(n for n, _ in layout)} expected; missing {missing}, unexpected {extra}")
    out = bytearray()
    for name, size in layout:
        v = values[name]
        if size == 0:
            out += bytes(v)
            continue
        n, signed = abs(size), size < 0
        lo, hi = (-(1 << (8 * n - 1)), (1 << (8 * n - 1)) - 1) if signed else (0, (1 << (8 * n)) - 1)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")
        out += v.to_bytes(n, "little", signed=signed)
    return bytes(out)


def decode_fields(layout, data: bytes) -> dict:
    """Fields of ``layout`` read from ``data`` (a raw field takes the rest); ``ProtocolError`` if too short."""
    out, pos = {}, 0
    for name, size in layout:
        if size == 0:
            out[name] = bytes(data[pos:])
            pos = len(data)
            continue
        n = abs(size)
        if pos + n > len(data):
            raise ProtocolError(f"DLPC900 reply too short: {len(data)} bytes, field {name!r} needs {pos + n}")
        out[name] = int.from_bytes(data[pos:pos + n], "little", signed=size < 0)
        pos += n
    return out


def build_message(opcode: int, data: bytes = b"", *, read: bool = False, reply: bool = True, sequence: int = 0,
                  destination: int = 0) -> bytes:
    """Header, command and data of one request (before splitting into reports), Section 1.2.1."""
    if not 0 <= opcode <= 0xFFFF:
        raise ValueError(f"opcode must be a 16-bit command, got {opcode!r}")
    if not 0 <= sequence <= 0xFF:
        raise ValueError(f"sequence must be a byte, got {sequence!r}")
    length = 2 + len(data)
    if HEADER_SIZE + length > MAX_MESSAGE:
        raise ValueError(f"DLPC900 message of {HEADER_SIZE + length} bytes exceeds the {MAX_MESSAGE}-byte command "
                         "buffer")
    flags = (FLAG_READ if read else 0) | (FLAG_REPLY if reply or read else 0) | (destination & DESTINATION_MASK)
    return bytes((flags, sequence)) + length.to_bytes(2, "little") + opcode.to_bytes(2, "little") + bytes(data)


def split_reports(message: bytes) -> list[bytes]:
    """``message`` cut into 64-byte HID reports, the last zero padded (Section 1.2.1, Figure 1-5)."""
    reports = []
    for start in range(0, max(len(message), 1), REPORT_SIZE):
        chunk = message[start:start + REPORT_SIZE]
        reports.append(bytes(chunk) + bytes(REPORT_SIZE - len(chunk)))
    return reports


@dataclass(frozen=True)
class Reply:
    """A parsed reply: ``flags``, echoed ``sequence`` and ``data`` (``length`` bytes)."""

    flags: int
    sequence: int
    data: bytes

    @property
    def error(self) -> bool:
        return bool(self.flags & FLAG_ERROR)


def reply_length(first_report: bytes) -> int:
    """Total bytes (header plus data) of the reply whose first report is given."""
    if len(first_report) < HEADER_SIZE:
        raise ProtocolError(f"DLPC900 reply report of {len(first_report)} bytes is shorter than its 4-byte header")
    return HEADER_SIZE + int.from_bytes(first_report[2:4], "little")


def parse_reply(reports) -> Reply:
    """Reassemble a reply from its reports (Section 1.2.2, Table 1-6): flags, sequence, length, data."""
    reports = [bytes(r) for r in reports]
    if not reports:
        raise ProtocolError("DLPC900 reply is empty")
    total = reply_length(reports[0])
    blob = b"".join(reports)
    if len(blob) < total:
        raise ProtocolError(f"DLPC900 reply truncated: length field says {total - HEADER_SIZE} data bytes, "
                            f"got {len(blob) - HEADER_SIZE}")
    return Reply(blob[0], blob[1], blob[HEADER_SIZE:total])


class Protocol:
    """Requests and replies over a :class:`~specgpu.hardware.dlpc900.transport.Transport`.

    Parameters
    ----------
    transport
        Anything with ``write(report)`` (64 bytes) and ``read(timeout_ms)`` (one 64-byte report).
    reply_writes
        Ask for a reply to every write (flags bit 6) so a rejected write is reported at once; the guide's
        write example (Table 1-7) does not, which is faster for bulk image data.
    """

    def __init__(self, transport, *, reply_writes: bool = True):
        self.transport = transport
        self.reply_writes = reply_writes
        self._sequence = 0
        self._lock = threading.Lock()  # one transaction at a time: the controller has a single command buffer

    def _next_sequence(self) -> int:
        self._sequence = (self._sequence + 1) & 0xFF
        return self._sequence

    def transact(self, cmd: Command, data: bytes = b"", *, read: bool = False, reply: bool | None = None,
                 check: bool = True) -> Reply | None:
        """Send one command; return its reply (``None`` for a write without reply).

        With ``check``, a reply with the error flag raises :class:`CommandRejected` carrying the controller's
        error code and description, read back with Read Error Code (0x0100) and Read Error Description (0x0101).
        """
        want = read or (self.reply_writes if reply is None else reply)
        with self._lock:
            seq = self._next_sequence()
            for report in split_reports(build_message(cmd.opcode, data, read=read, reply=want, sequence=seq)):
                self.transport.write(report)
            if not want:
                return None
            rep = self._read_reply(seq, cmd)
        if rep.error and check:
            code, text = self.error_status()
            what = ERROR_CODES.get(code, "undefined error") if code >= 0 else "error status unreadable"
            detail = f": {text}" if text else ""
            raise CommandRejected(f"DLPC900 rejected {cmd.name} (0x{cmd.opcode:04X}): error {code} ({what}){detail}",
                                  code, text)
        return rep

    def _read_reply(self, seq: int, cmd: Command) -> Reply:
        # A reply left over from an interrupted transaction carries an older sequence byte: skip a few of them.
        for _ in range(4):
            first = bytes(self.transport.read())
            reports = [first]
            total = reply_length(first)
            while sum(len(r) for r in reports) < total:
                reports.append(bytes(self.transport.read()))
            rep = parse_reply(reports)
            if rep.sequence == seq:
                return rep
        raise ProtocolError(f"DLPC900 reply to {cmd.name} (0x{cmd.opcode:04X}) never came: sequence bytes "
                            f"do not match 0x{seq:02X}")

    def error_status(self) -> tuple[int, str]:
        """Read Error Code (0x0100) and Read Error Description (0x0101) of the last command: (-1, "") for a code and
        "" for a description that cannot be read (no reply in time, malformed reply), so the rejection itself is
        still the error reported."""
        try:
            code = self.read("Read Error Code", check=False)["code"]
        except (ProtocolError, CommandRejected, DeviceTimeout):
            return -1, ""
        try:
            raw = self.read("Read Error Description", check=False)["text"]
        except (ProtocolError, CommandRejected, DeviceTimeout):
            return code, ""
        return code, raw.split(b"\0", 1)[0].decode("ascii", "replace").strip()

    def write(self, name: str, *, reply: bool | None = None, **values) -> None:
        """Write command ``name`` (TI name) with its parameters as keyword arguments."""
        cmd = command(name)
        if "w" not in cmd.access:
            raise ValueError(f"DLPC900 command {cmd.name} (0x{cmd.opcode:04X}) cannot be written")
        self.transact(cmd, encode_fields(cmd.layout, values), reply=reply)

    def read(self, name: str, data: bytes = b"", *, check: bool = True) -> dict:
        """Read command ``name``; return its reply fields by name."""
        cmd = command(name)
        if "r" not in cmd.access:
            raise ValueError(f"DLPC900 command {cmd.name} (0x{cmd.opcode:04X}) cannot be read")
        rep = self.transact(cmd, data, read=True, check=check)
        return decode_fields(cmd.reply_fields, rep.data)
