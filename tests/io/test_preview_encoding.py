"""How a PNG preview is encoded: every row unfiltered (the cheap encoding of a noisy rendering), the pixels exactly
those rendered."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import OpenImageIO as oiio

from specgpu import io
from specgpu.io.previews import sRGB8


def png_rows(path):
    """(filter type of each row, width, height, channels) from a PNG's IHDR and IDAT chunks."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    width, height, depth, colour_type = header[:4]
    channels = {2: 3, 6: 4, 0: 1}[colour_type]
    raw = zlib.decompress(idat)
    stride = 1 + width * channels * depth // 8
    return [raw[i * stride] for i in range(height)], width, height, channels


def test_a_preview_is_written_unfiltered_with_its_pixels_unchanged(tmp_path):
    rng = np.random.default_rng(1)
    XYZ = rng.uniform(0.05, 0.9, (24, 32, 3))
    path = io.write_sRGB_preview(tmp_path / "p.png", XYZ, exposure=0.0)
    filters, width, height, channels = png_rows(path)
    assert (width, height, channels) == (32, 24, 3)
    assert set(filters) == {0}  # filter type 0 (none) on every row
    back = oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)
    np.testing.assert_array_equal(back, sRGB8(XYZ))
