"""DLPC900 protocol and device layer against a Mock(spec=Transport): byte-exact requests, parsed replies.

Every expected report is written out by hand from TI's DLPC900 Programmer's Guide (DLPU018, rev. I/J); the comment
above each names the section or table. Reports are the 64 bytes that follow the HID report ID (the ID byte 0x00
the guide shows first is consumed by the HID layer, Section 1.2.1), zero padded.
"""

from __future__ import annotations

from unittest.mock import Mock

import numpy as np
import pytest

from specgpu.hardware.dlpc900 import DLPC900, LutEntry, Protocol, Transport
from specgpu.hardware.dlpc900.protocol import (
    COMMANDS,
    build_message,
    decode_fields,
    encode_fields,
    parse_reply,
    split_reports,
)
from specgpu.hardware.errors import CommandRejected, ProtocolError


def report(*values) -> bytes:
    """One 64-byte report from hand-written byte values (ints or bytes), zero padded."""
    out = bytearray()
    for v in values:
        out += bytes(v) if isinstance(v, (bytes, bytearray)) else bytes((v,))
    assert len(out) <= 64
    return bytes(out) + bytes(64 - len(out))


def ack(seq: int) -> bytes:
    # Reply to a write that asked for one: flags echo the reply bit (0x40), no data (Section 1.2.2).
    return report(0x40, seq, 0x00, 0x00)


def make(replies=(), *, first_seq=1):
    """A DLPC900 on a Mock transport fed ``replies``; the first request uses sequence byte ``first_seq``."""
    transport = Mock(spec=Transport)
    transport.read.side_effect = list(replies)
    dev = DLPC900(transport)
    dev.protocol._sequence = first_seq - 1
    return dev, transport


def sent(transport) -> list[bytes]:
    return [bytes(c.args[0]) for c in transport.write.call_args_list]


# ---- Section 1.2: the guide's own examples ------------------------------------------------------------------------
def test_read_request_and_reply_table_1_5_and_1_6():
    # Table 1-5: read Curtain Color: flags 0xC0 (read + reply), sequence 0x11, length 02 00, command 00 11.
    # Table 1-6: reply flags 0xC0, sequence 0x11, length 06 00, data FF 01 FF 01 FF 01 (each colour 511).
    proto = Protocol(Mock(spec=Transport))
    proto._sequence = 0x10
    proto.transport.read.side_effect = [report(0xC0, 0x11, 0x06, 0x00, 0xFF, 0x01, 0xFF, 0x01, 0xFF, 0x01)]
    assert proto.read("Curtain Color") == {"red": 511, "green": 511, "blue": 511}
    assert sent(proto.transport) == [report(0xC0, 0x11, 0x02, 0x00, 0x00, 0x11)]


def test_write_request_table_1_7():
    # Table 1-7: write Curtain Color 511, 511, 511 without reply: flags 0x00, sequence 0x12, length 08 00,
    # command 00 11, data FF 01 FF 01 FF 01.
    proto = Protocol(Mock(spec=Transport))
    proto._sequence = 0x11
    proto.write("Curtain Color", reply=False, red=511, green=511, blue=511)
    assert sent(proto.transport) == [report(0x00, 0x12, 0x08, 0x00, 0x00, 0x11, 0xFF, 0x01, 0xFF, 0x01, 0xFF, 0x01)]
    proto.transport.read.assert_not_called()


def test_long_message_split_into_64_byte_reports():
    # Section 1.2.1 / Figure 1-5: only the first transfer carries header and command; the rest continue the data.
    data = bytes(range(256)) + bytes(range(248))  # 504 bytes: a full Pattern BMP Load block
    msg = build_message(0x1A2B, (504).to_bytes(2, "little") + data, reply=False, sequence=7)
    reports = split_reports(msg)
    assert len(msg) == 512 and len(reports) == 8 and all(len(r) == 64 for r in reports)
    assert reports[0][:8] == bytes((0x00, 0x07, 0xFC, 0x01, 0x2B, 0x1A, 0xF8, 0x01))  # length 508 = 2 + 2 + 504
    assert b"".join(reports)[8:] == data
    short = split_reports(build_message(0x1A24, b"\x02", reply=False, sequence=1))
    assert short == [report(0x00, 0x01, 0x03, 0x00, 0x24, 0x1A, 0x02)]
    with pytest.raises(ValueError, match="512-byte command buffer"):
        build_message(0x1A2B, bytes(507))


