"""The file formats of specgpu, through OpenImageIO.

=====================  ===========================================================================================
spectral cube          OpenEXR, JCGT 2021 spectral layout (Fichet, Pacanowski, Wilkie): one channel per band named
                       ``T.<wavelength><unit>`` (``T.550,000000nm``), float32 or half, ``spectralLayoutVersion``
                       ``"1.0"`` in the header; or ``.npz`` with ``wavelengths`` (B,) and ``reflectance`` (H, W, B);
                       or ENVI (``.hdr`` header + ``.img`` raw data, BSQ / BIL / BIP, ``wavelength`` in nm).
                       :func:`write_cube`, :func:`read_cube` (by extension).
map                    OpenEXR with named channels: ``X,Y,Z`` (XYZ), ``L,a,b`` (CIELAB), one channel for a colour
                       difference (``dE76``, ``dE94``, ``dE2000``) or any names given. :func:`write_map`,
                       :func:`read_map`.
preview                8-bit sRGB PNG from XYZ (colour-science's ``XYZ_to_sRGB``, clipped, with an exposure) and
                       a colour-difference heat map PNG (perceptual colormap; scale in the PNG text metadata).
                       :func:`write_sRGB_preview`, :func:`write_delta_E_png`, :func:`read_png`.
frame sequence         a folder with 16-bit TIFF frames and ``sequence.json`` (format ``specgpu.sequence``,
                       version 1): per frame its file, frame id, pattern index, exposure, timestamp, size and
                       SHA-256, plus the plan hash. :func:`write_sequence`, :func:`read_sequence`,
                       :func:`read_sequence_header`, :func:`validate_sequence_document`.
=====================  ===========================================================================================

JCGT 2021 channel names (the paper's Section 3 and its reference code, ``afichet/spectral-exr``,
``EXRSpectralImage::channelType``; colour-science's ``colour.io.fichet2021`` follows the same grammar): a
reflective channel is ``T.`` + a number + an optional SI prefix (``Y Z E P T G M k h da d c m u n p``) + a unit,
``m`` (wavelength) or ``Hz`` (frequency). The number's decimal separator is a **comma**, because ``.`` separates
layers in OpenEXR channel names; the reference writer prints six decimals (``T.550,000000nm``). specgpu writes
that form (or the shortest exact decimals when six are not enough, so every float64 wavelength survives the
round trip) and reads every form of the grammar, plus a ``.`` separator (``T.405.5nm``) for files from tools that
use one. Emissive (``S0.*``), bi-spectral (``T.<wl>.<wl>``) and RGB channels are ignored by the cube reader.
Readers order bands by wavelength, never by channel order (OpenEXR itself stores channels sorted by name, so
``T.1000,000000nm`` comes before ``T.400,000000nm`` in every file).

Writes never leave a partial file under the final name: files go to a temporary name in the same folder and are
renamed with :func:`os.replace` when complete; a sequence folder gets its ``sequence.json`` last, the same way, so
a folder without one is an incomplete capture and readers refuse it. Every error on bad input is one line, a
:class:`FileNotFoundError` or :class:`ValueError` that starts with the offending file's path.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from specgpu.io import formats
from specgpu.io.formats import (SPECTRAL_LAYOUT_VERSION, atomic_path, format_channel, one_line, parse_channel,
                             read_cube_exr, read_cube_npz, read_exr, write_cube_exr, write_cube_npz, write_exr)

__all__ = [
    "format_channel", "parse_channel", "write_cube", "read_cube", "MAP_KINDS", "write_map", "read_map",
    "write_sRGB_preview", "write_delta_E_png", "read_png", "PERCEPTUAL_COLORMAPS",
    "SEQUENCE_FORMAT", "SEQUENCE_VERSION", "SEQUENCE_FILE", "write_sequence", "SequenceWriter", "read_sequence",
    "read_sequence_header", "validate_sequence_document", "JOURNAL_FILE", "salvage_sequence", "SPECTRAL_LAYOUT_VERSION",
    "write_cube_envi", "read_cube_envi", "read_envi_header", "ENVI_INTERLEAVES",
    "verify_journal", "journal_header", "companion_files",
]

_META_ATTRIBUTE = "specgpu:metadata"  # header attribute holding the caller's metadata as JSON (exact floats)


# ---- metadata ------------------------------------------------------------------------------------------------------
def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def _metadata_json(path, metadata) -> str | None:
    if metadata is None:
        return None
    if not isinstance(metadata, Mapping):
        raise ValueError(f"{path}: metadata must be a mapping of str to JSON values, got {type(metadata).__name__}")
    try:
        return json.dumps(dict(metadata), default=_json_default, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: metadata must be JSON-serialisable with finite numbers "
                         f"({one_line(str(exc))})") from None


def _metadata_from(path, attributes: dict) -> dict:
    text = attributes.get(_META_ATTRIBUTE)
    if text is None:
        return {}
    try:
        meta = json.loads(text)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: header attribute {_META_ATTRIBUTE!r} is not valid JSON "
                         f"({one_line(str(exc))})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: header attribute {_META_ATTRIBUTE!r} must hold a JSON object")
    return meta


# ---- spectral cubes ------------------------------------------------------------------------------------------------
def _suffix(path: Path, allowed: tuple[str, ...], what: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in allowed:
        raise ValueError(f"{path}: unknown {what} format {suffix!r}; expected {' or '.join(allowed)}")
    return suffix


def write_cube(path, cube, wavelengths, *, half: bool = False, metadata=None, interleave: str = "bsq") -> Path:
    """Write a spectral cube: OpenEXR in the JCGT 2021 layout (``.exr``), ``.npz`` or ENVI (``.hdr`` + ``.img``,
    :func:`write_cube_envi`; ``interleave`` ``"bsq"``, ``"bil"`` or ``"bip"``).

    Parameters
    ----------
    path : str or os.PathLike
        Target file, ``.exr`` or ``.npz``; its folder must exist. Written atomically.
    cube : array_like
        (H, W, B) values (reflectance: domain [0, 1], up to 1.5 for fluorescent whites; any float is stored),
        band b at ``wavelengths[b]``. NaN pixels are stored as NaN.
    wavelengths : array_like
        (B,) wavelengths in nm, finite, > 0, unique, in any order (one ``T.<wl>nm`` channel each).
    half : bool
        EXR only: store half floats (11 significant bits, relative error <= 2**-11, max 65504) instead of float32.
    metadata : mapping, optional
        JSON-serialisable values (NumPy scalars and arrays are converted), stored exactly: as the JSON header
        attribute ``specgpu:metadata`` in EXR, as the ``metadata`` array (JSON text) in npz.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        One line naming the file: unknown suffix, wrong shape, NaN / non-positive / duplicate wavelengths,
        metadata that is not JSON.
    """
    path = Path(path)
    suffix = _suffix(path, (".exr", ".npz", ".hdr"), "spectral cube")
    if suffix == ".hdr":
        if half:
            raise ValueError(f"{path}: ENVI has no half-float data type; write the cube without --half")
        return write_cube_envi(path, cube, wavelengths, interleave=interleave, metadata=metadata)
    meta = _metadata_json(path, metadata)
    if suffix == ".npz":
        extra = {} if meta is None else {"metadata": np.array(meta)}
        return write_cube_npz(path, np.asarray(cube, dtype=np.float32), wavelengths, extra)
    attrs = {} if meta is None else {_META_ATTRIBUTE: meta}
    return write_cube_exr(path, cube, wavelengths, half=half, attributes=attrs)


def read_cube(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read a spectral cube written by specgpu or any JCGT 2021 writer (or an ``.npz`` cube).

    Parameters
    ----------
    path : str or os.PathLike
        ``.exr``, ``.npz`` or ENVI ``.hdr`` file.

    Returns
    -------
    cube : numpy.ndarray
        (H, W, B) float32, bands ordered by increasing wavelength (half files widened exactly).
    wavelengths : numpy.ndarray
        (B,) float64, nm, strictly increasing.
    metadata : dict
        What :func:`write_cube` stored (empty for files from other writers).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        One line naming the file: unknown suffix, unreadable / truncated / corrupt file, no ``T.<wl>nm``
        channels, duplicate or degenerate wavelengths, NaN wavelengths, wrong shapes, bad metadata.
    """
    path = Path(path)
    suffix = _suffix(path, (".exr", ".npz", ".hdr"), "spectral cube")
    if suffix == ".hdr":
        return read_cube_envi(path)
    if suffix == ".npz":
        cube, wl, extra = read_cube_npz(path)
        meta = {}
        if "metadata" in extra:
            meta = _metadata_from(path, {_META_ATTRIBUTE: str(extra["metadata"])})
        try:
            cube = np.asarray(cube, dtype=np.float32)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: reflectance must be numeric, got dtype {cube.dtype}") from None
        return cube, wl, meta
    cube, wl, attributes = read_cube_exr(path)
    return cube, wl, _metadata_from(path, attributes)


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


