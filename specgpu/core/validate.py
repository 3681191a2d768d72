"""The project's validators: one module, one message style.

Every check returns the normalised value or raises ``ValueError`` / ``TypeError`` with one line that names the
argument (or file), the problem, and where it helps the shape found and the shape wanted, so a rig description,
a scene file or an array with a bad value fails with a clear reason instead of a wrong result.

Two families share it: scalar and host-array checks for descriptions and files (``check_number``,
``check_array``, ``check_wavelengths``: the name comes first) and the device-facing array checks of the kernels'
entry points (``check_frames``, ``check_matrix``, ``check_pixel_map``, ``check_band_wavelengths``: float32 where
the device wants float32). Device arrays (:class:`pyopencl.array.Array`) are checked for shape and dtype only:
scanning them for NaN would cost a transfer.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping

import numpy as np


class BadArgument(ValueError):
    """A value the caller chose is not one the function takes (an unknown name, an output over an input): the
    caller's mistake, not the data's, so the command line reports it as a usage error (exit status 2)."""


def check_number(name: str, value, *, low=None, high=None, low_open=False, integer=False) -> float:
    """Return ``value`` as a float (or int) after checking it is finite and inside ``[low, high]``.

    Parameters
    ----------
    name
        Name of the quantity, used in the error message.
    value
        The value to check.
    low, high
        Optional inclusive bounds; ``low_open=True`` makes the lower bound exclusive.
    integer
        Require an integral value and return an ``int``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    if isinstance(value, (int, np.integer)):
        value = int(value)  # exact: no round trip through float for large integers
        if not integer:
            value = float(value)
    else:
        if not math.isfinite(float(value)):
            raise ValueError(f"{name} must be finite, got {value!r}")
        if integer:
            if not float(value).is_integer():
                raise ValueError(f"{name} must be an integer, got {value!r}")
            value = int(value)
        else:
            value = float(value)
    if low is not None and (value <= low if low_open else value < low):
        raise ValueError(f"{name} must be {'>' if low_open else '>='} {low}, got {value!r}")
    if high is not None and value > high:
        raise ValueError(f"{name} must be <= {high}, got {value!r}")
    return value