def test_multi_report_reply_reassembled():
    # A 128-byte Read Error Description reply spans three reports (Section 1.2.2: length = data bytes).
    text = b"Invalid exposure".ljust(128, b"\0")
    body = bytes((0xC0, 0x05)) + (128).to_bytes(2, "little") + text
    rep = parse_reply(split_reports(body))
    assert rep.sequence == 5 and rep.data == text and not rep.error
    with pytest.raises(ProtocolError, match="truncated"):
        parse_reply(split_reports(body)[:1])


# ---- The guide's pattern-mode examples, command by command ----------------------------------------------------
def test_pre_stored_pattern_example():
    # DLPU018 "Pre-Stored Pattern Mode" example table, steps 1-5 (USB column, data bytes), sent with reply (0x40):
    # 1A1B 01; 1A34 00 00 C8 00 00 10 00 00 00 00 00 00 (pattern 0, 200 us, red, 1 bit);
    # 1A31 02 00 00 00 00 00 (2 entries, repeat forever); 1A24 02 (start).
    dev, t = make([ack(1), ack(2), ack(3), ack(4)])
    dev.set_display_mode("pre-stored")
    dev.define_pattern(LutEntry(0, 200, 0, 0, bit_depth=1, color="red", wait_for_trigger=False,
                                clear_after_exposure=False))
    dev.configure_lut(2, 0)
    dev.start()
    assert sent(t) == [
        report(0x40, 1, 0x03, 0x00, 0x1B, 0x1A, 0x01),
        report(0x40, 2, 0x0E, 0x00, 0x34, 0x1A, 0x00, 0x00, 0xC8, 0x00, 0x00, 0x10, 0x00, 0x00, 0x00, 0x00, 0x00,
               0x00),
        report(0x40, 3, 0x08, 0x00, 0x31, 0x1A, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00),
        report(0x40, 4, 0x03, 0x00, 0x24, 0x1A, 0x02),
    ]


def test_on_the_fly_example_lut_and_bmp_load():
    # DLPU018 "Image On-The-Fly Pattern Mode" example: 1A1B 03; 1A34 00 00 C8 00 00 11 00 00 00 00 00 00
    # (pattern 0, 200 us red 1-bit, clear after exposure); 1A34 01 00 90 01 00 23 00 00 00 00 00 08
    # (pattern 1, 400 us green 2-bit, bit position 1); 1A2A 00 00 A9 17 00 00 (image 0, 6057 bytes);
    # 1A2B F8 01 + 504 bytes ... 1A2B 09 00 + the last 9 bytes.
    blob = bytes((i * 7) & 0xFF for i in range(6057))
    n_loads = 13  # 12 full blocks of 504 = 6048 bytes, then 9
    dev, t = make([ack(i) for i in range(1, 5 + n_loads)])
    dev.set_display_mode("on-the-fly")
    dev.define_pattern(LutEntry(0, 200, 0, 0, color="red", wait_for_trigger=False, clear_after_exposure=True))
    dev.define_pattern(LutEntry(1, 400, 0, 1, bit_depth=2, color="green", wait_for_trigger=False,
                                clear_after_exposure=True))
    dev.load_image(0, blob)
    out = sent(t)
    assert out[0] == report(0x40, 1, 0x03, 0x00, 0x1B, 0x1A, 0x03)
    assert out[1] == report(0x40, 2, 0x0E, 0x00, 0x34, 0x1A, 0x00, 0x00, 0xC8, 0x00, 0x00, 0x11, 0x00, 0x00, 0x00,
                            0x00, 0x00, 0x00)
    assert out[2] == report(0x40, 3, 0x0E, 0x00, 0x34, 0x1A, 0x01, 0x00, 0x90, 0x01, 0x00, 0x23, 0x00, 0x00, 0x00,
                            0x00, 0x00, 0x08)
    assert out[3] == report(0x40, 4, 0x08, 0x00, 0x2A, 0x1A, 0x00, 0x00, 0xA9, 0x17, 0x00, 0x00)
    loads = out[4:]
    assert len(loads) == 12 * 8 + 1  # a 512-byte message is 8 reports; the last (15 bytes) fits in one
    assert loads[0][:8] == bytes((0x40, 5, 0xFC, 0x01, 0x2B, 0x1A, 0xF8, 0x01))
    assert loads[-1] == report(0x40, 17, 0x0D, 0x00, 0x2B, 0x1A, 0x09, 0x00, blob[-9:])
    data = b"".join(b"".join(loads[8 * i:8 * i + 8])[8:512] for i in range(12)) + loads[-1][8:17]
    assert data == blob


