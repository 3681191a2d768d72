"""Low-level file formats shared by :mod:`specgpu.io.files`, :mod:`specgpu.rig`, :mod:`specgpu.planning.basis` and the drivers.

The layouts live here, at the bottom of the import arrows (this module imports only :mod:`specgpu.core.validate`), so
that every room may read and write them and ``rig`` never imports ``io``; :mod:`specgpu.io.files` stays the public home
of file formats for users:

- OpenEXR through OpenImageIO, with the reflective channels of Fichet, Pacanowski and Wilkie, "An OpenEXR Layout
  for Spectral Images", JCGT 10(3), 2021 (:func:`format_channel`, :func:`parse_channel`);
- ``.npz`` with ``wavelengths`` (B,) and ``reflectance`` (H, W, B);
- two-column CSV spectral curves (:func:`read_spectrum_csv`, :func:`curve_on_grid`).

Every write goes to a temporary name in the target's folder and is renamed over the target with
:func:`os.replace` at the end, so a crash never leaves a partial file under the final name. Every error is one
line that starts with the file's path.
"""

from __future__ import annotations

import errno
import math
import os
import re
import secrets
import shutil
import stat
import tokenize
import zipfile
import zlib
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from specgpu.core.validate import available_memory_bytes, check_wavelengths, normalised_to_peak

