"""Patterns of mirror counts -> DMD bit-planes -> the DLPC900's 24-bit images, and back.

A pattern (C,) gives, for each wavelength column c of the light, the number of mirrors on (paper Fig. 2). On the DMD
the pattern's columns occupy a block of physical columns (``column_step`` per pattern column, starting at
``column_offset``) and the ``rows`` intensity rows a block of physical rows; the ``n`` mirrors of a column are a
contiguous run centred in that block, so the lit area stays where the light guide's entrance is.

In pattern-on-the-fly mode the controller takes 24-bit images: bit ``b`` of every pixel is the binary pattern shown
for a LUT entry with bit position ``b`` (DLPU018, Pattern Display LUT Definition, bytes 11:10), so 24 binary
patterns share one image. On the wire a pixel is three bytes, bits 23-16, 15-8, 7-0 (the order the public
pycrafter6500 / ERLE encoders use on hardware; TI's GUI names the bytes after its own RGB buffer).

Each image is sent with the 48-byte header of DLPU018 Table 2-109 and one of three encodings:

- 0, uncompressed: lines of 3 * width bytes, each padded to a 16-byte boundary (TI's GUI, splash.c);
- 1, RLE (Tables 2-110, 2-111): ``n>0, pixel`` repeats a pixel n times; ``0, c>=2, c pixels`` copies raw pixels;
  ``0, 0`` ends a line and the next line starts on a 4-byte boundary (zero padding); ``0, 1`` ends the image, padded
  to 16 bytes;
- 2, enhanced RLE (Tables 2-112, 2-113): as RLE with 15-bit counts (``c < 128``: one byte; else ``c & 0x7F | 0x80``
  then ``c >> 7``), plus ``0, 1, count`` = copy ``count`` pixels from the line above; ``0, 0`` ends a line; ``0, 1, 0``
  ends the image. (Table 2-113's example writes ``82 01`` for 513 repeats, which no reading of the count rule gives;
  the rule above is the one in TI's own encoder, compress.c, and in the public encoders.)

For a dual-controller DMD (DLP9000, 2560 x 1600) each controller gets its half of every image (left half to the
primary), and the header's width is half the DMD's (Table 2-109).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from specgpu.core.validate import check_number

__all__ = ["DMDGeometry", "GEOMETRIES", "DMDLayout", "COMPRESSIONS", "BITS_PER_IMAGE", "encode_image",
           "decode_image", "image_header", "split_controllers", "join_controllers"]

BITS_PER_IMAGE = 24
HEADER_SIZE = 48
SIGNATURE = b"Spld"
COMPRESSIONS = {"none": 0, "rle": 1, "erle": 2}


@dataclass(frozen=True)
class DMDGeometry:
    """A DLPC900 DMD.

    Attributes
    ----------
    name : str
    width, height : int
        Mirrors per row and rows.
    controllers : int
        1 (DLP6500) or 2 (DLP9000: each controller drives half the columns).
    min_exposure_us : int
        Shortest exposure of a 1-bit pattern in pattern-on-the-fly mode, us (Trigger In 1's reset delay, 105 us).
    """

    name: str
    width: int
    height: int
    controllers: int = 1
    min_exposure_us: int = 105

    def __post_init__(self):
        check_number("width", self.width, low=1, high=65535, integer=True)
        check_number("height", self.height, low=1, high=65535, integer=True)
        if self.controllers not in (1, 2) or self.width % self.controllers:
            raise ValueError(f"{self.name}: controllers must be 1 or 2 and divide the width, got {self.controllers}")


GEOMETRIES = {
    "lightcrafter-6500": DMDGeometry("lightcrafter-6500", 1920, 1080, 1),
    "lightcrafter-9000": DMDGeometry("lightcrafter-9000", 2560, 1600, 2),
}


def geometry(name_or_geometry) -> DMDGeometry:
    """A :class:`DMDGeometry` by name (``ValueError`` listing the names) or passed through."""
    if isinstance(name_or_geometry, DMDGeometry):
        return name_or_geometry
    try:
        return GEOMETRIES[name_or_geometry]
    except (KeyError, TypeError):
        raise ValueError(f"unknown DMD {name_or_geometry!r}; valid: {', '.join(GEOMETRIES)}") from None


@dataclass(frozen=True)
class DMDLayout:
    """Where a pattern's columns and intensity rows sit on the DMD.

    Attributes
    ----------
    geometry : DMDGeometry
    columns : int
        Pattern columns C (the calibration's column map has one wavelength per column).
    rows : int
        Intensity rows: a pattern value is a mirror count in [0, rows].
    column_offset : int
        First DMD column of pattern column 0 (default: the pattern centred).
    column_step : int
        DMD columns per pattern column (>= 1): all show the same count.
    row_offset : int
        First DMD row of the intensity block (default: centred).
    """

    geometry: DMDGeometry
    columns: int
    rows: int
    column_offset: int = -1
    column_step: int = 1
    row_offset: int = -1

    def __post_init__(self):
        g = self.geometry
        check_number("columns", self.columns, low=1, integer=True)
        check_number("rows", self.rows, low=1, high=g.height, integer=True)
        check_number("column_step", self.column_step, low=1, integer=True)
        span = self.columns * self.column_step
        if span > g.width:
            raise ValueError(f"{self.columns} columns x {self.column_step} DMD columns each = {span} do not fit the "
                             f"{g.width} columns of the {g.name}")
        if self.column_offset == -1:
            object.__setattr__(self, "column_offset", (g.width - span) // 2)
        if self.row_offset == -1:
            object.__setattr__(self, "row_offset", (g.height - self.rows) // 2)
        if not 0 <= self.column_offset <= g.width - span:
            raise ValueError(f"column_offset {self.column_offset} puts the pattern outside the {g.width} DMD columns")
        if not 0 <= self.row_offset <= g.height - self.rows:
            raise ValueError(f"row_offset {self.row_offset} puts the {self.rows} rows outside the {g.height} DMD rows")

    @classmethod
    def from_calibration(cls, bundle, dmd="lightcrafter-6500", **kw) -> DMDLayout:
        """The layout for a calibration bundle's column map (``bundle.columns`` columns, ``bundle.rows`` rows)."""
        return cls(geometry(dmd), int(bundle.columns), int(bundle.rows), **kw)

    def check_patterns(self, patterns) -> np.ndarray:
        """(K, C) int32 mirror counts in [0, rows]; ``ValueError`` naming the problem."""
        p = np.asarray(patterns)
        if p.ndim == 1:
            p = p[None]
        if p.ndim != 2 or p.shape[1] != self.columns or p.shape[0] < 1:
            raise ValueError(f"patterns must be (K, {self.columns}) mirror counts, got shape {np.shape(patterns)}")
        if not np.issubdtype(p.dtype, np.integer):
            if not np.all(np.isfinite(p)) or np.any(p != np.round(p)):
                raise ValueError("patterns must hold whole mirror counts")
        p = p.astype(np.int64)
        if p.min() < 0 or p.max() > self.rows:
            raise ValueError(f"mirror counts must lie in [0, {self.rows}], got [{p.min()}, {p.max()}]")
        return p.astype(np.int32)

    def _runs(self, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        start = self.row_offset + (self.rows - counts) // 2
        return start, start + counts

    def pattern_to_mask(self, pattern) -> np.ndarray:
        """(height, width) bool mirror states of one pattern."""
        p = self.check_patterns(pattern)[0]
        g = self.geometry
        start, stop = self._runs(np.repeat(p, self.column_step))
        r = np.arange(g.height)[:, None]
        mask = np.zeros((g.height, g.width), bool)
        c0 = self.column_offset
        mask[:, c0:c0 + p.size * self.column_step] = (r >= start[None]) & (r < stop[None])
        return mask

    def patterns_to_images(self, patterns) -> np.ndarray:
        """(ceil(K / 24), height, width) uint32 24-bit images; pattern k is bit ``k % 24`` of image ``k // 24``."""
        p = self.check_patterns(patterns)
        g = self.geometry
        n_img = -(-p.shape[0] // BITS_PER_IMAGE)
        images = np.zeros((n_img, g.height, g.width), np.uint32)
        for k in range(p.shape[0]):
            images[k // BITS_PER_IMAGE] |= self.pattern_to_mask(p[k]).astype(np.uint32) << np.uint32(k % 24)
        return images

    def mask_to_pattern(self, mask) -> np.ndarray:
        """The mirror counts a (height, width) mirror image shows; ``ValueError`` if it is not such a pattern
        (mirrors outside the block, a column that is not one centred run, or columns of a step that differ)."""
        m = np.asarray(mask, bool)
        g = self.geometry
        if m.shape != (g.height, g.width):
            raise ValueError(f"mask must be ({g.height}, {g.width}), got {m.shape}")
        c0, span = self.column_offset, self.columns * self.column_step
        block = m[self.row_offset:self.row_offset + self.rows, c0:c0 + span]
        if m.sum() != block.sum():
            raise ValueError("mirrors are on outside the pattern's block")
        counts = block.sum(axis=0)
        per = counts.reshape(self.columns, self.column_step)
        if np.any(per != per[:, :1]):
            raise ValueError("DMD columns of one pattern column show different counts")
        p = per[:, 0].astype(np.int32)
        if not np.array_equal(self.pattern_to_mask(p), m):
            raise ValueError("a column's mirrors are not one run centred in the intensity block")
        return p

    def images_to_patterns(self, images, n_patterns: int) -> np.ndarray:
        """Inverse of :meth:`patterns_to_images`: the first ``n_patterns`` bit-planes decoded to (K, C) counts."""
        imgs = np.asarray(images, np.uint32)
        if n_patterns > imgs.shape[0] * BITS_PER_IMAGE:
            raise ValueError(f"{imgs.shape[0]} images hold at most {imgs.shape[0] * 24} patterns, not {n_patterns}")
        return np.stack([self.mask_to_pattern((imgs[k // 24] >> np.uint32(k % 24)) & 1)
                         for k in range(n_patterns)])


# ---- the controller's image format --------------------------------------------------------------------------
def image_header(width: int, height: int, data_bytes: int, compression: int) -> bytes:
    """The 48-byte image header of DLPU018 Table 2-109 (``width`` is per controller)."""
    return (SIGNATURE + width.to_bytes(2, "little") + height.to_bytes(2, "little")
            + data_bytes.to_bytes(4, "little") + b"\xff" * 8 + bytes(4)  # reserved; background colour BB GG RR 00
            + bytes((0x00, compression, 0x01)) + bytes(21))


def _pixels(line: np.ndarray) -> np.ndarray:
    """(..., W) uint32 -> (..., W, 3) uint8, bits 23-16, 15-8, 7-0."""
    return np.stack([(line >> 16) & 0xFF, (line >> 8) & 0xFF, line & 0xFF], axis=-1).astype(np.uint8)


def _count(n: int) -> bytes:
    # enhanced RLE counts: 7 bits, or 15 bits over two bytes with the top bit of the first set
    return bytes((n,)) if n < 128 else bytes(((n & 0x7F) | 0x80, n >> 7))


def _runs(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starts and lengths of the runs of equal values."""
    edges = np.flatnonzero(values[1:] != values[:-1]) + 1
    starts = np.concatenate(([0], edges))
    return starts, np.diff(np.concatenate((starts, [values.size])))


def _encode_line_rle(line: np.ndarray, out: bytearray) -> None:
    px = _pixels(line)
    starts, lengths = _runs(line)
    raw = []  # start indices of pending single pixels

    def flush():
        i = 0
        while i < len(raw):
            n = min(255, len(raw) - i)
            a = raw[i]
            if n == 1:
                out.extend(b"\x01" + px[a].tobytes())
            else:
                out.extend(bytes((0, n)) + px[a:a + n].tobytes())
            i += n
        raw.clear()

    for s, n in zip(starts.tolist(), lengths.tolist()):
        if n == 1:
            raw.append(s)  # single pixels between runs are contiguous: one raw command
            continue
        flush()
        while n > 0:
            m = min(255, n)
            if m == 1:
                out.extend(b"\x01" + px[s].tobytes())
            else:
                out.extend(bytes((m,)) + px[s].tobytes())
            s += m
            n -= m
    flush()


def _first_from(flags: np.ndarray, value: bool) -> np.ndarray:
    """For each i along the last axis, the first index >= i where ``flags`` equals ``value`` (the axis' size if
    none): rows of a 2-D array each on their own."""
    n = flags.shape[-1]
    idx = np.where(flags == value, np.arange(n), n)
    return np.minimum.accumulate(idx[..., ::-1], axis=-1)[..., ::-1]


def _encode_erle(img: np.ndarray, out: bytearray) -> None:
    """Every line of ``img`` (H, W) uint32 in enhanced RLE, each ended by its end-of-line command. A line that
    repeats the one above (a pattern of columns, as spectral ones are) is one copy command; for the others, where
    each copy, repeat and raw span ends is found for all of them at once, and only the walk over the spans is per
    line."""
    h, w = img.shape
    whole_copy = np.zeros(h, bool)
    whole_copy[1:] = (img[1:] == img[:-1]).all(axis=1)
    rows = np.flatnonzero(~whole_copy)
    lines = img[rows]
    px = _pixels(lines)  # (R, W, 3)
    same_prev = np.zeros(lines.shape, bool)
    above = rows > 0
    same_prev[above] = lines[above] == img[rows[above] - 1]
    same_next = np.zeros(lines.shape, bool)
    same_next[:, :-1] = lines[:, 1:] == lines[:, :-1]
    copy_end = _first_from(same_prev, False)  # a copy from j covers [j, copy_end[j])
    run_end = _first_from(same_next, False)  # a repeat from j covers [j, run_end[j]]
    stop_at = _first_from(same_prev | same_next, True)  # raw pixels stop where a copy or repeat can start
    copy_line = b"\x00\x01" + _count(w) + b"\x00\x00"
    r = 0
    for y in range(h):
        if whole_copy[y]:
            out.extend(copy_line)
            continue
        prev, nxt, line = same_prev[r].tolist(), same_next[r].tolist(), px[r]
        copies, repeats, stops = copy_end[r].tolist(), run_end[r].tolist(), stop_at[r].tolist()
        r += 1
        j = 0
        while j < w:
            if prev[j]:
                n = copies[j] - j
                out.extend(b"\x00\x01" + _count(n))
            elif nxt[j]:
                n = repeats[j] - j + 1
                out.extend(_count(n) + line[j].tobytes())
            else:
                n = (stops[j + 1] if j + 1 < w else w) - j
                if n == 1:
                    out.extend(b"\x01" + line[j].tobytes())
                else:
                    out.extend(b"\x00" + _count(n) + line[j:j + n].tobytes())
            j += n
        out.extend(b"\x00\x00")


def encode_image(image, compression: str = "erle") -> bytes:
    """One controller's 24-bit image (H, W) uint32 -> header (Table 2-109) + encoded data."""
    if compression not in COMPRESSIONS:
        raise ValueError(f"unknown compression {compression!r}; valid: {', '.join(COMPRESSIONS)}")
    img = np.asarray(image)
    if img.ndim != 2 or not np.issubdtype(img.dtype, np.integer) or (img.size and int(img.max()) >= 1 << 24):
        raise ValueError(f"image must be (H, W) integers below 2**24, got {img.shape} {img.dtype}")
    img = img.astype(np.uint32)
    h, w = img.shape
    out = bytearray()
    if compression == "none":
        pad = bytes(-(3 * w) % 16)
        for y in range(h):
            out += _pixels(img[y]).tobytes() + pad
    elif compression == "rle":
        for y in range(h):
            _encode_line_rle(img[y], out)
            if y < h - 1:
                out += b"\x00\x00"
                out += bytes(-len(out) % 4)
        out += b"\x00\x01"
        out += bytes(-len(out) % 16)
    else:
        _encode_erle(img, out)
        out += b"\x00\x01\x00"
        out += bytes(-len(out) % 4)
    return image_header(w, h, len(out), COMPRESSIONS[compression]) + bytes(out)


def decode_image(blob: bytes) -> np.ndarray:
    """Header + encoded data -> (H, W) uint32; ``ValueError`` on a malformed image (a strict decoder, as the
    controller's: every line must be filled exactly)."""
    blob = bytes(blob)
    if len(blob) < HEADER_SIZE or blob[:4] != SIGNATURE:
        raise ValueError("not a DLPC900 image: missing 'Spld' signature")
    w = int.from_bytes(blob[4:6], "little")
    h = int.from_bytes(blob[6:8], "little")
    size = int.from_bytes(blob[8:12], "little")
    comp = blob[25]
    data = blob[HEADER_SIZE:HEADER_SIZE + size]
    if len(data) != size:
        raise ValueError(f"image data truncated: header says {size} bytes, got {len(data)}")
    if w == 0 or h == 0:
        raise ValueError(f"image of zero size {w} x {h}")
    img = np.zeros((h, w, 3), np.uint8)
    if comp == 0:
        stride = 3 * w + (-(3 * w) % 16)
        if size < stride * h:
            raise ValueError(f"uncompressed image needs {stride * h} bytes, got {size}")
        rows = np.frombuffer(data[:stride * h], np.uint8).reshape(h, stride)[:, :3 * w]
        img[:] = rows.reshape(h, w, 3)
    elif comp in (1, 2):
        _decode_runs(data, img, enhanced=comp == 2)
    else:
        raise ValueError(f"unknown compression type {comp} in image header")
    return (img[..., 0].astype(np.uint32) << 16) | (img[..., 1].astype(np.uint32) << 8) | img[..., 2]


def _decode_runs(data: bytes, img: np.ndarray, *, enhanced: bool) -> None:
    h, w, _ = img.shape
    pos, y, x = 0, 0, 0

    def need(n):
        if pos + n > len(data):
            raise ValueError(f"image data ends inside a command at byte {pos}")

    def count():
        nonlocal pos
        need(1)
        c = data[pos]
        pos += 1
        if enhanced and c & 0x80:
            need(1)
            c = (c & 0x7F) | (data[pos] << 7)
            pos += 1
        return c

    def put(values, n):
        nonlocal x, y
        if y >= h or x + n > w:
            raise ValueError(f"run of {n} pixels overflows line {y} at column {x} (width {w})")
        img[y, x:x + n] = values
        x += n
        if x == w and enhanced:  # enhanced RLE lines end implicitly when full
            x, y = 0, y + 1

    while True:
        need(1)
        if data[pos] != 0:
            n = count()
            need(3)
            put(np.frombuffer(data[pos:pos + 3], np.uint8), n)
            pos += 3
            continue
        pos += 1
        need(1)
        c = data[pos]
        if c == 0:  # end of line
            pos += 1
            if enhanced:
                if x != 0:
                    raise ValueError(f"end of line at column {x} of line {y}: line not filled")
            else:
                if x != w:
                    raise ValueError(f"end of line at column {x} of line {y}: line not filled")
                x, y = 0, y + 1
                pos += -pos % 4
        elif c == 1 and not enhanced:  # end of image
            pos += 1
            if not (y == h - 1 and x == w):
                raise ValueError(f"end of image at line {y}, column {x}: image not filled")
            return
        elif c == 1:
            pos += 1
            n = count()
            if n == 0:  # end of image
                if y != h:
                    raise ValueError(f"end of image at line {y}: image not filled")
                return
            if y == 0:
                raise ValueError("copy from the previous line in the first line")
            put(img[y - 1, x:x + n].copy(), n)
        else:
            n = count()
            need(3 * n)
            put(np.frombuffer(data[pos:pos + 3 * n], np.uint8).reshape(n, 3), n)
            pos += 3 * n


def split_controllers(image: np.ndarray, controllers: int) -> list[np.ndarray]:
    """A full-DMD image cut into the halves each controller of a dual-controller DMD receives (left first)."""
    return list(np.split(np.asarray(image), controllers, axis=1))


def join_controllers(parts) -> np.ndarray:
    return np.concatenate(list(parts), axis=1)
