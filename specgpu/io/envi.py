"""ENVI spectral cubes: a text header (``.hdr``) and raw data (``.img``), BSQ / BIL / BIP, ``wavelength`` in nm.

:func:`write_cube_envi` writes float32 little-endian data beside the header; :func:`read_cube_envi` reads every data
type, interleave and byte order the header declares and finds the data file as ENVI tools do
(:func:`envi_data_path`); bands come back ordered by wavelength.
"""

from __future__ import annotations

import base64
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.text import one_line
from specgpu.io.bands import check_cube, wavelength_order
from specgpu.io.metadata import _META_ATTRIBUTE, _metadata_from, _metadata_json
from specgpu.io.paths import atomic_path

__all__ = [
    "ENVI_DATA_TYPES", "ENVI_INTERLEAVES", "envi_data_path", "write_cube_envi", "read_envi_header",
    "read_cube_envi"
]

# ---- ENVI ----------------------------------------------------------------------------------------------------------
#: ENVI ``data type`` codes and their NumPy types (ENVI header reference: 1 byte, 2 int16, 3 int32, 4 float32,
#: 5 float64, 12 uint16, 13 uint32, 14 int64, 15 uint64).
ENVI_DATA_TYPES = {1: np.uint8, 2: np.int16, 3: np.int32, 4: np.float32, 5: np.float64, 12: np.uint16,
                   13: np.uint32, 14: np.int64, 15: np.uint64}
ENVI_INTERLEAVES = ("bsq", "bil", "bip")
_ENVI_TO_HWB = {"bsq": (1, 2, 0), "bil": (0, 2, 1), "bip": (0, 1, 2)}  # stored axes -> (H, W, B)
_ENVI_FROM_HWB = {"bsq": (2, 0, 1), "bil": (0, 2, 1), "bip": (0, 1, 2)}
_ENVI_UNITS_NM = {"nanometers": 1.0, "nanometer": 1.0, "nm": 1.0, "micrometers": 1e3, "micrometer": 1e3,
                  "microns": 1e3, "um": 1e3, "millimeters": 1e6, "mm": 1e6}


def envi_data_path(header) -> Path:
    """The data file of an ENVI header ``CUBE.hdr``: ``CUBE.img`` (what Spectral Python and ENVI look for)."""
    return Path(header).with_suffix(".img")


def _envi_data_candidates(path: Path, data_file: str | None = None) -> list[Path]:
    """The files an ENVI header's data may be in, in the order :func:`read_cube_envi` tries them."""
    return ([path.parent / data_file] if data_file else []) + [
        envi_data_path(path), path.with_suffix(".IMG"), path.with_suffix(".dat"), path.with_suffix(".raw"),
        path.with_suffix("")]


def write_cube_envi(path: str | os.PathLike[str], cube: ArrayLike, wavelengths: ArrayLike, *, interleave: str = "bsq",
                    metadata: dict | None = None) -> Path:
    """Write an (H, W, B) cube as ENVI: ``CUBE.hdr`` (text header) and ``CUBE.img`` (raw float32, little endian).

    The header names ``wavelength`` (nm, shortest exact decimals) and ``wavelength units = Nanometers``, so ENVI,
    Spectral Python (``spectral.envi.open``), QGIS / GDAL read the bands with their wavelengths. Both are written
    under temporary names first, then the data file is renamed and the header last: a header on disk always
    describes a whole data file, and a failed write replaces neither.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.hdr`` target.
    cube : array_like
        (H, W, B) values, stored as float32 (NaN kept).
    wavelengths : array_like
        (B,) nm, finite, > 0, unique.
    interleave : {"bsq", "bil", "bip"}
        Band sequential, band interleaved by line, band interleaved by pixel.
    metadata : mapping, optional
        JSON values, stored in the header as ``specgpu metadata`` (base64 JSON: ENVI values may not hold braces).
    """
    path = Path(path)
    if path.suffix.lower() != ".hdr":
        raise ValueError(f"{path}: an ENVI cube is written through its .hdr header")
    if str(interleave).lower() not in ENVI_INTERLEAVES:
        raise ValueError(f"{path}: unknown ENVI interleave {interleave!r}; valid: {', '.join(ENVI_INTERLEAVES)}")
    interleave = str(interleave).lower()
    arr, wl = check_cube(path, cube, wavelengths)
    meta = _metadata_json(path, metadata)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    h, w, b = arr.shape
    data = np.ascontiguousarray(np.transpose(np.asarray(arr, "<f4"), _ENVI_FROM_HWB[interleave]))
    lines = ["ENVI", "description = {specgpu spectral cube}", f"samples = {w}", f"lines = {h}", f"bands = {b}",
             "header offset = 0", "file type = ENVI Standard", "data type = 4", f"interleave = {interleave}",
             "byte order = 0", "wavelength units = Nanometers",
             "wavelength = {" + ", ".join(repr(float(v)) for v in wl) + "}"]
    if meta is not None:
        lines.append("specgpu metadata = " + base64.b64encode(meta.encode()).decode())
    with atomic_path(path) as header:  # both written before either is renamed: a failure replaces neither
        header.write_text("\n".join(lines) + "\n", encoding="ascii")
        with atomic_path(envi_data_path(path)) as tmp:
            with open(tmp, "wb") as fh:  # not ndarray.tofile: its short write carries no errno ("N requested and M
                fh.write(data.reshape(-1).view(np.uint8))  # written"), a plain write says "No space left on device"
    return path


