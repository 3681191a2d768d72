"""OpenEXR through OpenImageIO, with the spectral layout of Fichet, Pacanowski and Wilkie.

"An OpenEXR Layout for Spectral Images", JCGT 10(3), 2021: one reflective channel per band named
``T.<wavelength><unit>`` (:func:`format_channel`, :func:`parse_channel`) and ``spectralLayoutVersion`` ``"1.0"`` in
the header. This module reads and writes any EXR (:func:`read_exr`, :func:`write_exr`), spectral cubes in that
layout (:func:`read_cube_exr`, :func:`write_cube_exr`) and other images through OpenImageIO (:func:`write_image`).
Readers order bands by wavelength, never by channel order (OpenEXR stores channels sorted by name).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from numpy.typing import ArrayLike

from specgpu.core.text import one_line, short_list
from specgpu.io.bands import check_cube
from specgpu.io.paths import _check_exists, atomic_path, error_of, write_failed

__all__ = [
    "SPECTRAL_LAYOUT_VERSION", "format_channel", "parse_channel", "read_exr", "write_exr", "write_image",
    "read_cube_exr", "write_cube_exr"
]

#: Value of the ``spectralLayoutVersion`` header attribute the JCGT 2021 layout defines.
SPECTRAL_LAYOUT_VERSION = "1.0"

SPEED_OF_LIGHT = 299_792_458.0  # m/s, exact (SI)

# JCGT 2021 (and the authors' reference code, afichet/spectral-exr lib/EXRSpectralImage.cpp, and colour-science's
# colour/io/fichet2021.py): reflective channel = "T." + number + optional SI prefix + unit ("m" or "Hz").
# The number uses a comma as decimal separator because "." separates layers in OpenEXR channel names
# ("T.550,000000nm"). We also accept a "." (e.g. "T.405.5nm", which OpenEXR tools see as layer "T.405",
# channel "5nm") for files written by other tools; we always write the comma.
_PREFIXES = {"Y": 24, "Z": 21, "E": 18, "P": 15, "T": 12, "G": 9, "M": 6, "k": 3, "h": 2, "da": 1, "": 0,
             "d": -1, "c": -2, "m": -3, "u": -6, "n": -9, "p": -12}
_REFLECTIVE = re.compile(
    r"^T\.(?P<number>(?:\d+(?:[.,]\d*)?|[.,]\d+)(?:[eE][+-]?\d+)?)"
    r"(?P<prefix>da|[YZEPTGMkhdcmunp])?(?P<unit>m|Hz)$")



def format_channel(wavelength_nm) -> str:
    """JCGT 2021 name of the reflective channel at ``wavelength_nm``.

    Parameters
    ----------
    wavelength_nm : float
        Wavelength in nm, finite and > 0.

    Returns
    -------
    str
        ``"T." + number + "nm"`` with a comma as decimal separator and six decimals as the reference code writes
        them (``550 -> "T.550,000000nm"``); when six decimals would not give the value back exactly, the shortest
        exact decimal form (``"T.405,12345678nm"``). ``parse_channel(format_channel(w)) == w`` for every finite
        positive float ``w``.
    """
    try:
        wl = float(wavelength_nm)
    except (TypeError, ValueError):
        raise ValueError(f"wavelength must be a number, got {wavelength_nm!r}") from None
    if not math.isfinite(wl) or wl <= 0:
        raise ValueError(f"wavelength must be finite and > 0 nm, got {wavelength_nm!r}")
    text = f"{wl:.6f}"
    if float(text) != wl:
        text = repr(wl)
    return "T." + text.replace(".", ",") + "nm"


def parse_channel(name: str) -> float | None:
    """Wavelength in nm of a JCGT 2021 reflective channel name, or None if ``name`` is not one.

    Parameters
    ----------
    name : str
        Channel name, e.g. ``"T.550,000000nm"``, ``"T.405,5nm"``, ``"T.0,55um"``, ``"T.545THz"``.

    Returns
    -------
    float or None
        Wavelength in nm (frequencies converted with c = 299 792 458 m/s); may be 0 or inf for degenerate names
        such as ``"T.0nm"`` (callers reject them). None for other channels (``R``, ``S0.550,000000nm``, ...).
    """
    m = _REFLECTIVE.match(str(name))
    if not m:
        return None
    value = float(m.group("number").replace(",", "."))
    exponent = _PREFIXES[m.group("prefix") or ""]
    if m.group("unit") == "m":
        e = exponent + 9  # to nm
        if e == 0:
            return value
        return value * 10.0 ** e if e > 0 else value / 10.0 ** -e
    hertz = value * 10.0 ** exponent if exponent >= 0 else value / 10.0 ** -exponent
    return math.inf if hertz == 0 else SPEED_OF_LIGHT / hertz * 1e9




# ---- OpenEXR -----------------------------------------------------------------------------------------------------
def read_exr(path: str | os.PathLike[str], what: str = "EXR") -> tuple[np.ndarray, list[str], dict]:
    """Read every channel of an OpenEXR file as float32.

    Returns
    -------
    data : numpy.ndarray
        (H, W, C) float32 (half channels widened exactly).
    names : list of str
        The C channel names, in the file's order (OpenEXR stores them sorted by name).
    attributes : dict
        Header attributes, name -> value.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ValueError
        The file cannot be opened as OpenEXR, is deep, or its pixels are truncated or corrupt.
    """
    path = Path(path)
    _check_exists(path, what)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: cannot open EXR ({one_line(error_of(oiio))})")
    try:
        if inp.format_name() != "openexr":
            raise ValueError(f"{path}: not an OpenEXR file (OpenImageIO reads it as {inp.format_name()!r})")
        spec = inp.spec()
        if spec.deep:
            raise ValueError(f"{path}: deep OpenEXR images are not supported")
        try:
            names = list(spec.channelnames)
            attributes = {a.name: a.value for a in spec.extra_attribs}
        except UnicodeDecodeError:
            raise ValueError(f"{path}: corrupt EXR header (a channel or attribute is not UTF-8 text)") from None
        data = inp.read_image(0, 0, 0, spec.nchannels, "float")
        err = error_of(inp)
        expected = spec.width * spec.height * spec.nchannels
        if data is None or not isinstance(data, np.ndarray) or data.size != expected or err:
            reason = one_line(err or error_of(oiio) or "no pixel data")
            raise ValueError(f"{path}: truncated or corrupt EXR ({reason})")
    finally:
        inp.close()
    return np.ascontiguousarray(data.reshape(spec.height, spec.width, spec.nchannels), np.float32), names, attributes


def write_exr(path: str | os.PathLike[str], data: ArrayLike, names, *, half: bool = False,
              attributes: dict | None = None) -> Path:
    """Write an (H, W, C) array as an OpenEXR file with the given channel names, atomically.

    Parameters
    ----------
    path
        Target file (``.exr``); its folder must exist.
    data : array_like
        (H, W, C) values, written as float32 or, with ``half=True``, as half (rounded to nearest).
    names : sequence of str
        C unique channel names.
    attributes : dict, optional
        Header attributes, name -> str, int or float.
    """
    path = Path(path)
    arr = np.asarray(data, dtype=np.float32)
    names = [str(n) for n in names]
    if arr.ndim != 3 or arr.shape[2] != len(names) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{path}: data must have shape (H, W, {len(names)}) with H, W >= 1, got {arr.shape}")
    if len(set(names)) != len(names):
        repeated = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"{path}: channel names must be unique; repeated: {short_list(repeated)}")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, "half" if half else "float")
    spec.channelnames = tuple(names)
    spec.attribute("compression", "zip")
    for key, value in (attributes or {}).items():
        spec.attribute(str(key), value)
    return write_image(path, arr, spec, "openexr", "EXR")


def write_image(path: Path, pixels: np.ndarray, spec, format_name: str, label: str) -> Path:
    """Write ``pixels`` (H, W, C) with an OpenImageIO ``spec`` through ``format_name``, atomically (temporary name,
    renamed at the end); a failure is a one-line ValueError naming the file."""
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(format_name)
        if out is None or not out.open(str(tmp), spec):
            raise write_failed(path, tmp, label, oiio.geterror())
        try:
            if not out.write_image(np.ascontiguousarray(pixels)):
                raise write_failed(path, tmp, label, out.geterror())
        finally:
            closed = out.close()  # the last of the file (an EXR's offset table) is written here
        if not closed:
            raise write_failed(path, tmp, label, out.geterror() or oiio.geterror() or "closing the file failed")
    return path


def read_cube_exr(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read the reflective spectral channels of a JCGT 2021 OpenEXR file, bands ordered by wavelength.

    Returns
    -------
    cube : numpy.ndarray
        (H, W, B) float32, band b at ``wavelengths[b]``; other channels (RGB previews, emissive ``S0.*``) are
        ignored.
    wavelengths : numpy.ndarray
        (B,) float64, nm, strictly increasing, finite, > 0.
    attributes : dict
        Header attributes.

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming the file: see :func:`read_exr`; no ``T.<wavelength>nm`` channel; a degenerate or
        duplicated wavelength.
    """
    path = Path(path)
    data, names, attributes = read_exr(path, "spectral cube")
    picked = [(wl, i, n) for i, n in enumerate(names) if (wl := parse_channel(n)) is not None]
    if not picked:
        shown = one_line(", ".join(names[:8]) + (", ..." if len(names) > 8 else ""))
        raise ValueError(f"{path}: no reflective spectral channels named 'T.<wavelength>nm' (found {shown})")
    for wl, _, n in picked:
        if not math.isfinite(wl) or wl <= 0:
            raise ValueError(f"{path}: channel {n!r} gives wavelength {wl} nm; must be finite and > 0")
    picked.sort()
    for (a, _, na), (b, _, nb) in zip(picked, picked[1:]):
        if a == b:
            raise ValueError(f"{path}: a wavelength appears in more than one 'T.' channel "
                             f"({na!r} and {nb!r}: {a:g} nm)")
    wavelengths = np.array([wl for wl, _, _ in picked], dtype=np.float64)
    cube = np.ascontiguousarray(data[..., [i for _, i, _ in picked]])
    return cube, wavelengths, attributes


def write_cube_exr(path: str | os.PathLike[str], cube: ArrayLike, wavelengths: ArrayLike, *, half: bool = False,
                   attributes: dict | None = None) -> Path:
    """Write an (H, W, B) cube as JCGT 2021 reflective channels ``T.<wl>nm`` (float32 or half), atomically.

    The header carries ``spectralLayoutVersion = "1.0"`` plus ``attributes``.
    """
    path = Path(path)
    arr, wl = check_cube(path, cube, wavelengths)
    attrs = {"spectralLayoutVersion": SPECTRAL_LAYOUT_VERSION}
    attrs.update(attributes or {})
    return write_exr(path, arr, [format_channel(v) for v in wl], half=half, attributes=attrs)