__all__ = [
    "format_channel", "parse_channel", "read_exr", "write_exr", "read_cube_exr", "write_cube_exr",
    "read_cube_npz", "write_cube_npz", "npz_members", "check_cube", "atomic_path", "one_line",
    "SPECTRAL_LAYOUT_VERSION", "new_temporary", "replace_with", "write_target", "final_name", "final_names",
    "write_failed", "disk_full", "os_error", "error_of", "read_spectrum_csv", "curve_on_grid",
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


def one_line(text: str, limit: int = 240) -> str:
    """Collapse a (possibly multi-line, repeated) library error message to one short line."""
    seen = []
    for line in str(text).splitlines():
        line = " ".join(line.split())
        if line and line not in seen:
            seen.append(line)
    out = "; ".join(seen) or "unknown error"
    return out if len(out) <= limit else out[: limit - 3] + "..."


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


_TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[A-Za-z0-9_]+\.tmp(?P<suffix>\.[^.]*)?$")
_TEMP_IN_TEXT = re.compile(r"\.[^\s\"'()/\\]*?\.\d+\.[A-Za-z0-9_]+\.tmp[^\s\"'()/\\]*")


def final_name(name: str) -> str:
    """The file a temporary name (``.<name>.<pid>.<random>.tmp<suffix>``, possibly nested: the temporary of a
    temporary) stands for; any other name unchanged. A temporary whose suffix differs from its name's is a
    companion's (an ENVI header's temporary renamed to ``.img`` for its data file): it stands for that file."""
    while True:
        m = _TEMP_NAME.match(name)
        if m is None:
            return name
        name, suffix = m.group("name"), m.group("suffix") or ""
        if suffix and Path(name).suffix != suffix:
            name = str(Path(name).with_suffix(suffix)) if Path(name).suffix else name + suffix


def final_names(text: str) -> str:
    """``text`` (an error message) with every temporary file name replaced by the name of the file it stands for:
    a message names the output the user asked for, never the temporary written on its way."""
    return _TEMP_IN_TEXT.sub(lambda m: final_name(m.group(0)), str(text))


def new_temporary(path) -> Path:
    """Create an empty temporary file beside ``path`` (``.<name>.<pid>.<random>.tmp<suffix>``) and return it.

    It is created with ``0o666`` less the process's umask (and the folder's default ACL), as the kernel applies
    them to a plain ``open(path, "w")`` (:func:`tempfile.mkstemp` would make every output ``0o600``, unreadable to
    the user's group); :func:`replace_with` gives it the mode of the file it replaces, when there is one.
    """
    path = Path(path)
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{path.suffix}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(errno.EEXIST, f"{path}: no free temporary name beside it")


def replace_with(tmp, path) -> None:
    """Rename the finished temporary ``tmp`` over ``path`` atomically; a file already at ``path`` keeps its
    permission bits, as a plain ``open()`` that truncates it would keep them (applied now, once the temporary
    is written, so a read-only file can still be replaced as before)."""
    try:
        existing = os.stat(path)
        if stat.S_ISREG(existing.st_mode):
            os.chmod(tmp, stat.S_IMODE(existing.st_mode))
    except OSError:  # no file there yet (or not ours to stat): the creation mode stands
        pass
    os.replace(tmp, path)


def write_target(path) -> Path:
    """The file a write to ``path`` replaces: ``path`` itself, or the file a symbolic link at ``path`` points to
    (as a plain ``open()`` writes through a link; renaming over the link would replace the link instead)."""
    path = Path(path)
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextmanager
def atomic_path(path: Path):
    """Yield a temporary path next to ``path`` (same suffix); on success rename it over ``path`` atomically,
    on failure remove it.

    The temporary name carries the writer's pid (``.<name>.<pid>.<random>.tmp<suffix>``), so one left by a killed
    process is recognised and removed by :func:`specgpu.core.locks.clean_stale_temporaries`. The file gets the mode a
    plain ``open()`` would give (:func:`new_temporary`); a ``path`` that is a symbolic link is written through,
    to the file it points to. An operating-system error (disk full, read-only folder) is re-raised as one line
    naming ``path``, never the temporary name; so is any error whose message names the temporary.
    """
    path = Path(path)
    target = write_target(path)
    if target.is_dir():  # found before anything is written, not by the rename at the end
        error = IsADirectoryError(f"{path}: is a folder, not a file; choose a file name")
        error.errno = errno.EISDIR
        raise error
    try:
        tmp = new_temporary(target)
    except OSError as exc:
        raise os_error(path, exc) from None
    try:
        yield tmp
        replace_with(tmp, target)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and (str(exc).startswith("[Errno") or (exc.errno is None and
                                                                         str(path) not in str(exc))):
            raise os_error(path, exc) from None  # a raw OS message ("[Errno 21] ...: 'a' -> 'b'"): one line
        text = str(exc)
        if isinstance(exc, (OSError, ValueError)) and final_names(text) != text:
            try:
                error = type(exc)(final_names(text))
            except TypeError:  # a type that needs more than a message (UnicodeDecodeError): as it was raised
                raise exc from None
            if isinstance(exc, OSError):
                error.errno = exc.errno
            raise error from None
        raise


def write_failed(path: Path, tmp: Path, label: str, message: str) -> Exception:
    """The error of a library's failed write of ``tmp`` (on its way to ``path``): one line naming ``path``, with
    the operating system's cause when the disk is full (the library says only "write error" or "scanline
    failed"), else the library's message with temporary names replaced."""
    full = disk_full(tmp.parent)
    if full is not None:
        error = OSError(f"{path}: cannot write {label} ({full})")
        error.errno = errno.ENOSPC
        return error
    return ValueError(f"{path}: cannot write {label} ({one_line(final_names(message))})")


def disk_full(folder: Path, probe_bytes: int = 1 << 20) -> str | None:
    """"No space left on device, N MB free" when the file system holding ``folder`` cannot take ``probe_bytes``
    more (a probe file written, synced and removed), else None. Called after a write failed, while its partial
    file still holds what it wrote: a full disk then has less room than one more block of it."""
    probe = None
    try:
        probe = new_temporary(Path(folder) / "space-probe")
        with open(probe, "wb") as fh:
            fh.write(bytes(probe_bytes))
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
            return None
        reason = exc.strerror or "No space left on device"
        try:
            reason += f", {shutil.disk_usage(folder).free / 1e6:.1f} MB free"
        except OSError:
            pass
        return reason
    finally:
        if probe is not None:
            try:
                probe.unlink()
            except OSError:
                pass
    return None


def os_error(path: Path, exc: OSError) -> OSError:
    """``exc`` as one line that names ``path`` (and how much room is left when the disk is full)."""
    reason = exc.strerror or one_line(str(exc))
    if exc.errno == errno.ENOSPC:
        try:
            free = shutil.disk_usage(path.parent).free
            reason += f", {free / 1e6:.1f} MB free"
        except OSError:
            pass
    error = type(exc)(f"{path}: cannot write ({reason})")
    error.errno = exc.errno
    return error


def _check_exists(path: Path, what: str) -> None:
    if not path.exists():
        raise FileNotFoundError(f"{path}: {what} not found")
    if not path.is_file():
        raise ValueError(f"{path}: {what} is not a file")


def error_of(source) -> str:
    """``source.geterror()`` (an OpenImageIO reader or the module); a message holding a corrupt file's bytes that
    are not UTF-8 would otherwise raise UnicodeDecodeError."""
    try:
        return source.geterror()
    except UnicodeDecodeError:
        return "corrupt data (error message not UTF-8)"


# ---- OpenEXR -----------------------------------------------------------------------------------------------------
def read_exr(path, what: str = "EXR") -> tuple[np.ndarray, list[str], dict]:
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
    import OpenImageIO as oiio

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


def write_exr(path, data, names, *, half: bool = False, attributes: dict | None = None) -> Path:
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
    import OpenImageIO as oiio

    path = Path(path)
    arr = np.asarray(data, dtype=np.float32)
    names = [str(n) for n in names]
    if arr.ndim != 3 or arr.shape[2] != len(names) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{path}: data must have shape (H, W, {len(names)}) with H, W >= 1, got {arr.shape}")
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: channel names must be unique, got {names}")
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
    import OpenImageIO as oiio

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


def read_cube_exr(path) -> tuple[np.ndarray, np.ndarray, dict]:
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


def check_cube(path, cube, wavelengths) -> tuple[np.ndarray, np.ndarray]:
    """Validate a cube for writing: (H, W, B) numeric and B finite, positive, unique wavelengths (nm)."""
    wl = np.asarray(wavelengths, dtype=np.float64)
    arr = np.asarray(cube)
    if wl.ndim != 1 or wl.size < 1:
        raise ValueError(f"{path}: wavelengths must have shape (B,) with B >= 1, got {wl.shape}")
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
        raise ValueError(f"{path}: wavelengths must be finite and > 0 nm, got {wl[:8].tolist()}")
    if np.unique(wl).size != wl.size:
        dup = sorted({float(v) for v in wl if np.count_nonzero(wl == v) > 1})
        raise ValueError(f"{path}: duplicate wavelength(s) {dup} nm "
                         "(wavelengths must be strictly increasing once sorted)")
    if arr.ndim != 3 or arr.shape[2] != wl.size or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{path}: cube must have shape (H, W, {wl.size}) with H, W >= 1, got {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{path}: cube must be numeric, got dtype {arr.dtype}")
    return arr, wl


def write_cube_exr(path, cube, wavelengths, *, half: bool = False, attributes: dict | None = None) -> Path:
    """Write an (H, W, B) cube as JCGT 2021 reflective channels ``T.<wl>nm`` (float32 or half), atomically.

    The header carries ``spectralLayoutVersion = "1.0"`` plus ``attributes``.
    """
    path = Path(path)
    arr, wl = check_cube(path, cube, wavelengths)
    attrs = {"spectralLayoutVersion": SPECTRAL_LAYOUT_VERSION}
    attrs.update(attributes or {})
    return write_exr(path, arr, [format_channel(v) for v in wl], half=half, attributes=attrs)


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


def read_cube_npz(path) -> tuple[np.ndarray, np.ndarray, dict]:
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


def wavelength_order(path, wl) -> np.ndarray:
    """The order that sorts a cube file's band wavelengths ``wl`` (nm); one line naming ``path`` for a non-finite,
    non-positive or repeated wavelength (bands are ordered by wavelength, never by their order in the file)."""
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
        raise ValueError(f"{path}: wavelengths must be finite and > 0 nm, got {wl[:8].tolist()}")
    order = np.argsort(wl, kind="stable")
    wl = wl[order]
    dup = np.unique(wl[1:][np.diff(wl) == 0])
    if dup.size:
        raise ValueError(f"{path}: duplicate wavelength(s) {dup.tolist()} nm "
                         "(wavelengths must be strictly increasing once sorted)")
    return order


def write_cube_npz(path, cube, wavelengths, extra: dict | None = None) -> Path:
    """Write a cube as compressed ``.npz`` (``wavelengths``, ``reflectance`` plus ``extra`` arrays), atomically."""
    path = Path(path)
    arr, wl = check_cube(path, cube, wavelengths)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    arrays = {"wavelengths": wl, "reflectance": arr}
    arrays.update(extra or {})
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:  # a file object: np.savez would otherwise append ".npz" to the temp name
            np.savez_compressed(fh, **arrays)
    return path


# ---- CSV spectral curves -----------------------------------------------------------------------------------------
def read_spectrum_csv(path) -> tuple[np.ndarray, np.ndarray]:
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