def read_envi_header(path: str | os.PathLike[str]) -> dict:
    """Parse an ENVI header into a dict of lower-case keys to strings (``{...}`` values unwrapped, joined)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: ENVI header not found")
    try:
        text = path.read_text(encoding="latin-1")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the ENVI header ({one_line(str(exc))})") from None
    if not text.lstrip().startswith("ENVI"):
        raise ValueError(f"{path}: not an ENVI header (the first line must be 'ENVI')")
    fields, key, buf = {}, None, []
    for raw in text.splitlines()[1:]:
        if key is not None:
            buf.append(raw)
            if "}" in raw:
                fields[key] = " ".join(buf).strip()[1:].rsplit("}", 1)[0].strip()
                key = None
            continue
        if not raw.strip() or raw.lstrip().startswith(";"):
            continue
        if "=" not in raw:
            raise ValueError(f"{path}: bad ENVI header line {raw.strip()[:60]!r} (expected 'key = value')")
        k, v = (s.strip() for s in raw.split("=", 1))
        if v.startswith("{") and "}" not in v:
            key, buf = k.lower(), [v]
        else:
            fields[k.lower()] = v[1:].rsplit("}", 1)[0].strip() if v.startswith("{") else v
    if key is not None:
        raise ValueError(f"{path}: ENVI header value of {key!r} opens '{{' and never closes it")
    return fields


def read_cube_envi(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read an ENVI cube (``.hdr`` + data file) into (H, W, B) float32, bands by increasing wavelength.

    Accepts every interleave, byte order and numeric ``data type``, a header offset, and wavelengths in nm or
    micrometres. The data file is ``CUBE.img`` (or the header's ``data file`` entry, or ``CUBE`` with no suffix).

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming the file: no header or data file, a malformed header, a data file whose size is not
        what the header describes, no or bad wavelengths, unknown data type, interleave or units.
    """
    path = Path(path)
    fields = read_envi_header(path)

    def integer(key, default=None, low=0):
        value = fields.get(key, default)
        try:
            n = int(str(value))
        except (TypeError, ValueError):
            raise ValueError(f"{path}: ENVI header '{key}' must be an integer, got {value!r}") from None
        if n < low:
            raise ValueError(f"{path}: ENVI header '{key}' must be >= {low}, got {n}")
        return n

    w, h, b = integer("samples", low=1), integer("lines", low=1), integer("bands", low=1)
    offset = integer("header offset", 0)
    code = integer("data type")
    if code not in ENVI_DATA_TYPES:
        raise ValueError(f"{path}: unsupported ENVI data type {code}; supported: "
                         f"{', '.join(map(str, ENVI_DATA_TYPES))}")
    interleave = str(fields.get("interleave", "bsq")).lower()
    if interleave not in ENVI_INTERLEAVES:
        raise ValueError(f"{path}: unknown ENVI interleave {interleave!r}; valid: {', '.join(ENVI_INTERLEAVES)}")
    order = integer("byte order", 0)
    if order not in (0, 1):
        raise ValueError(f"{path}: ENVI 'byte order' must be 0 or 1, got {order}")
    if "wavelength" not in fields:
        raise ValueError(f"{path}: the ENVI header has no 'wavelength' list (not a spectral cube with wavelengths)")
    try:
        wl = np.array([float(v) for v in fields["wavelength"].split(",")], np.float64)
    except ValueError:
        raise ValueError(f"{path}: ENVI 'wavelength' must be a list of numbers") from None
    if wl.size != b:
        raise ValueError(f"{path}: ENVI header lists {wl.size} wavelengths for {b} bands")
    units = str(fields.get("wavelength units", "Nanometers")).strip().lower()
    if units not in _ENVI_UNITS_NM:
        raise ValueError(f"{path}: unknown ENVI 'wavelength units' {fields['wavelength units']!r}; expected "
                         "Nanometers or Micrometers")
    wl = wl * _ENVI_UNITS_NM[units]
    dtype = np.dtype(ENVI_DATA_TYPES[code]).newbyteorder(">" if order else "<")
    candidates = _envi_data_candidates(path, fields.get("data file"))
    data_path = next((p for p in candidates if p.is_file() and p != path), None)
    if data_path is None:
        raise FileNotFoundError(f"{path}: the ENVI data file {envi_data_path(path).name} is missing")
    expected = offset + h * w * b * dtype.itemsize
    size = data_path.stat().st_size
    if size != expected:
        raise ValueError(f"{path}: data file {data_path.name} holds {size} bytes but the header describes "
                         f"{expected} ({h} lines x {w} samples x {b} bands of {dtype.itemsize}-byte data type {code}"
                         f"{f' after a {offset}-byte offset' if offset else ''})")
    stored = np.fromfile(data_path, dtype=dtype, count=h * w * b, offset=offset)
    shape = {"bsq": (b, h, w), "bil": (h, b, w), "bip": (h, w, b)}[interleave]
    cube = np.ascontiguousarray(np.transpose(stored.reshape(shape), _ENVI_TO_HWB[interleave])).astype(np.float32)
    order_wl = wavelength_order(path, wl)
    wl = wl[order_wl]
    meta = {}
    if "specgpu metadata" in fields:
        try:
            text = base64.b64decode(fields["specgpu metadata"], validate=True).decode()
        except (ValueError, UnicodeDecodeError):
            raise ValueError(f"{path}: ENVI 'specgpu metadata' is not base64 JSON") from None
        meta = _metadata_from(path, {_META_ATTRIBUTE: text})
    return cube[..., order_wl], wl, meta
