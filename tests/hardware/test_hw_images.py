"""Patterns <-> DMD bit-planes <-> the DLPC900's image format, and a whole upload replayed back to the patterns."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from specgpu.hardware.dlpc900 import DLPC900, DLPC900Light, DMDGeometry, DMDLayout, SimulatedDLPC900
from specgpu.hardware.dlpc900.images import decode_image, encode_image, geometry, image_header

SMALL = DMDGeometry("test-dmd", 96, 40)


def px(*hexes) -> list[int]:
    return [int(h, 16) for h in hexes]


# ---- the image header and the encodings, byte-exact from the guide ------------------------------------------------
def test_image_header_table_2_109():
    # Table 2-109: signature 53 70 6C 64, width, height, data bytes (LE), 8 x FF reserved, background BB GG RR 00,
    # 00 reserved, compression, 01 reserved, 21 x 00 reserved.
    expected = bytes([0x53, 0x70, 0x6C, 0x64, 0x80, 0x07, 0x38, 0x04, 0x79, 0x17, 0x00, 0x00] + [0xFF] * 8
                     + [0x00] * 4 + [0x00, 0x02, 0x01] + [0x00] * 21)
    assert image_header(1920, 1080, 6009, 2) == expected and len(expected) == 48


def test_rle_encoding_table_2_111():
    # Table 2-111: a 2-line image of 13 pixels per line. Line 1: 03 040506 | 05 777777 | 00 03 040506 070809 0A0B0C |
    # 02 789ABC | 00 00 (end of line) | 00 00 00 (padding to a 4-byte boundary); line 2: 07 1D1E1F | 06 212223 |
    # 00 01 (end of image). TI's encoder then pads the data to 16 bytes.
    line1 = px("040506") * 3 + px("777777") * 5 + px("040506", "070809", "0A0B0C") + px("789ABC") * 2
    line2 = px("1D1E1F") * 7 + px("212223") * 6
    image = np.array([line1, line2], np.uint32)
    data = bytes.fromhex("03040506 05777777 0003040506070809 0A0B0C 02789ABC 0000 000000"
                         "071D1E1F 06212223 0001")
    data += bytes(-len(data) % 16)
    blob = encode_image(image, "rle")
    assert blob == image_header(13, 2, len(data), 1) + data
    np.testing.assert_array_equal(decode_image(blob), image)


def test_enhanced_rle_encoding_table_2_112():
    # Table 2-112 grammar with 15-bit counts (c < 128: one byte, else c & 0x7F | 0x80, c >> 7): repeat n + pixel,
    # 00 n + n raw pixels, 00 01 n = copy n pixels from the line above, 00 00 end of line, 00 01 00 end of image.
    line1 = px("040506") * 3 + px("777777") * 5 + px("040506", "070809", "0A0B0C") + px("789ABC") * 130
    line2 = px("010203") + line1[1:]
    image = np.array([line1, line2], np.uint32)
    data = bytes.fromhex("03040506 05777777 0003040506070809 0A0B0C 8201789ABC 0000"  # 130 = 0x82 0x01
                         "01010203 00018C01 0000"  # 1 raw pixel, copy 140 = 0x8C 0x01, end of line
                         "000100")
    data += bytes(-len(data) % 4)
    blob = encode_image(image, "erle")
    assert blob == image_header(141, 2, len(data), 2) + data
    np.testing.assert_array_equal(decode_image(blob), image)


def test_enhanced_rle_lines_that_repeat_the_one_above_are_one_copy_each():
    """A pattern of columns (every line the same, as a spectral pattern's are): the first line in runs, each other
    line one copy of the whole line (a 15-bit count here: 200 = 0xC8 0x01); a changed line between them is encoded
    on its own, the lines after it copying it."""
    first = px("010203") * 150 + px("0A0B0C") * 50
    other = px("010203") * 149 + px("FFFFFF") + px("0A0B0C") * 50
    image = np.array([first, first, first, other, other], np.uint32)
    copy = "0001C801 0000"
    data = bytes.fromhex("9601010203 320A0B0C 0000" + copy + copy  # 150 = 0x96 0x01; 50 = 0x32
                         + "00019501 01FFFFFF 000132 0000"  # copy 149 (0x95 0x01), 1 raw pixel, copy 50
                         + copy + "000100")
    data += bytes(-len(data) % 4)
    blob = encode_image(image, "erle")
    assert blob == image_header(200, 5, len(data), 2) + data
    np.testing.assert_array_equal(decode_image(blob), image)


def test_uncompressed_lines_padded_to_16_bytes():
    image = np.arange(2 * 7, dtype=np.uint32).reshape(2, 7) * 0x010101
    blob = encode_image(image, "none")
    line = 3 * 7 + 11  # 21 bytes padded to 32
    assert len(blob) == 48 + 2 * line and blob[48:51] == bytes((0, 0, 0)) and blob[51:54] == bytes((1, 1, 1))
    np.testing.assert_array_equal(decode_image(blob), image)


@pytest.mark.parametrize("compression", ["none", "rle", "erle"])
def test_encodings_round_trip_random_and_structured(compression):
    rng = np.random.default_rng(7)
    for shape in [(1, 1), (3, 300), (17, 33)]:
        noise = rng.integers(0, 1 << 24, shape).astype(np.uint32)
        blocks = (rng.integers(0, 3, shape) * 0x00FF01).astype(np.uint32)
        rows = np.repeat(blocks[:1], shape[0], axis=0)
        for image in (noise, blocks, rows):
            np.testing.assert_array_equal(decode_image(encode_image(image, compression)), image)


def test_malformed_images_are_refused():
    image = np.ones((4, 5), np.uint32)
    blob = bytearray(encode_image(image, "rle"))
    with pytest.raises(ValueError, match="Spld"):
        decode_image(b"Nope" + bytes(blob[4:]))
    with pytest.raises(ValueError, match="truncated"):
        decode_image(bytes(blob[:-4]))
    short = bytearray(blob)
    short[48] = 4  # the first run now leaves the line one pixel short before its end of line
    with pytest.raises(ValueError, match="line not filled|overflows"):
        decode_image(bytes(short))
    with pytest.raises(ValueError, match="below 2\\*\\*24"):
        encode_image(np.full((2, 2), 1 << 24, np.uint32))
    with pytest.raises(ValueError, match="unknown compression 'zip'"):
        encode_image(image, "zip")


# ---- patterns <-> bit-planes -----------------------------------------------------------------------------------
def test_layout_places_centred_runs():
    layout = DMDLayout(SMALL, columns=4, rows=10, column_step=2)
    assert (layout.column_offset, layout.row_offset) == (44, 15)
    mask = layout.pattern_to_mask([0, 10, 3, 4])
    assert mask.sum() == 2 * (10 + 3 + 4)
    np.testing.assert_array_equal(np.flatnonzero(mask[:, 46]), np.arange(15, 25))  # full column
    np.testing.assert_array_equal(np.flatnonzero(mask[:, 48]), np.arange(18, 21))  # 3 centred in 10
    np.testing.assert_array_equal(layout.mask_to_pattern(mask), [0, 10, 3, 4])
    bad = mask.copy()
    bad[0, 0] = True
    with pytest.raises(ValueError, match="outside the pattern's block"):
        layout.mask_to_pattern(bad)
    with pytest.raises(ValueError, match=r"mirror counts must lie in \[0, 10\]"):
        layout.pattern_to_mask([0, 11, 0, 0])
    with pytest.raises(ValueError, match="do not fit"):
        DMDLayout(SMALL, columns=60, rows=10, column_step=2)


def test_bitplanes_pack_24_patterns_per_image():
    layout = DMDLayout(SMALL, columns=32, rows=40)
    p = np.random.default_rng(3).integers(0, 41, (50, 32))
    images = layout.patterns_to_images(p)
    assert images.shape == (3, 40, 96) and images.dtype == np.uint32
    # pattern 25 is bit 1 of image 1
    np.testing.assert_array_equal((images[1] >> 1) & 1, layout.pattern_to_mask(p[25]))
    np.testing.assert_array_equal(layout.images_to_patterns(images, 50), p)


# ---- an upload replayed and decoded back: the full-size DMDs ---------------------------------------------------
@pytest.mark.parametrize("dmd, compression", [("lightcrafter-6500", "erle"), ("lightcrafter-9000", "rle"),
                                              ("lightcrafter-6500", "none")])
def test_sequence_upload_replayed_to_patterns(dmd, compression):
    sim = SimulatedDLPC900(dmd)
    light = DLPC900Light(DLPC900(sim, dmd=dmd), exposure_s=0.002, compression=compression)
    k = 26 if compression != "none" else 3  # 26 patterns: two images, the second partly used
    rng = np.random.default_rng(11)
    patterns = rng.integers(0, light.layout.rows + 1, (k, light.layout.columns))
    patterns[0] = 0  # dark
    patterns[1] = light.layout.rows  # all on
    light.load_sequence(patterns)
    # Replay the recorded reports through a fresh simulated controller: it must rebuild the same images.
    replay = SimulatedDLPC900(dmd)
    replay.open()
    for direction, rep in sim.log:
        if direction == "out":
            replay.write(rep)
    n_img = -(-k // 24)
    images = np.stack([replay.image(i) for i in range(n_img)])
    assert images.shape[1:] == (geometry(dmd).height, geometry(dmd).width)
    np.testing.assert_array_equal(light.layout.images_to_patterns(images, k), patterns)
    # and the LUT says pattern j is image j // 24, bit j % 24, 1 bit, waiting for the trigger
    for j in sorted({0, 23, 24, k - 1} & set(range(k))):
        e = replay.lut[j]
        assert (e["image"] & 0x7FF, e["image"] >> 11, e["options"] >> 7, (e["options"] >> 1) & 7) == \
            (j // 24, j % 24, 1, 0)
    assert replay.lut_entries == k and replay.mode == 3


def test_plan_from_calibration_uploaded_through_the_column_map():
    # A narrowband plan from the oracle calibration: its (K, 1024) mirror counts on the calibration's column map
    # become LightCrafter 6500 images; the controller ends up holding exactly the plan's patterns.
    from specgpu.calibration.bundle import oracle_calibration
    from specgpu.planning import plan_narrowband

    bundle = oracle_calibration()
    plan = plan_narrowband(bundle, step_nm=20.0)
    sim = SimulatedDLPC900("lightcrafter-6500")
    light = DLPC900Light(DLPC900(sim), calibration=bundle)
    assert (light.layout.columns, light.layout.rows, light.layout.column_offset) == (1024, 768, 448)
    light.load_plan(plan)
    k = plan.patterns.shape[0]
    images = np.stack([sim.image(i) for i in range(-(-k // 24))])
    np.testing.assert_array_equal(light.layout.images_to_patterns(images, k), plan.patterns)
    assert sim.lut[0]["exposure_us"] == round(plan.exposure_s * 1e6)
    np.testing.assert_allclose(light.emitted_spectrum(3), bundle.emitted(plan.patterns[3]))
    with pytest.raises(ValueError, match="stale"):
        light.load_plan(dataclasses.replace(plan, calibration="0" * 64))
    from specgpu.rig.light import LightParameters, ProgrammableLight

    with pytest.raises(ValueError, match="calibration has 1024 columns x 768 rows, the light model 128 x 64"):
        DLPC900Light(DLPC900(sim), model=ProgrammableLight(LightParameters(columns=128, rows=64)), calibration=bundle)