def companion_files(path) -> list[Path]:
    """The files that go with ``path`` and are read or written with it: for an ENVI header (``.hdr``), the data
    file written beside it (``CUBE.img``) and every file its reader would take the data from (the header's ``data
    file`` entry, ``CUBE.IMG``, ``.dat``, ``.raw``, ``CUBE``) that exists; nothing for other files.

    A command treats them as its inputs and outputs too: an output that is an input's data file would destroy that
    input, and a writer of ``CUBE.hdr`` holds the lock of ``CUBE.img`` as well."""
    path = Path(path)
    if path.suffix.lower() != ".hdr":
        return []
    data_file = None
    try:
        data_file = read_envi_header(path).get("data file") if path.is_file() else None
    except (OSError, ValueError):
        pass
    found = [p for p in _envi_data_candidates(path, data_file) if p != path and p.is_file()]
    return list(dict.fromkeys([envi_data_path(path), *found]))


def write_cube_envi(path, cube, wavelengths, *, interleave: str = "bsq", metadata=None) -> Path:
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
    import base64

    path = Path(path)
    if path.suffix.lower() != ".hdr":
        raise ValueError(f"{path}: an ENVI cube is written through its .hdr header")
    if str(interleave).lower() not in ENVI_INTERLEAVES:
        raise ValueError(f"{path}: unknown ENVI interleave {interleave!r}; valid: {', '.join(ENVI_INTERLEAVES)}")
    interleave = str(interleave).lower()
    arr, wl = formats.check_cube(path, cube, wavelengths)
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


def read_envi_header(path) -> dict:
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


