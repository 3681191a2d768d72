"""Small validators shared by every room (rig, capture, hardware, file formats).

Every message is one line that names the argument (or file) and the problem, so a rig description or a
scene file with a bad value fails with a clear reason instead of a wrong simulation.
"""

from __future__ import annotations

import math
import os

import numpy as np


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