# ---- every other command: request bytes from each command's table ----------------------------------------------
READS = [
    # (method, USB command, reply data, expected result); tables: Sections 2.1.1-2.1.7 and the command tables.
    ("hardware_status", (0x0A, 0x1A), bytes((0x01,)), lambda r: r.initialized and r.errors == []),
    ("system_status", (0x0B, 0x1A), bytes((0x01,)), lambda r: r == 1),
    ("main_status", (0x0C, 0x1A), bytes((0x02,)), lambda r: r.sequencer_running and not r.parked),
    ("display_mode", (0x1B, 0x1A), bytes((0x03,)), lambda r: r == "on-the-fly"),
    ("lut_configuration", (0x31, 0x1A), bytes((0x3D, 0x00, 0x00, 0x00, 0x00, 0x00)), lambda r: r == (61, 0)),
    ("firmware_version", (0x05, 0x02), bytes((0x00, 0x00, 0x05, 0x06)) + bytes(12),
     lambda r: r["application"] == 0x06050000),
]


@pytest.mark.parametrize("method, cmd, data, check", READS, ids=[r[0] for r in READS])
def test_read_commands(method, cmd, data, check):
    dev, t = make([report(0xC0, 0x01, len(data), 0x00, data)])
    assert check(getattr(dev, method)())
    assert sent(t) == [report(0xC0, 0x01, 0x02, 0x00, *cmd)]


WRITES = [
    # (call, expected bytes after the 4-byte header): command LSB, MSB, then data as each table lays it out.
    (lambda d: d.stop(), (0x24, 0x1A, 0x00)),  # Pattern Display Start/Stop: 0 stop
    (lambda d: d.pause(), (0x24, 0x1A, 0x01)),  # 1 pause
    (lambda d: d.start(), (0x24, 0x1A, 0x02)),  # 2 start
    (lambda d: d.set_power_mode("standby"), (0x00, 0x02, 0x01)),  # Power Mode 0x0200: 1 standby
    (lambda d: d.set_display_mode("video"), (0x1B, 0x1A, 0x00)),  # Display Mode Selection: 0 video
    # Trigger Out 1 (0x1A1D): byte 0 bit 0 invert; bytes 2:1 rising delay int16; bytes 4:3 falling delay int16
    (lambda d: d.set_trigger_out1(invert=True, rising_delay_us=-20, falling_delay_us=100),
     (0x1D, 0x1A, 0x01, 0xEC, 0xFF, 0x64, 0x00)),
    (lambda d: d.set_trigger_out1(rising_delay_us=20000), (0x1D, 0x1A, 0x00, 0x20, 0x4E, 0x00, 0x00)),
    # Trigger In 1: bytes 1:0 delay (us), byte 2 at its reset value 0
    (lambda d: d.set_trigger_in1(105), (0x35, 0x1A, 0x69, 0x00, 0x00)),
    (lambda d: d.set_trigger_in1(1000), (0x35, 0x1A, 0xE8, 0x03, 0x00)),
    (lambda d: d.configure_lut(400, 1000), (0x31, 0x1A, 0x90, 0x01, 0xE8, 0x03, 0x00, 0x00)),  # Table 2-136
    # Pattern Display LUT Definition: entry 300, 1 ms, white 1-bit, wait for trigger, dark 50 us, trigger 2 off,
    # image 12 bit 23: byte 5 = 0b1_111_000_0 = 0xF0; bytes 11:10 = 12 | 23 << 11 = 0xB80C
    (lambda d: d.define_pattern(LutEntry(300, 1000, 12, 23, dark_us=50, trigger_out2=False,
                                         clear_after_exposure=False)),
     (0x34, 0x1A, 0x2C, 0x01, 0xE8, 0x03, 0x00, 0xF0, 0x32, 0x00, 0x00, 0x01, 0x0C, 0xB8)),
    # Initialize Pattern BMP Load / Pattern BMP Load, secondary controller (0x1A2C, 0x1A2D), same layouts
    (lambda d: d.load_image(3, b"\xAB\xCD", controller=1), (0x2C, 0x1A, 0x03, 0x00, 0x02, 0x00, 0x00, 0x00)),
]


@pytest.mark.parametrize("call, body", WRITES, ids=[f"{w[1][1]:02X}{w[1][0]:02X}-{i}" for i, w in enumerate(WRITES)])
def test_write_commands(call, body):
    dev, t = make([ack(1), ack(2)])
    call(dev)
    assert sent(t)[0] == report(0x40, 0x01, len(body), 0x00, *body)


def test_secondary_bmp_load_data():
    dev, t = make([ack(1), ack(2)])
    dev.load_image(3, b"\xAB\xCD", controller=1)
    assert sent(t)[1] == report(0x40, 0x02, 0x06, 0x00, 0x2D, 0x1A, 0x02, 0x00, 0xAB, 0xCD)