def read_cube_envi(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read an ENVI cube (``.hdr`` + data file) into (H, W, B) float32, bands by increasing wavelength.

    Accepts every interleave, byte order and numeric ``data type``, a header offset, and wavelengths in nm or
    micrometres. The data file is ``CUBE.img`` (or the header's ``data file`` entry, or ``CUBE`` with no suffix).

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming the file: no header or data file, a malformed header, a data file whose size is not
        what the header describes, no or bad wavelengths, unknown data type, interleave or units.
    """
    import base64

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
    order_wl = formats.wavelength_order(path, wl)
    wl = wl[order_wl]
    meta = {}
    if "specgpu metadata" in fields:
        try:
            text = base64.b64decode(fields["specgpu metadata"], validate=True).decode()
        except (ValueError, UnicodeDecodeError):
            raise ValueError(f"{path}: ENVI 'specgpu metadata' is not base64 JSON") from None
        meta = _metadata_from(path, {_META_ATTRIBUTE: text})
    return cube[..., order_wl], wl, meta


# ---- maps ----------------------------------------------------------------------------------------------------------
#: Map kind -> channel names, in the order of the last axis of the array.
MAP_KINDS = {
    "XYZ": ("X", "Y", "Z"),
    "Lab": ("L", "a", "b"),
    "dE76": ("dE76",),
    "dE94": ("dE94",),
    "dE2000": ("dE2000",),
}


def _channels_of(kind, path) -> tuple[str, ...]:
    if isinstance(kind, str):
        if kind not in MAP_KINDS:
            raise ValueError(f"{path}: unknown map kind {kind!r}; valid kinds: {', '.join(MAP_KINDS)} "
                             "(or a tuple of channel names)")
        return MAP_KINDS[kind]
    names = tuple(str(n) for n in kind)
    if not names or len(set(names)) != len(names) or any(not n for n in names):
        raise ValueError(f"{path}: map channel names must be unique non-empty strings, got {names}")
    return names


def write_map(path, data, kind, *, half: bool = False, metadata=None) -> Path:
    """Write an XYZ, Lab or colour-difference map (or any named channels) as OpenEXR, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        ``.exr`` target.
    data : array_like
        (H, W, C) values, or (H, W) for a single channel. XYZ: domain [0, 1] with Y = 1 for the perfect
        diffuser; Lab: L* in [0, 100]; dE: >= 0. NaN pixels are kept.
    kind : str or sequence of str
        A name of :data:`MAP_KINDS` (``"XYZ"``, ``"Lab"``, ``"dE76"``, ``"dE94"``, ``"dE2000"``) or the C
        channel names.
    half : bool
        Store half floats instead of float32.
    metadata : mapping, optional
        JSON-serialisable values, stored exactly (header attribute ``specgpu:metadata``).

    Returns
    -------
    pathlib.Path
    """
    path = Path(path)
    _suffix(path, (".exr",), "map")
    names = _channels_of(kind, path)
    arr = np.asarray(data, dtype=np.float32)
    if arr.ndim == 2 and len(names) == 1:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] != len(names):
        raise ValueError(f"{path}: a {'/'.join(names)} map must have shape (H, W, {len(names)}), got {arr.shape}")
    meta = _metadata_json(path, metadata)
    return write_exr(path, arr, names, half=half, attributes={} if meta is None else {_META_ATTRIBUTE: meta})


def read_map(path, kind=None) -> tuple[np.ndarray, tuple[str, ...], dict]:
    """Read a map written by :func:`write_map` (or any OpenEXR file).

    Parameters
    ----------
    path : str or os.PathLike
        ``.exr`` file.
    kind : str or sequence of str, optional
        Expected kind (see :data:`MAP_KINDS`) or channel names: the result holds exactly those channels in that
        order. None: a file whose channels are a known kind comes back in that kind's order, any other in the
        file's order.

    Returns
    -------
    data : numpy.ndarray
        (H, W, C) float32.
    channels : tuple of str
        The C channel names.
    metadata : dict
        What :func:`write_map` stored.

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming the file: unreadable, truncated or corrupt file, channels that are not the expected set.
    """
    path = Path(path)
    _suffix(path, (".exr",), "map")
    data, names, attributes = read_exr(path, "map")
    if kind is None:
        wanted = next((ch for ch in MAP_KINDS.values() if set(ch) == set(names)), tuple(names))
    else:
        wanted = _channels_of(kind, path)
        missing = [n for n in wanted if n not in names]
        if missing:
            label = kind if isinstance(kind, str) else "/".join(wanted)
            raise ValueError(f"{path}: not a {label} map: expected channels {', '.join(wanted)}, "
                             f"found {', '.join(names[:8])}{', ...' if len(names) > 8 else ''}")
    index = [names.index(n) for n in wanted]
    return np.ascontiguousarray(data[..., index]), tuple(wanted), _metadata_from(path, attributes)


# ---- previews ------------------------------------------------------------------------------------------------------
#: Perceptually uniform matplotlib colormaps accepted for heat maps.
PERCEPTUAL_COLORMAPS = ("magma", "inferno", "viridis", "plasma", "cividis")


def _write_png(path: Path, rgb8: np.ndarray, attributes: dict) -> Path:
    import OpenImageIO as oiio

    h, w, c = rgb8.shape
    spec = oiio.ImageSpec(w, h, c, "uint8")
    spec.attribute("oiio:ColorSpace", "sRGB")
    for key, value in attributes.items():
        spec.attribute(key, str(value))
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    return formats.write_image(path, rgb8, spec, "png", "PNG")


def _auto_exposure_ev(Y: np.ndarray, percentile: float = 99.0) -> float:
    finite = Y[np.isfinite(Y)]
    level = float(np.percentile(finite, percentile)) if finite.size else 0.0
    return 0.0 if level <= 0 else -math.log2(level)


def write_sRGB_preview(path, XYZ, *, exposure="auto", illuminant=None, metadata=None) -> Path:
    """Write an 8-bit sRGB PNG rendering of an XYZ map.

    Parameters
    ----------
    path : str or os.PathLike
        ``.png`` target, written atomically.
    XYZ : array_like
        (H, W, 3) tristimulus values, domain [0, 1] with Y = 1 for the perfect diffuser (colour-science's
        reference scale). NaN pixels render black.
    exposure : float or "auto"
        Exposure in stops (EV): the image is ``XYZ * 2**exposure`` before encoding. ``"auto"`` picks the EV that
        brings the 99th percentile of Y to 1 (specular outliers clip, the rest is not crushed); 0 shows the
        values as they are (a perfect white at code 255).
    illuminant : array_like, optional
        CIE xy chromaticity of the XYZ white (e.g. illuminant A's (0.44758, 0.40745)); the rendering is
        chromatically adapted (CAT02) from it to sRGB's D65 white. None: the XYZ is already relative to D65.
    metadata : mapping, optional
        Extra PNG text entries (str keys; values written as text).

    Returns
    -------
    pathlib.Path
        ``path``; the PNG text holds ``specgpu:exposure_EV`` (the exposure applied).
    """
    import colour

    path = Path(path)
    _suffix(path, (".png",), "preview")
    arr = np.asarray(XYZ, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"{path}: XYZ must have shape (H, W, 3), got {arr.shape}")
    if isinstance(exposure, str):
        if exposure != "auto":
            raise ValueError(f"{path}: exposure must be a number of stops or 'auto', got {exposure!r}")
        ev = _auto_exposure_ev(arr[..., 1])
    else:
        ev = float(exposure)
        if not math.isfinite(ev):
            raise ValueError(f"{path}: exposure must be finite, got {exposure!r}")
    kwargs = {}
    if illuminant is not None:
        kwargs["illuminant"] = np.asarray(illuminant, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        rgb = colour.XYZ_to_sRGB(np.nan_to_num(arr * 2.0 ** ev, nan=0.0, posinf=0.0, neginf=0.0), **kwargs)
    rgb8 = np.round(np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    attrs = {"specgpu:exposure_EV": repr(ev), "ImageDescription": f"sRGB preview of XYZ, exposure {ev:+.3f} EV"}
    attrs.update({str(k): v for k, v in (metadata or {}).items()})
    return _write_png(path, rgb8, attrs)


def write_delta_E_png(path, delta_E, *, vmax=None, colormap: str = "magma", quantity: str = "dE2000",
                      metadata=None) -> Path:
    """Write a colour-difference map as a heat-map PNG with a perceptually uniform colormap.

    Parameters
    ----------
    path : str or os.PathLike
        ``.png`` target, written atomically.
    delta_E : array_like
        (H, W) or (H, W, 1) colour differences, >= 0. NaN pixels render mid grey.
    vmax : float, optional
        dE mapped to the top of the colormap (larger values clip); default the largest finite value (1 if none
        is positive). The bottom is 0.
    colormap : str
        One of :data:`PERCEPTUAL_COLORMAPS` (matplotlib's).
    quantity : str
        Name of the difference for the metadata (``"dE2000"``, ``"dE76"`` ...).
    metadata : mapping, optional
        Extra PNG text entries.

    Returns
    -------
    pathlib.Path
        ``path``; the PNG text holds the scale: ``specgpu:quantity``, ``specgpu:colormap``, ``specgpu:vmin``
        (0), ``specgpu:vmax``, and a readable ``ImageDescription``.
    """
    import matplotlib

    path = Path(path)
    _suffix(path, (".png",), "heat map")
    if colormap not in PERCEPTUAL_COLORMAPS:
        raise ValueError(f"{path}: unknown colormap {colormap!r}; valid colormaps: {', '.join(PERCEPTUAL_COLORMAPS)}")
    arr = np.asarray(delta_E, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise ValueError(f"{path}: delta_E must have shape (H, W) or (H, W, 1), got {arr.shape}")
    finite = np.isfinite(arr)
    if vmax is None:
        top = float(arr[finite].max()) if finite.any() else 0.0
        vmax = top if top > 0 else 1.0
    vmax = float(vmax)
    if not math.isfinite(vmax) or vmax <= 0:
        raise ValueError(f"{path}: vmax must be finite and > 0, got {vmax!r}")
    lut = np.round(matplotlib.colormaps[colormap](np.linspace(0.0, 1.0, 256))[:, :3] * 255.0).astype(np.uint8)
    index = np.round(np.clip(np.where(finite, arr, 0.0) / vmax, 0.0, 1.0) * 255.0).astype(np.intp)
    rgb8 = lut[index]
    rgb8[~finite] = 128
    attrs = {"specgpu:quantity": quantity, "specgpu:colormap": colormap, "specgpu:vmin": "0",
             "specgpu:vmax": repr(vmax),
             "ImageDescription": f"{quantity} heat map, colormap {colormap}, 0 -> {vmax:g} (clipped above, NaN grey)"}
    attrs.update({str(k): v for k, v in (metadata or {}).items()})
    return _write_png(path, rgb8, attrs)


def read_png(path) -> tuple[np.ndarray, dict]:
    """Read an 8-bit PNG: (H, W, C) uint8 pixels and its text metadata (name -> str)."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: PNG not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: cannot open PNG ({one_line(oiio.geterror())})")
    try:
        spec = inp.spec()
        data = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
        err = inp.geterror()
        if data is None or err:
            raise ValueError(f"{path}: truncated or corrupt PNG ({one_line(err or 'no pixel data')})")
        meta = {a.name: a.value for a in spec.extra_attribs}
    finally:
        inp.close()
    return data.reshape(spec.height, spec.width, spec.nchannels), meta


# ---- frame sequences -----------------------------------------------------------------------------------------------
SEQUENCE_FORMAT = "specgpu.sequence"
SEQUENCE_VERSION = 1
SEQUENCE_FILE = "sequence.json"
_FRAME_NAME = "frame_{:06d}.tif"
_FRAME_RE = re.compile(r"^frame_\d{6,}\.tif$")
_RECORD_FIELDS = ("frame_id", "pattern_index", "exposure_s", "timestamp_s")


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def validate_sequence_document(doc, path="sequence.json") -> dict:
    """Check a parsed ``sequence.json`` and return it normalized (plain Python ints, floats and strings).

    The document (format ``specgpu.sequence``, version 1)::

        {"format": "specgpu.sequence", "version": 1, "plan_hash": str (non-empty),
         "height": int >= 1, "width": int >= 1, "dtype": "uint16",
         "frames": [{"file": "frame_000000.tif", "frame_id": int >= 0 (strictly increasing),
                     "pattern_index": int >= 0, "exposure_s": float > 0, "timestamp_s": finite float (s),
                     "bytes": int >= 0, "sha256": 64 hex digits}, ...]  (at least one; files unique plain names),
         "n_frames": len(frames) (optional), "metadata": {...}  (optional JSON object)}

    Extra keys in a frame record are kept (a newer writer's additions), so are unknown top-level keys.

    Raises
    ------
    ValueError
        One line that starts with ``path`` and names the field, e.g.
        ``"seq/sequence.json: frames[3].frame_id must be an integer >= 0, got -1"``.
    """
    where = str(path)

    def fail(msg):
        raise ValueError(f"{where}: {msg}")

    if not isinstance(doc, dict):
        fail(f"must hold a JSON object, got {type(doc).__name__}")
    if doc.get("format") != SEQUENCE_FORMAT:
        fail(f"not a specgpu frame sequence (format {doc.get('format')!r}, expected {SEQUENCE_FORMAT!r})")
    version = doc.get("version")
    if not _is_int(version):
        fail(f"version must be an integer, got {version!r}")
    if version != SEQUENCE_VERSION:
        fail(f"unknown format version {version} (this specgpu reads version {SEQUENCE_VERSION})")
    plan_hash = doc.get("plan_hash")
    if not isinstance(plan_hash, str) or not plan_hash:
        fail(f"plan_hash must be a non-empty string, got {plan_hash!r}")
    dims = {}
    for key in ("height", "width"):
        v = doc.get(key)
        if not _is_int(v) or v < 1:
            fail(f"{key} must be an integer >= 1, got {v!r}")
        dims[key] = int(v)
    if doc.get("dtype") != "uint16":
        fail(f"dtype must be 'uint16', got {doc.get('dtype')!r}")
    metadata = doc.get("metadata", {})
    if not isinstance(metadata, dict):
        fail(f"metadata must be a JSON object, got {type(metadata).__name__}")
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        fail("frames must be a non-empty list")
    if "n_frames" in doc and (not _is_int(doc["n_frames"]) or doc["n_frames"] != len(frames)):
        fail(f"n_frames is {doc['n_frames']!r} but {len(frames)} frame(s) are listed")
    records, files, last_id = [], set(), -1
    for i, rec in enumerate(frames):
        at = f"frames[{i}]"
        if not isinstance(rec, dict):
            fail(f"{at} must be an object, got {type(rec).__name__}")
        missing = [k for k in ("file", *_RECORD_FIELDS, "bytes", "sha256") if k not in rec]
        if missing:
            fail(f"{at} lacks {', '.join(missing)}")
        name = rec["file"]
        if not isinstance(name, str) or not name or name != Path(name).name or name in (".", "..") or "\\" in name:
            fail(f"{at}.file must be a plain file name inside the folder, got {name!r}")
        if name in files:
            fail(f"{at}.file {name!r} is listed twice")
        files.add(name)
        fid = rec["frame_id"]
        if not _is_int(fid) or fid < 0:
            fail(f"{at}.frame_id must be an integer >= 0, got {fid!r}")
        if fid <= last_id:
            fail(f"{at}.frame_id {fid} must be greater than the previous frame's {last_id} (capture order)")
        last_id = int(fid)
        pat = rec["pattern_index"]
        if not _is_int(pat) or pat < 0:
            fail(f"{at}.pattern_index must be an integer >= 0, got {pat!r}")
        exp = rec["exposure_s"]
        if not _is_number(exp) or not math.isfinite(exp) or exp <= 0:
            fail(f"{at}.exposure_s must be a finite number > 0 (s), got {exp!r}")
        ts = rec["timestamp_s"]
        if not _is_number(ts) or not math.isfinite(ts):
            fail(f"{at}.timestamp_s must be a finite number (s), got {ts!r}")
        size = rec["bytes"]
        if not _is_int(size) or size < 0:
            fail(f"{at}.bytes must be an integer >= 0, got {size!r}")
        digest = rec["sha256"]
        if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-f]{64}", digest):
            fail(f"{at}.sha256 must be 64 lowercase hex digits, got {digest!r}")
        out = dict(rec)
        out.update(file=name, frame_id=int(fid), pattern_index=int(pat), exposure_s=float(exp),
                   timestamp_s=float(ts), bytes=int(size), sha256=digest)
        records.append(out)
    result = dict(doc)
    result.update(version=int(version), plan_hash=plan_hash, dtype="uint16", metadata=metadata, frames=records,
                  **dims)
    return result


def _record_of(rec, i: int, directory: Path) -> dict:
    """One capture record (a mapping or an object such as capture.driver.FrameInfo) as plain data."""
    if isinstance(rec, Mapping):
        get = rec.get
    else:
        def get(key, default=None):
            return getattr(rec, key, default)
    out = {}
    for key in _RECORD_FIELDS:
        v = get(key)
        if v is None:
            raise ValueError(f"{directory}: record {i} lacks {key} (records need {', '.join(_RECORD_FIELDS)})")
        out[key] = v.item() if isinstance(v, np.generic) else v
    return out


def _frame_array(frame, i: int, directory: Path, shape) -> np.ndarray:
    arr = np.asarray(frame)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{directory}: frame {i} must have shape (H, W), got {arr.shape}")
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{directory}: frame {i} has shape {arr.shape}, the first frame {shape}")
    if arr.dtype != np.uint16:
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{directory}: frame {i} must be uint16 (16-bit DN), got dtype {arr.dtype}")
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise ValueError(f"{directory}: frame {i} values must lie in 0-65535, got {arr.min()}-{arr.max()}")
        arr = arr.astype(np.uint16)
    return np.ascontiguousarray(arr[..., None])


def _write_tiff(path: Path, frame: np.ndarray) -> tuple[int, str]:
    import OpenImageIO as oiio

    h, w, _ = frame.shape
    spec = oiio.ImageSpec(w, h, 1, "uint16")
    spec.attribute("compression", "zip")
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create("tiff")
        if out is None or not out.open(str(tmp), spec):
            raise formats.write_failed(path, tmp, "TIFF", oiio.geterror())
        try:
            if not out.write_image(frame):  # a full disk: "TIFFWriteScanline failed", its cause found here
                raise formats.write_failed(path, tmp, "TIFF", out.geterror())
        finally:
            closed = out.close()
        if not closed:
            raise formats.write_failed(path, tmp, "TIFF", out.geterror() or oiio.geterror() or "closing it failed")
        raw = tmp.read_bytes()
    return len(raw), hashlib.sha256(raw).hexdigest()


def write_sequence(directory, frames, records=None, plan_hash: str = "", *, metadata=None,
                   overwrite: bool = False) -> Path:
    """Write a captured frame sequence: 16-bit TIFF frames and ``sequence.json``, the JSON last.

    Parameters
    ----------
    directory : str or os.PathLike
        Target folder (created if needed).
    frames : array_like or iterable
        (N, H, W) uint16 frames (DN), or an iterable of (H, W) frames (written as they come, e.g. from the
        assembler), or a :class:`specgpu.capture.assemble.Sequence` (its records are used when ``records`` is
        None). Other integer dtypes are accepted when their values fit 0-65535.
    records : sequence
        One per frame, in capture order: mappings or objects (e.g. :class:`specgpu.capture.driver.FrameInfo`)
        with ``frame_id`` (int >= 0, increasing), ``pattern_index`` (int >= 0), ``exposure_s`` (s, > 0) and
        ``timestamp_s`` (s) — what ``Sequence.frame_records()`` returns.
    plan_hash : str
        Hash of the plan the capture ran (a capture records its plan's hash).
    metadata : mapping, optional
        JSON-serialisable extras (rig, scene, ...), stored under ``"metadata"``.
    overwrite : bool
        Replace a complete sequence already in ``directory``: its ``sequence.json`` is removed first, so the
        folder never looks complete while it is rewritten (the old sequence is gone from then on, even if this
        write fails). Leftover ``frame_*.tif`` of an interrupted write (no ``sequence.json``) are always
        replaced.

    Returns
    -------
    pathlib.Path
        The folder.

    Raises
    ------
    FileExistsError
        ``directory`` already holds a sequence and ``overwrite`` is False.
    ValueError
        One line naming the folder: frames of different shapes or non-16-bit values, a record count that does
        not match the frames, invalid records or plan hash. Frames written by this call are removed and no
        ``sequence.json`` is written.
    """
    directory = Path(directory)
    if hasattr(frames, "frame_records") and hasattr(frames, "frames"):  # a capture.assemble.Sequence
        records = frames.frame_records() if records is None else records
        frames = frames.frames
    if records is None:
        raise ValueError(f"{directory}: records are required (frame_id, pattern_index, exposure_s, timestamp_s)")
    _check_plan_hash(directory, plan_hash)
    meta_text = _metadata_json(directory, metadata)
    records = [_record_of(r, i, directory) for i, r in enumerate(records)]
    if records:  # check the records before any pixel is written (placeholders for what the frames will give)
        validate_sequence_document(
            {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": plan_hash, "height": 1,
             "width": 1, "dtype": "uint16",
             "frames": [{"file": _FRAME_NAME.format(i), **r, "bytes": 0, "sha256": "0" * 64}
                        for i, r in enumerate(records)]}, directory / SEQUENCE_FILE)
    writer = SequenceWriter(directory, plan_hash, overwrite=overwrite)
    try:
        for i, frame in enumerate(frames):
            if i >= len(records):
                raise ValueError(f"{directory}: more frames than records ({len(records)})")
            writer.add(frame, records[i])
        if writer.n_frames != len(records):
            raise ValueError(f"{directory}: {writer.n_frames} frame(s) but {len(records)} record(s)")
        return writer.close(None if meta_text is None else json.loads(meta_text))
    except BaseException:
        writer.abort()
        raise


def _check_plan_hash(directory: Path, plan_hash) -> None:
    if not isinstance(plan_hash, str) or not plan_hash:
        raise ValueError(f"{directory}: plan_hash must be a non-empty string, got {plan_hash!r}")


class SequenceWriter:
    """Write a frame sequence one frame at a time (a long capture never holds its frames in memory):
    :meth:`add` each frame with its record as it arrives, then :meth:`close` writes ``sequence.json``, last;
    :meth:`abort` removes the frames written. Until :meth:`close` returns, the folder never reads as complete.

    With ``journal``, :meth:`commit` appends the records of the frames added since the last commit to
    :data:`JOURNAL_FILE` and syncs it (a capture commits each complete sequence), so a process killed before
    :meth:`close` leaves its frames indexed: :func:`salvage_sequence` turns them into a readable sequence.

    Parameters
    ----------
    directory, plan_hash, overwrite
        As :func:`write_sequence`; the folder checks (not a folder, a sequence already there) happen here,
        before any frame is written, and leftover frames of an interrupted write are removed.
    journal : dict, optional
        Keep the journal; this JSON object (for example the capture's metadata and K) is its first line.
    """

    def __init__(self, directory, plan_hash: str, *, overwrite: bool = False, journal: dict | None = None):
        directory = self.directory = Path(directory)
        _check_plan_hash(directory, plan_hash)
        self.plan_hash = plan_hash
        index = self.index = directory / SEQUENCE_FILE
        if directory.exists() and not directory.is_dir():
            raise ValueError(f"{directory}: exists and is not a folder")
        if index.exists():
            if not overwrite:
                raise FileExistsError(f"{directory}: already holds a frame sequence (pass overwrite=True to replace "
                                      "it)")
            index.unlink()
        directory.mkdir(parents=True, exist_ok=True)
        for stale in directory.iterdir():  # frames of an interrupted or replaced write
            if _FRAME_RE.match(stale.name) or (stale.name.startswith(".frame_") and ".tmp" in stale.name):
                stale.unlink()
        self.entries: list[dict] = []
        self.written: list[Path] = []
        self.shape = None
        self.committed = 0
        self.journal = directory / JOURNAL_FILE if journal is not None else None
        if self.journal is not None:
            header = {"format": JOURNAL_FORMAT, "plan_hash": plan_hash, "header": journal}
            _append_synced(self.journal, [header], fresh=True)

    @property
    def n_frames(self) -> int:
        return len(self.entries)

    def add(self, frame, record) -> None:
        """Write one (H, W) frame (uint16 DN, or integers in 0-65535) with its capture record."""
        i = len(self.entries)
        rec = _record_of(record, i, self.directory)
        arr = _frame_array(frame, i, self.directory, self.shape)
        self.shape = arr.shape[:2]
        name = _FRAME_NAME.format(i)
        self.written.append(self.directory / name)
        try:
            size, digest = _write_tiff(self.directory / name, arr)
        except OSError as exc:  # disk full, folder gone: one line naming the frame
            if str(self.directory / name) in str(exc):
                raise
            raise formats.os_error(self.directory / name, exc) from None
        self.entries.append({"file": name, **rec, "bytes": size, "sha256": digest})

    def commit(self) -> None:
        """Journal the frames added since the last commit (appended and synced; nothing without ``journal``)."""
        if self.journal is not None and self.committed < len(self.entries):
            shape = {"height": int(self.shape[0]), "width": int(self.shape[1])}
            _append_synced(self.journal, [{**e, **shape} for e in self.entries[self.committed:]])
        self.committed = len(self.entries)

    def truncate(self, n_frames: int) -> None:
        """Keep only the first ``n_frames`` frames: the files of the later ones (a sequence cut short) are removed."""
        for path in self.written[n_frames:]:
            path.unlink(missing_ok=True)
        del self.entries[n_frames:], self.written[n_frames:]
        self.committed = min(self.committed, n_frames)

    def close(self, metadata=None) -> Path:
        """Validate the whole document and write ``sequence.json`` (atomically, synced); return the folder."""
        meta_text = _metadata_json(self.directory, metadata)
        if not self.entries:
            raise ValueError(f"{self.directory}: no frames to write")
        doc = {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": self.plan_hash,
               "height": int(self.shape[0]), "width": int(self.shape[1]), "dtype": "uint16",
               "n_frames": len(self.entries), "frames": self.entries,
               "metadata": {} if meta_text is None else json.loads(meta_text)}
        doc = validate_sequence_document(doc, self.index)
        with atomic_path(self.index) as tmp:
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump(doc, fh, indent=1, allow_nan=False)
                fh.write("\n")
                fh.flush()
                os.fsync(fh.fileno())
        if self.journal is not None:
            self.journal.unlink(missing_ok=True)
        return self.directory

    def abort(self) -> None:
        """Remove the frames this writer wrote and its journal (no ``sequence.json`` is written)."""
        for p in self.written:
            p.unlink(missing_ok=True)
        self.written = []
        if self.journal is not None:
            self.journal.unlink(missing_ok=True)


JOURNAL_FILE = ".specgpu-capture-journal.jsonl"
JOURNAL_FORMAT = "specgpu.capture-journal"


def _line_check(line: dict) -> str:
    """The checksum a journal line carries (``check``): SHA-256 of its other fields in canonical JSON, 16 hex
    digits. One flipped byte anywhere in the line (a value, a key, the checksum itself) makes it disagree."""
    body = {k: v for k, v in line.items() if k != "check"}
    text = json.dumps(body, sort_keys=True, allow_nan=False, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _append_synced(path: Path, lines, *, fresh: bool = False) -> None:
    """Append JSON lines, each with its checksum, to ``path`` (create or replace it with ``fresh``) and sync them
    to the disk."""
    try:
        with open(path, "w" if fresh else "a", encoding="utf-8") as fh:
            for line in lines:
                fh.write(json.dumps({**line, "check": _line_check(line)}, allow_nan=False) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        raise formats.os_error(path, exc) from None


def _journal_line(raw: bytes):
    """A journal line parsed and verified: (object, None), or (None, why it cannot be trusted). A line without a
    checksum (a journal from a writer before checksums) is taken as it is; its frames are still verified."""
    try:
        line = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None, "not valid JSON"
    if not isinstance(line, dict):
        return None, "not a JSON object"
    if "check" in line and line["check"] != _line_check(line):
        return None, "its checksum does not match its content"
    return line, None


def _frame_shape(path: Path):
    """(height, width) of a frame file from its header, or None when it cannot be read as an image."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        formats.error_of(oiio)  # clear the library's pending error
        return None
    try:
        spec = inp.spec()
        return spec.height, spec.width
    finally:
        inp.close()


def verify_journal(directory, group: int) -> tuple[dict, dict]:
    """Verify what an interrupted capture journaled, without writing anything: every whole sequence of ``group``
    frames whose journal lines are intact (their checksums agree), whose records are valid and in capture order,
    and whose frame files are present, match their journaled sizes and checksums and have the journaled shape.

    Returns
    -------
    doc : dict
        The ``sequence.json`` document of the intact sequences (validated), its metadata holding ``salvaged``.
    info : dict
        ``frames_journaled``, ``frames_kept``, ``sequences``, ``sequences_journaled``, ``left_out`` (one
        ``{"sequence", "first_file", "last_file", "reason"}`` per sequence not kept, 0-based in capture order),
        ``stopped`` (the reasons in one line, or None) and ``frames_unindexed`` (frame files outside the index).

    Raises
    ------
    ValueError
        One line naming the file: no journal, a journal that is not specgpu's or whose header (the plan it names)
        is damaged, or no complete intact sequence (with the first reason).
    """
    directory = Path(directory)
    journal = directory / JOURNAL_FILE
    header, lines = _read_journal(directory)
    group = int(group)
    entries, damaged = {}, []  # frame index -> [(line number, entry)]; line numbers that cannot be trusted
    n_lines = 0
    for number, raw in enumerate(lines[1:], start=2):
        if not raw.strip():
            continue
        n_lines += 1
        entry, why = _journal_line(raw)
        m = _FRAME_INDEX.match(entry["file"]) if entry is not None and isinstance(entry.get("file"), str) else None
        if m is None:
            damaged.append((number, why or "not a frame record"))
            continue
        entries.setdefault(int(m.group(1)), []).append((number, entry))
    last = max(entries) if entries else -1
    n_sequences = max(last // group + 1, n_lines // group) if group > 0 else 0
    kept, left_out, shape, last_id = [], [], None, -1
    for s in range(n_sequences):
        first, stop = s * group, (s + 1) * group
        found = [entries.get(i, []) for i in range(first, stop)]
        reason = None
        if any(len(f) > 1 for f in found):
            reason = "the journal lists one of its frames twice"
        elif not all(found):
            missing = [_FRAME_NAME.format(first + j) for j, f in enumerate(found) if not f]
            before = max((n for i, f in entries.items() if i < first for n, _ in f), default=1)
            after = min((n for i, f in entries.items() if i >= stop for n, _ in f), default=len(lines) + 1)
            bad = [f"line {n} ({why})" for n, why in damaged if before < n < after]
            if s == n_sequences - 1 and not bad and stop > last + 1 >= first:
                reason = (f"incomplete: the last {last + 1 - first} frame(s) of a sequence of {group} (the capture "
                          "stopped while writing it)")
            else:
                reason = (f"no intact journal record of {', '.join(missing[:3])}"
                          f"{' and more' if len(missing) > 3 else ''}"
                          + (f"; damaged journal {', '.join(bad)}" if bad else ""))
        chunk = [f[0] for f in found] if reason is None else []
        if reason is None:
            reason = _sequence_problem(directory, [e for _, e in chunk], first, shape, last_id, journal)
        if reason is not None:
            left_out.append({"sequence": s, "first_file": _FRAME_NAME.format(first),
                             "last_file": _FRAME_NAME.format(stop - 1), "reason": reason})
            continue
        shape = (chunk[0][1]["height"], chunk[0][1]["width"])
        last_id = chunk[-1][1]["frame_id"]
        kept.extend(e for _, e in chunk)
    stopped = "; ".join(f"sequence {x['sequence']}: {x['reason']}" for x in left_out) or None
    if not kept:
        raise ValueError(f"{directory}: no complete, intact sequence to salvage "
                         f"({left_out[0]['reason'] if left_out else 'nothing journaled'})")
    frames = [{k: v for k, v in e.items() if k not in ("height", "width", "check")} for e in kept]
    names = {e["file"] for e in frames}
    info = {"frames_journaled": n_lines, "frames_kept": len(kept), "sequences": len(kept) // group,
            "sequences_journaled": n_sequences, "left_out": left_out, "stopped": stopped,
            "frames_unindexed": sum(1 for p in directory.iterdir() if _FRAME_RE.match(p.name) and p.name not in names)}
    meta = {k: v for k, v in (header.get("header") or {}).items()}
    meta["salvaged"] = info
    doc = {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": header.get("plan_hash"),
           "height": shape[0], "width": shape[1], "dtype": "uint16", "n_frames": len(frames), "frames": frames,
           "metadata": meta}
    return validate_sequence_document(doc, journal), info


_FRAME_INDEX = re.compile(r"^frame_(\d{6,})\.tif$")


def journal_header(directory) -> dict:
    """The verified first line of a capture folder's journal: ``plan_hash`` (the plan the frames were captured
    with) and ``header`` (the capture's own, e.g. ``plan_method`` and ``K``). Raises as :func:`verify_journal`."""
    return _read_journal(directory)[0]


def _read_journal(directory: Path) -> tuple[dict, list[bytes]]:
    journal = Path(directory) / JOURNAL_FILE
    if (Path(directory) / SEQUENCE_FILE).exists():
        raise FileExistsError(f"{directory}: already holds {SEQUENCE_FILE}; nothing to salvage")
    if not journal.is_file():
        raise ValueError(f"{directory}: no capture journal ({JOURNAL_FILE}); nothing of it can be indexed")
    lines = journal.read_bytes().split(b"\n")
    header, why = _journal_line(lines[0])
    if header is None:
        raise ValueError(f"{journal}: corrupt at line 1, its header ({why}): the plan the frames were captured "
                         "with cannot be verified, so none of them is indexed")
    if header.get("format") != JOURNAL_FORMAT or not isinstance(header.get("plan_hash"), str):
        raise ValueError(f"{journal}: not a specgpu capture journal")
    return header, lines


def _sequence_problem(directory: Path, chunk: list, first: int, shape, last_id: int, journal: Path) -> str | None:
    """Why a whole journaled sequence (its ``chunk`` of records, frame ``first`` on) cannot be kept, or None."""
    try:
        validate_sequence_document(
            {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "plan_hash": "journal", "height": 1, "width": 1,
             "dtype": "uint16", "frames": [{k: v for k, v in e.items() if k not in ("height", "width", "check")}
                                           for e in chunk]}, journal)
    except ValueError as error:
        return f"an invalid journal record ({str(error).split(': ', 1)[-1]})"
    for j, e in enumerate(chunk):
        h, w = e.get("height"), e.get("width")
        if not (_is_int(h) and _is_int(w) and h >= 1 and w >= 1):
            return f"{e['file']}: its journal record has no valid height and width"
        if e["pattern_index"] != j:
            return f"{e['file']}: pattern {e['pattern_index']} where the sequence's pattern {j} belongs"
    if chunk[0]["frame_id"] <= last_id:
        return f"{chunk[0]['file']}: frame id {chunk[0]['frame_id']} is not after the previous sequence's {last_id}"
    for e in chunk:
        problem = _journaled_frame_problem(directory, e)
        if problem is not None:
            return problem
        actual = _frame_shape(directory / e["file"])
        if actual is None:
            return f"{e['file']} cannot be read as an image"
        if actual != (e["height"], e["width"]):
            return (f"{e['file']} is {actual[0]} x {actual[1]} pixels but its journal record says {e['height']} x "
                    f"{e['width']}")
        if shape is not None and actual != tuple(shape):
            return f"{e['file']} is {actual[0]} x {actual[1]} pixels, the sequences kept {shape[0]} x {shape[1]}"
    return None


def _journaled_frame_problem(directory: Path, entry) -> str | None:
    """Why a journaled frame cannot be kept (missing, or its bytes differ from the journal), or None."""
    path = directory / Path(entry["file"]).name
    try:
        raw = path.read_bytes()
    except OSError:
        return f"{path.name} is missing"
    if len(raw) != entry.get("bytes") or hashlib.sha256(raw).hexdigest() != entry.get("sha256"):
        return f"{path.name} does not match its journaled checksum"
    return None


def salvage_sequence(directory, group: int, *, metadata=None, check=None, confirm=None) -> dict:
    """Index what an interrupted capture journaled: write ``sequence.json`` for every whole sequence of ``group``
    frames that :func:`verify_journal` finds intact; the others are left out, each with its reason (in the
    returned ``left_out`` and in ``sequence.json``'s ``metadata.salvaged``).

    Verify first, commit last: ``check(doc)`` (the caller's checks of the document, e.g. its plan) runs before
    anything is written; ``sequence.json`` is written atomically, then ``confirm()`` (reading the folder back)
    runs, and only once it passes is the journal removed. Any failure leaves the folder as it was (journal kept,
    no ``sequence.json``), so salvage can be run again. No frame file is deleted.

    Returns
    -------
    dict
        See :func:`verify_journal` (``info``).

    Raises
    ------
    ValueError
        See :func:`verify_journal`; whatever ``check`` or ``confirm`` raise.
    """
    directory = Path(directory)
    doc, info = verify_journal(directory, group)
    if metadata:
        doc["metadata"] = {**doc["metadata"], **metadata, "salvaged": info}
    if check is not None:
        check(doc)
    index = directory / SEQUENCE_FILE
    with atomic_path(index) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=1, allow_nan=False)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
    if confirm is not None:
        try:
            confirm()
        except BaseException:
            index.unlink(missing_ok=True)  # not readable after all: back to the journal, to be salvaged again
            raise
    (directory / JOURNAL_FILE).unlink(missing_ok=True)
    return info


def read_sequence_header(directory) -> tuple[list[dict], dict]:
    """Read and validate only ``sequence.json`` of a sequence folder (no pixels).

    Returns
    -------
    records : list of dict
        Per frame, in capture order: ``file``, ``frame_id``, ``pattern_index``, ``exposure_s``, ``timestamp_s``,
        ``bytes``, ``sha256``.
    meta : dict
        ``format``, ``version``, ``plan_hash``, ``height``, ``width``, ``dtype``, ``n_frames``, ``metadata``.

    Raises
    ------
    FileNotFoundError
        The folder does not exist.
    ValueError
        One line naming the file: no ``sequence.json`` (an incomplete or interrupted capture), invalid JSON, or
        a document :func:`validate_sequence_document` rejects.
    """
    directory = Path(directory)
    if not directory.exists():
        raise FileNotFoundError(f"{directory}: sequence folder not found")
    if not directory.is_dir():
        raise ValueError(f"{directory}: not a folder (a frame sequence is a folder with {SEQUENCE_FILE})")
    index = directory / SEQUENCE_FILE
    if not index.is_file():
        raise ValueError(f"{index}: missing; {directory} is not a complete frame sequence (an interrupted write "
                         "leaves no sequence.json)")
    try:
        doc = json.loads(index.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"{index}: corrupt (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{index}: corrupt JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    doc = validate_sequence_document(doc, index)
    records = doc.pop("frames")
    doc["n_frames"] = len(records)
    return records, doc


def _read_tiff(path: Path, shape) -> np.ndarray:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: truncated or corrupt TIFF ({one_line(formats.error_of(oiio))})")
    try:
        spec = inp.spec()
        if inp.format_name() != "tiff" or spec.nchannels != 1 or str(spec.format) != "uint16":
            raise ValueError(f"{path}: frame must be a 1-channel 16-bit TIFF, got {inp.format_name()} "
                             f"{spec.nchannels} channel(s) {spec.format}")
        if (spec.height, spec.width) != tuple(shape):
            raise ValueError(f"{path}: frame is {spec.height} x {spec.width}, sequence.json says "
                             f"{shape[0]} x {shape[1]}")
        data = inp.read_image(0, 0, 0, 1, "uint16")
        err = formats.error_of(inp)
        if data is None or err or data.size != shape[0] * shape[1]:
            raise ValueError(f"{path}: truncated or corrupt TIFF ({one_line(err or 'no pixel data')})")
    finally:
        inp.close()
    return data.reshape(shape)


def read_sequence(directory, *, verify: bool = True) -> tuple[np.ndarray, list[dict], dict]:
    """Read a frame sequence folder written by :func:`write_sequence`.

    Parameters
    ----------
    directory : str or os.PathLike
        The folder.
    verify : bool
        Check each frame file's SHA-256 against ``sequence.json`` (catches corruption that keeps the size);
        sizes are always checked.

    Returns
    -------
    frames : numpy.ndarray
        (N, H, W) uint16 frames (DN), in capture order.
    records : list of dict
        Per frame (see :func:`read_sequence_header`).
    meta : dict
        ``plan_hash``, ``height``, ``width``, ``n_frames``, ``format``, ``version``, ``metadata``.

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming the file: see :func:`read_sequence_header`; a listed frame missing, truncated (size
        differs), corrupt (checksum or decoding) or of the wrong shape or type.
    """
    directory = Path(directory)
    records, meta = read_sequence_header(directory)
    shape = (meta["height"], meta["width"])
    frames = None  # allocated once the first frame has shown that the header's size is real
    for i, rec in enumerate(records):
        frame = _read_listed_frame(directory, i, rec, shape, verify)
        if frames is None:
            try:
                frames = np.empty((len(records), *shape), dtype=np.uint16)
            except (MemoryError, ValueError):
                raise ValueError(f"{directory / SEQUENCE_FILE}: {len(records)} frames of {shape[0]} x {shape[1]} "
                                 f"pixels ({len(records) * shape[0] * shape[1] * 2 / 2**30:.1f} GiB) do not fit "
                                 "in memory") from None
        frames[i] = frame
    return frames, records, meta


def _check_listed_frame(directory: Path, i: int, rec: dict) -> Path:
    """The file of frame ``i`` listed in ``sequence.json``, there and of the listed size."""
    path = directory / rec["file"]
    if not path.is_file():
        raise ValueError(f"{path}: frame {i} (frame id {rec['frame_id']}) listed in {SEQUENCE_FILE} is missing")
    size = path.stat().st_size
    if size != rec["bytes"]:
        raise ValueError(f"{path}: truncated or altered frame: {size} bytes, {SEQUENCE_FILE} says {rec['bytes']}")
    return path


def _read_listed_frame(directory: Path, i: int, rec: dict, shape, verify: bool) -> np.ndarray:
    path = _check_listed_frame(directory, i, rec)
    if verify:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest != rec["sha256"]:
            raise ValueError(f"{path}: corrupt frame: SHA-256 differs from {SEQUENCE_FILE}")
    return _read_tiff(path, shape)


def check_frame_files(directory, records) -> None:
    """Every frame listed in ``sequence.json`` (``records``, from :func:`read_sequence_header`) is there with its
    listed size: what a reader checks before any work, without reading pixels (a one-line error naming the
    file)."""
    directory = Path(directory)
    for i, rec in enumerate(records):
        _check_listed_frame(directory, i, rec)


def read_frames(directory, records, meta, start: int, stop: int, *, verify: bool = True) -> np.ndarray:
    """Frames ``start:stop`` of a sequence folder whose header :func:`read_sequence_header` returned
    (``records``, ``meta``), each checked as :func:`read_sequence` checks it: (stop - start, H, W) uint16. Reading
    a folder a sequence at a time keeps memory to one sequence however long the capture."""
    directory = Path(directory)
    shape = (meta["height"], meta["width"])
    if not 0 <= start <= stop <= len(records):
        raise ValueError(f"{directory}: frames {start}:{stop} are out of range ({len(records)} listed)")
    out = np.empty((stop - start, *shape), dtype=np.uint16)
    for j, i in enumerate(range(start, stop)):
        out[j] = _read_listed_frame(directory, i, records[i], shape, verify)
    return out
