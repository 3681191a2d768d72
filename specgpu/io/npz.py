"""``.npz`` cubes and two-column CSV spectral curves.

A cube ``.npz`` holds ``wavelengths`` (B,) and ``reflectance`` (H, W, B) (:func:`read_cube_npz`,
:func:`write_cube_npz`). :func:`npz_members` opens any ``.npz`` within fixed limits (member size against the memory
available, inflation ratio), so a damaged or hostile archive is one line, not an exhausted machine. CSV curves
(:func:`read_spectrum_csv`) are resampled onto a band grid by :func:`curve_on_grid`.
"""

from __future__ import annotations

import math
import os
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.text import one_line
from specgpu.core.validate import (
    available_memory_bytes,
    check_wavelengths,
    normalised_to_peak,
)
from specgpu.io.bands import check_cube, wavelength_order
from specgpu.io.paths import _check_exists, atomic_path

__all__ = [
    "NPZ_UNIFORM_BYTES", "NPZ_MAX_RATIO", "NPZ_COMPRESSLEVEL", "npz_members", "savez_deflated", "read_cube_npz",
    "write_cube_npz", "read_spectrum_csv", "curve_on_grid"
]

# ---- npz ---------------------------------------------------------------------------------------------------------
#: An npz member this large (bytes, as its header declares) ...
NPZ_UNIFORM_BYTES = 64 * 2**20
#: ... that inflates more than this many times over its compressed size is refused: deflate reaches ~1000:1 only
#: on constant data, which no measured cube, plan or calibration of that size is (a "zip bomb" that would take
#: its declared size in memory before any check could look at its content).
NPZ_MAX_RATIO = 500


def npz_members(path) -> dict:
    """The arrays of an ``.npz`` as their ``.npy`` headers declare them, read without inflating any data:
    name -> (shape, dtype). Refuses, in one line naming the file and the member: a header whose declared size is
    not what the archive stores, an array of more bytes than this machine has memory available, or a large member
    that inflates like a zip bomb (see :data:`NPZ_MAX_RATIO`). Call it before ``np.load`` reads any array."""
    path = Path(path)
    members, total = {}, 0
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                name = info.filename[:-4]
                with zf.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    if version == (1, 0):
                        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
                    elif version == (2, 0):
                        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
                    else:
                        raise ValueError(f"unsupported .npy version {version}")
                    header_bytes = fh.tell()
                if dtype.hasobject:
                    raise ValueError(f"{path}: array {name!r} is not numeric (dtype {dtype})")
                nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if header_bytes + nbytes != info.file_size:
                    raise ValueError(f"{path}: array {name!r} declares {nbytes} bytes but the archive stores "
                                     f"{info.file_size - header_bytes}; truncated or corrupt .npz")
                if nbytes >= NPZ_UNIFORM_BYTES and nbytes > NPZ_MAX_RATIO * max(info.compress_size, 1):
                    raise ValueError(f"{path}: array {name!r} {tuple(shape)} would inflate "
                                     f"{info.compress_size / 1e6:.2f} MB to {nbytes / 1e6:.0f} MB "
                                     f"({nbytes / max(info.compress_size, 1):.0f}:1, constant data); refused "
                                     "before loading it")
                members[name] = (tuple(shape), dtype)
                total += nbytes
    except ValueError as exc:
        msg = one_line(str(exc))
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: truncated or corrupt .npz ({msg})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, SyntaxError, tokenize.TokenError,
            RuntimeError, NotImplementedError) as exc:
        raise ValueError(f"{path}: truncated or corrupt .npz ({exc.__class__.__name__}: {one_line(str(exc))})"
                         ) from None
    available = available_memory_bytes()
    if available is not None and total > available:
        raise ValueError(f"{path}: its arrays take {total / 1e9:.2f} GB once loaded but only {available / 1e9:.2f} "
                         "GB of memory are available; refused before loading them")
    return members