def test_lut_entry_round_trip_and_limits():
    e = LutEntry(17, 123456, 5, 9, bit_depth=3, color="cyan", wait_for_trigger=False, dark_us=77,
                 clear_after_exposure=True, trigger_out2=False)
    layout = COMMANDS["Pattern Display LUT Definition"].layout
    assert LutEntry.from_fields(decode_fields(layout, encode_fields(layout, e.fields()))) == e
    with pytest.raises(ValueError, match="bit position"):
        LutEntry(0, 200, 0, 24).fields()
    with pytest.raises(ValueError, match="exposure_us must be an integer in"):
        encode_fields(layout, LutEntry(0, 1 << 24).fields())


# ---- replies: errors, error status read-back, sequence matching -----------------------------------------------
def test_error_reply_reads_back_error_status():
    # Reply flags with bit 5 set (Section 1.2.2): the driver reads Read Error Code (0x0100, Section 2.1.6) and
    # Read Error Description (0x0101, Section 2.1.7) and raises with both.
    desc = b"Exposure out of range".ljust(128, b"\0")
    replies = [report(0x60, 0x01, 0x00, 0x00),  # write reply with the error bit
               report(0xC0, 0x02, 0x01, 0x00, 0x0E),  # error code 14
               *split_reports(bytes((0xC0, 0x03, 0x80, 0x00)) + desc)]
    dev, t = make(replies)
    with pytest.raises(CommandRejected, match=r"Pattern Display LUT Definition \(0x1A34\): error 14 \(pattern "
                                              r"exposure time is out of range\): Exposure out of range") as err:
        dev.define_pattern(LutEntry(0, 50))
    assert err.value.code == 14
    out = sent(t)
    assert out[1] == report(0xC0, 0x02, 0x02, 0x00, 0x00, 0x01)
    assert out[2] == report(0xC0, 0x03, 0x02, 0x00, 0x01, 0x01)


def test_stale_reply_skipped_and_missing_reply_is_protocol_error():
    # A reply with an older sequence byte (left over from an interrupted transaction) is not this command's.
    dev, _ = make([report(0xC0, 0x07, 0x01, 0x00, 0x00), report(0xC0, 0x01, 0x01, 0x00, 0x02)])
    assert dev.main_status().sequencer_running
    dev, _ = make([report(0xC0, 0x09, 0x01, 0x00, 0x00)] * 4)
    with pytest.raises(ProtocolError, match="Main Status .*sequence"):
        dev.main_status()
    dev, _ = make([report(0xC0, 0x01, 0x00, 0x00)])
    with pytest.raises(ProtocolError, match="too short"):
        dev.main_status()


def test_unknown_command_names_listed():
    with pytest.raises(ValueError, match="known: Read Error Code"):
        Protocol(Mock(spec=Transport)).write("Make Coffee")
    with pytest.raises(ValueError, match="cannot be written"):
        Protocol(Mock(spec=Transport)).write("Main Status", status=0)


def test_upload_sequence_order_and_argument_checks():
    # Stop, on-the-fly mode, K LUT entries, LUT configuration, then images last first (DLPU018 example order).
    from specgpu.hardware.dlpc900 import SimulatedDLPC900

    sim = SimulatedDLPC900("lightcrafter-9000")
    dev = DLPC900(sim, dmd="lightcrafter-9000")
    images = np.zeros((2, 1600, 2560), np.uint32)
    dev.upload_sequence(images, [LutEntry(k, 500, k // 24, k % 24) for k in range(30)], compression="rle")
    names = [n for n, _ in sim.commands]
    assert names[:2] == ["Pattern Display Start/Stop", "Display Mode Selection"]
    assert names[2:32] == ["Pattern Display LUT Definition"] * 30 and names[32] == "Pattern Display LUT Configuration"
    inits = [(n, f["image_index"]) for n, f in sim.commands if n.startswith("Initialize")]
    assert inits == [("Initialize Pattern BMP Load", 1), ("Initialize Pattern BMP Load Secondary", 1),
                     ("Initialize Pattern BMP Load", 0), ("Initialize Pattern BMP Load Secondary", 0)]
    with pytest.raises(ValueError, match=r"images must be \(N, 1600, 2560\)"):
        dev.upload_sequence(np.zeros((1, 1080, 1920), np.uint32), [LutEntry(0, 500)])
    with pytest.raises(ValueError, match="1 to 400 LUT entries"):
        dev.upload_sequence(images, [])