def check_array(name: str, array, *, ndim=None, shape=None, finite=True, low=None, high=None,
                dtype=np.float64) -> np.ndarray:
    """Return ``array`` as a NumPy array after checking dimensions, shape, finiteness and range.

    ``shape`` may hold ``None`` for axes of any length. Messages name the argument and the shape found.
    """
    try:
        arr = np.asarray(array, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array ({exc})") from None
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    if shape is not None:
        if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
            want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
            raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if finite and arr.size and not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise ValueError(f"{name} contains {bad} NaN or infinite value(s)")
    if low is not None and arr.size and float(arr.min()) < low:
        raise ValueError(f"{name} must be >= {low}, got minimum {float(arr.min())!r}")
    if high is not None and arr.size and float(arr.max()) > high:
        raise ValueError(f"{name} must be <= {high}, got maximum {float(arr.max())!r}")
    return arr


def check_wavelengths(name: str, wavelengths) -> np.ndarray:
    """Return a 1-D, finite, strictly increasing wavelength array in nm (at least two samples)."""
    wl = check_array(name, wavelengths, ndim=1)
    if wl.size < 2:
        raise ValueError(f"{name} must hold at least 2 wavelengths, got {wl.size}")
    if np.any(np.diff(wl) <= 0):
        raise ValueError(f"{name} must be strictly increasing (nm), got {wl[:6].tolist()}...")
    if wl[0] < 100 or wl[-1] > 3000:
        raise ValueError(f"{name} must lie in 100-3000 nm, got {wl[0]:g}-{wl[-1]:g}")
    return wl


def normalised_to_peak(values: np.ndarray, wavelengths: np.ndarray, zero_message: str) -> np.ndarray:
    """``values / max(values)``; a curve with no positive value is an error saying ``zero_message`` and the range."""
    peak = float(values.max()) if values.size else 0.0
    if not peak > 0:
        raise ValueError(f"{zero_message} between {wavelengths.min():g} and {wavelengths.max():g} nm")
    return values / peak


def available_memory_bytes() -> int | None:
    """Memory the system can still give this process now (Linux: ``MemAvailable``; elsewhere the free physical
    pages), or None where unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None

FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
OUT_DTYPES = (np.dtype(np.float32), np.dtype(np.float16))


def is_device_array(a: object) -> bool:
    """Whether ``a`` is a device array (:class:`pyopencl.array.Array`).

    Only a process that has imported pyopencl can hold one, so the check never imports OpenCL itself.
    """
    cla = sys.modules.get("pyopencl.array")
    return cla is not None and isinstance(a, cla.Array)


def _shape(a) -> str:
    return "(" + ", ".join(str(s) for s in a.shape) + ")"


def validate_method(method: str, methods: Mapping, argument: str = "method"):
    """The entry of ``methods`` named ``method`` (case-insensitive); :class:`BadArgument` (a ValueError) listing
    the valid names."""
    if isinstance(method, str):
        for name, value in methods.items():
            if name.lower() == method.lower():
                return value
    raise BadArgument(f"{argument}={method!r} is not one of {', '.join(repr(m) for m in methods)}")


def check_frames(frames, name: str = "frames"):
    """A stack of K frames, shape ``(K, *spatial)``, dtype uint8, uint16 or float32 (float64 becomes float32).

    Returns the array (NumPy, C-contiguous, or the device array as given) and K.
    """
    if is_device_array(frames):
        if frames.dtype not in FRAME_DTYPES:
            raise TypeError(f"{name} has dtype {frames.dtype}; supported: uint8, uint16, float32")
        if not frames.flags.c_contiguous:
            raise ValueError(f"{name} device array must be C-contiguous")
    else:
        frames = np.asarray(frames)
        if frames.dtype == np.float64:
            finite = frames[np.isfinite(frames)]
            if finite.size and np.max(np.abs(finite)) > np.finfo(np.float32).max:
                raise ValueError(f"{name} has values beyond float32 range (max |value| {np.max(np.abs(finite)):.3g})")
            frames = frames.astype(np.float32)
        if frames.dtype not in FRAME_DTYPES:
            raise TypeError(f"{name} has dtype {frames.dtype}; supported: uint8, uint16, float32 "
                            "(float64 is converted)")
        frames = np.ascontiguousarray(frames)
    if frames.ndim < 2:
        raise ValueError(f"{name} must have shape (K, H, W) or (K, N), got {_shape(frames)}")
    if frames.shape[0] < 1:
        raise ValueError(f"{name} holds no frame (K = 0), shape {_shape(frames)}")
    return frames, frames.shape[0]


def check_matrix(A, name: str = "A", columns: int | None = None, rows: int | None = None,
                 columns_from: str = "frames") -> np.ndarray:
    """A finite 2-D matrix, returned float32 C-contiguous; ``columns`` / ``rows`` enforce its shape."""
    if np.iscomplexobj(A):  # the imaginary part would be dropped silently
        raise TypeError(f"{name} is complex; a decoder must be real")
    try:
        A = np.asarray(A, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a numeric matrix, got {type(A).__name__}") from None
    if A.ndim != 2:
        raise ValueError(f"{name} must be a 2-D matrix, got shape {_shape(A)}")
    if rows is not None and A.shape[0] != rows:
        raise ValueError(f"{name} has {A.shape[0]} rows, expected {rows}: shape {_shape(A)}")
    if columns is not None and A.shape[1] != columns:
        raise ValueError(
            f"{name} has {A.shape[1]} columns but {columns_from} has K = {columns} frames: shape {_shape(A)}"
        )
    if A.size == 0:
        raise ValueError(f"{name} is empty: shape {_shape(A)}")
    if not np.all(np.isfinite(A)):
        raise ValueError(f"{name} contains NaN or inf ({int(np.sum(~np.isfinite(A)))} entries)")
    if np.max(np.abs(A)) > np.finfo(np.float32).max:
        raise ValueError(f"{name} has entries beyond float32 range")
    return np.ascontiguousarray(A, dtype=np.float32)


def as_float32(a, name: str):
    """``a`` as C-contiguous float32: NumPy input converted (it must be numeric), a device array checked."""
    if is_device_array(a):
        if a.dtype != np.float32:
            raise TypeError(f"{name} device array must be float32, got {a.dtype}")
        if not a.flags.c_contiguous:
            raise ValueError(f"{name} device array must be C-contiguous")
        return a
    a = np.asarray(a)
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise TypeError(f"{name} must be numeric, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float32)


def check_pixel_map(a, name: str, spatial: tuple[int, ...], planes: int | None = None, *,
                    nan_marks_dead: bool = False):
    """A per-pixel float map of shape ``spatial`` or, when ``planes`` is given, also ``(planes, *spatial)``.

    Returns (float32 array or device array, per_plane flag). Non-finite values are refused: calibration
    data (dark frames, flat fields) must be finite. With ``nan_marks_dead`` (a gain map) NaN is allowed: it marks a
    pixel with no response (:func:`specgpu.core.numerics.live_gain`), whose outputs are NaN; inf is still refused.
    """
    allowed = [tuple(spatial)] + ([(planes, *spatial)] if planes else [])
    a = as_float32(a, name)
    if not is_device_array(a):
        bad = np.isinf(a) if nan_marks_dead else ~np.isfinite(a)
        if bad.any():
            raise ValueError(f"{name} contains {'inf' if nan_marks_dead else 'NaN or inf'} at {int(bad.sum())} "
                             "pixels")
    if tuple(a.shape) not in allowed:
        wanted = " or ".join("(" + ", ".join(map(str, s)) + ")" for s in allowed)
        raise ValueError(f"{name} has shape {_shape(a)}, expected {wanted} to match the frames")
    return a, tuple(a.shape) != tuple(spatial)


def check_gain_map(a, spatial: tuple[int, ...]):
    """A flat field (``gain``) of shape ``spatial`` as :func:`check_pixel_map` checks it, NaN allowed (a pixel with
    no response); returns the float32 array or device array."""
    return check_pixel_map(a, "gain", spatial, None, nan_marks_dead=True)[0]


def check_last_axis(a, name: str, size: int = 3, allow_single: bool = True):
    """An array with ``size`` channels on its last axis, float32 (NumPy input converted, NaN allowed)."""
    a = as_float32(a, name)
    if a.ndim == 0 or a.shape[-1] != size:
        raise ValueError(f"{name} must have {size} channels on its last axis, got shape {_shape(a)}")
    if a.ndim == 1 and not allow_single:
        raise ValueError(f"{name} must be an image (..., {size}), got a single colour {_shape(a)}")
    return a


def check_band_wavelengths(wavelengths, bands: int, name: str = "wavelengths") -> np.ndarray:
    """Strictly increasing, evenly spaced, finite wavelengths in nm, one per band (float64)."""
    w = np.asarray(wavelengths, dtype=np.float64)
    if w.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {_shape(w)}")
    if w.size != bands:
        raise ValueError(f"{name} has {w.size} entries but the data has {bands} bands on its last axis")
    if not np.all(np.isfinite(w)):
        raise ValueError(f"{name} contains NaN or inf")
    if w.size > 1:
        steps = np.diff(w)
        if np.any(steps <= 0):
            raise ValueError(f"{name} must be strictly increasing")
        if np.ptp(steps) > 1e-6 * max(1.0, float(steps.mean())):
            raise ValueError(
                f"{name} must be evenly spaced (steps range {steps.min():g} to {steps.max():g} nm)"
            )
    return w


def check_out_dtype(dtype) -> np.dtype:
    dt = np.dtype(dtype)
    if dt not in OUT_DTYPES:
        raise TypeError(f"out_dtype must be float32 or float16, got {dt}")
    return dt


def check_level(value, name: str = "saturation") -> float:
    """A finite real number (a saturation level, DN), returned as float; None stays None."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not np.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def check_result_size(nbytes: int, device, *, host_copies: int = 1, what: str = "result") -> None:
    """Refuse, before any allocation, a result larger than the device's largest buffer, or than the memory left
    for it on the host (``host_copies`` times its size): a one-line ValueError with the figures, never a raw
    allocation error or the OOM killer."""
    limit = int(getattr(device, "max_mem_alloc_size", 0) or 0)
    if limit and nbytes > limit:
        raise ValueError(f"the {what} needs {nbytes / 1e9:.2f} GB, more than the largest buffer of "
                         f"{getattr(device, 'name', 'the device').strip()} ({limit / 1e9:.2f} GB); process the "
                         "frames in tiles")
    free = available_memory_bytes()
    if host_copies and free is not None and nbytes * host_copies > free:
        raise ValueError(f"the {what} needs {nbytes * host_copies / 1e9:.2f} GB of memory, {free / 1e9:.2f} GB are "
                         "available; process the frames in tiles")


def check_sequence(sequence, count: int, where) -> None:
    """Refuse, in one line naming ``where``, a sequence index outside the ``count`` sequences held there (the one
    range check of a sequence index, whoever reads the sequences)."""
    if sequence is not None and not 0 <= sequence < count:
        raise ValueError(f"sequence {sequence} is out of range: {where} holds {count}")