def read_cube_npz(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read a ``.npz`` cube, bands ordered by wavelength.

    Returns
    -------
    cube : numpy.ndarray
        (H, W, B) reflectance as stored (dtype kept).
    wavelengths : numpy.ndarray
        (B,) float64, nm, strictly increasing.
    extra : dict
        Every other array in the file, by name (e.g. ``mask_<name>``).
    """
    path = Path(path)
    _check_exists(path, "spectral cube")
    members = npz_members(path)  # sizes from the headers, before any array is inflated
    if "wavelengths" in members and "reflectance" in members:  # the shapes too, before the data
        wl_shape, refl_shape = members["wavelengths"][0], members["reflectance"][0]
        if len(wl_shape) != 1:
            raise ValueError(f"{path}: wavelengths must have shape (B,), got {wl_shape}")
        if len(refl_shape) != 3 or refl_shape[2] != wl_shape[0]:
            raise ValueError(f"{path}: reflectance must have shape (H, W, {wl_shape[0]}), got {refl_shape}")
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
            missing = {"wavelengths", "reflectance"} - keys
            if missing:
                raise ValueError(f"{path}: missing array(s) {sorted(missing)}; found {sorted(keys)}")
            wl = np.array(data["wavelengths"])
            refl = np.array(data["reflectance"])
            extra = {k: np.array(data[k]) for k in data.files if k not in ("wavelengths", "reflectance")}
    except ValueError as exc:
        msg = one_line(str(exc))
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: truncated or corrupt .npz ({msg})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, SyntaxError, tokenize.TokenError,
            MemoryError, RuntimeError) as exc:  # a corrupt .npy header (parsed as a Python literal), zip flags
        raise ValueError(f"{path}: truncated or corrupt .npz "
                         f"({exc.__class__.__name__}: {one_line(str(exc))})") from None
    if wl.ndim != 1:
        raise ValueError(f"{path}: wavelengths must have shape (B,), got {wl.shape}")
    try:
        wl = wl.astype(np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: wavelengths must be numbers, got dtype {wl.dtype}") from None
    if refl.ndim != 3 or refl.shape[2] != wl.size:
        raise ValueError(f"{path}: reflectance must have shape (H, W, {wl.size}), got {refl.shape}")
    order = wavelength_order(path, wl)
    return refl[..., order], wl[order], extra


#: zlib level of the ``.npz`` files specgpu writes. numpy's ``savez_compressed`` uses zlib's default, 6; on this
#: project's arrays (float32 cubes, calibration maps, noisy dark frames) level 1 writes about twice as fast for files
#: about a tenth larger (a motion truth cube of a chart: 28:1 at level 6, 26:1 at level 1), and reads alike.
NPZ_COMPRESSLEVEL = 1


def savez_deflated(file, arrays: dict) -> None:
    """Write ``arrays`` to the open binary ``file`` as an ``.npz`` (deflated, :data:`NPZ_COMPRESSLEVEL`), the same
    format ``numpy.savez_compressed`` writes and ``numpy.load`` reads; no array may need pickling."""
    with zipfile.ZipFile(file, "w", zipfile.ZIP_DEFLATED, compresslevel=NPZ_COMPRESSLEVEL) as zf:
        for name, value in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def write_cube_npz(path: str | os.PathLike[str], cube: ArrayLike, wavelengths: ArrayLike,
                   extra: dict | None = None) -> Path:
    """Write a cube as compressed ``.npz`` (``wavelengths``, ``reflectance`` plus ``extra`` arrays), atomically."""
    path = Path(path)
    arr, wl = check_cube(path, cube, wavelengths)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    arrays = {"wavelengths": wl, "reflectance": arr}
    arrays.update(extra or {})
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:  # a file object: np.savez would otherwise append ".npz" to the temp name
            savez_deflated(fh, arrays)
    return path


# ---- CSV spectral curves -----------------------------------------------------------------------------------------
def read_spectrum_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a two-column CSV spectral curve: wavelength (nm), value.

    Lines starting with ``#`` and a single non-numeric header line are skipped; separators may be commas,
    semicolons, tabs or spaces. Wavelengths are sorted ascending (the file order does not matter).

    Parameters
    ----------
    path
        File path.

    Returns
    -------
    wavelengths, values : numpy.ndarray
        float64 arrays of equal length (>= 2), wavelengths strictly increasing in nm.

    Raises
    ------
    ValueError
        Naming the file and line for a missing file, a line without two numbers, NaN, duplicated or
        negative wavelengths, or fewer than two samples.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read spectral CSV ({exc.__class__.__name__}: {exc})") from None
    rows = []
    header_seen = False
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f for f in stripped.replace(";", ",").replace("\t", ",").replace(" ", ",").split(",") if f]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if not rows and not header_seen:
                header_seen = True
                continue
            raise ValueError(f"{path}:{number}: expected two numbers, got {stripped!r}") from None
        if len(values) != 2:
            raise ValueError(f"{path}:{number}: expected two columns (wavelength nm, value), got {len(values)}")
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{path}:{number}: NaN or infinite value in {stripped!r}")
        rows.append(values)
    if len(rows) < 2:
        raise ValueError(f"{path}: a spectral CSV needs at least 2 rows (wavelength nm, value), got {len(rows)}")
    data = np.array(rows, dtype=np.float64)
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    if np.any(np.diff(data[:, 0]) == 0):
        dup = data[1:, 0][np.diff(data[:, 0]) == 0][0]
        raise ValueError(f"{path}: wavelength {dup:g} nm appears more than once")
    try:
        wl = check_wavelengths(f"{path}: wavelengths", data[:, 0])
    except ValueError as exc:
        raise ValueError(str(exc)) from None
    return wl, data[:, 1].copy()


def curve_on_grid(path, wavelengths: np.ndarray, what: str, zero_message: str) -> np.ndarray:
    """A two-column CSV spectral curve (``what``: e.g. ``"lamp power"``) on ``wavelengths``, 0 outside its range,
    normalised to a peak of 1; negative values, or nothing but zeros on the grid (``zero_message``), are errors."""
    src_wl, src_val = read_spectrum_csv(path)
    if np.any(src_val < 0):
        raise ValueError(f"{path}: {what} must be non-negative, got minimum {src_val.min():g}")
    return normalised_to_peak(np.interp(wavelengths, src_wl, src_val, left=0.0, right=0.0), wavelengths,
                              zero_message)
