"""Spectral cubes and maps, the format chosen by the file name, with the caller's metadata; the formats at a glance.

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
                       In :mod:`specgpu.io.previews`.
frame sequence         a folder with 16-bit TIFF frames and ``sequence.json`` (format ``specgpu.sequence``,
                       version 1): per frame its file, frame id, pattern index, exposure, timestamp, size and
                       SHA-256, plus the plan hash. In :mod:`specgpu.io.sequence`.
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

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.text import short_list
from specgpu.io.envi import (
    _envi_data_candidates,
    envi_data_path,
    read_cube_envi,
    read_envi_header,
    write_cube_envi,
)
from specgpu.io.exr import read_cube_exr, read_exr, write_cube_exr, write_exr
from specgpu.io.metadata import _META_ATTRIBUTE, _metadata_from, _metadata_json
from specgpu.io.npz import read_cube_npz, write_cube_npz
from specgpu.io.paths import _suffix

__all__ = ["write_cube", "read_cube", "companion_files", "MAP_KINDS", "write_map", "read_map"]


# ---- spectral cubes ------------------------------------------------------------------------------------------------
def write_cube(path: str | os.PathLike[str], cube: ArrayLike, wavelengths: ArrayLike, *, half: bool = False,
               metadata: dict | None = None, interleave: str = "bsq") -> Path:
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

    Examples
    --------
    >>> import pathlib, tempfile
    >>> import numpy as np
    >>> from specgpu.io import read_cube, write_cube
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "cube.exr"
    >>> write_cube(path, np.full((2, 3, 4), 0.5), [400, 500, 600, 700], metadata={"method": "demo"}).name
    'cube.exr'
    >>> cube, wavelengths, metadata = read_cube(path)
    >>> cube.shape, wavelengths.tolist(), metadata
    ((2, 3, 4), [400.0, 500.0, 600.0, 700.0], {'method': 'demo'})
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


def read_cube(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, dict]:
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

    Examples
    --------
    Bands come back ordered by wavelength, whatever their order in the file:

    >>> import pathlib, tempfile
    >>> import numpy as np
    >>> from specgpu.io import read_cube, write_cube
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "cube.npz"
    >>> _ = write_cube(path, np.stack([np.zeros((2, 2)), np.ones((2, 2))], axis=-1), [600, 400])
    >>> cube, wavelengths, _ = read_cube(path)
    >>> wavelengths.tolist(), cube[0, 0].tolist()
    ([400.0, 600.0], [1.0, 0.0])
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


def write_map(path: str | os.PathLike[str], data: ArrayLike, kind, *, half: bool = False,
              metadata: dict | None = None) -> Path:
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

    Examples
    --------
    >>> import pathlib, tempfile
    >>> import numpy as np
    >>> from specgpu.io import read_map, write_map
    >>> path = write_map(pathlib.Path(tempfile.mkdtemp()) / "xyz.exr", np.full((2, 3, 3), 0.25), "XYZ")
    >>> data, channels, metadata = read_map(path)
    >>> data.shape, channels, metadata
    ((2, 3, 3), ('X', 'Y', 'Z'), {})
    """
    path = Path(path)
    _suffix(path, (".exr",), "map")
    names = _channels_of(kind, path)
    arr = np.asarray(data, dtype=np.float32)
    if arr.ndim == 2 and len(names) == 1:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] != len(names):
        raise ValueError(f"{path}: a {short_list(names, sep='/')} map must have shape (H, W, {len(names)}), "
                         f"got {arr.shape}")
    meta = _metadata_json(path, metadata)
    return write_exr(path, arr, names, half=half, attributes={} if meta is None else {_META_ATTRIBUTE: meta})


def read_map(path: str | os.PathLike[str], kind=None) -> tuple[np.ndarray, tuple[str, ...], dict]:
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

    Examples
    --------
    >>> import pathlib, tempfile
    >>> import numpy as np
    >>> from specgpu.io import read_map, write_map
    >>> path = write_map(pathlib.Path(tempfile.mkdtemp()) / "xyz.exr", np.arange(6.0).reshape(1, 2, 3), "XYZ")
    >>> data, channels, _ = read_map(path, ["Z", "X"])
    >>> channels, data[0, 1].tolist()
    (('Z', 'X'), [5.0, 3.0])
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
            label = kind if isinstance(kind, str) else short_list(wanted, sep="/")
            raise ValueError(f"{path}: not a {label} map: expected channels {short_list(wanted)}, "
                             f"found {', '.join(names[:8])}{', ...' if len(names) > 8 else ''}")
    index = [names.index(n) for n in wanted]
    return np.ascontiguousarray(data[..., index]), tuple(wanted), _metadata_from(path, attributes)
