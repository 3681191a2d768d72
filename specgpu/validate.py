"""Small validators whose messages name the argument, the shape found and the shape wanted.

Each returns the normalised value (float32 where the device wants float32) or raises ``ValueError`` /
``TypeError`` with a one-line message. Device arrays (:class:`pyopencl.array.Array`) are checked for shape and
dtype only: scanning them for NaN would cost a transfer.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyopencl.array as cla

from specgpu.checks import available_memory_bytes

__all__ = [
    "FRAME_DTYPES",
    "is_device_array",
    "as_float32",
    "validate_method",
    "check_frames",
    "check_matrix",
    "check_pixel_map",
    "check_last_axis",
    "check_wavelengths",
    "check_out_dtype",
]

FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
OUT_DTYPES = (np.dtype(np.float32), np.dtype(np.float16))


def is_device_array(a) -> bool:
    return isinstance(a, cla.Array)


def _shape(a) -> str:
    return "(" + ", ".join(str(s) for s in a.shape) + ")"


def validate_method(method: str, methods: Mapping, argument: str = "method"):
    """The entry of ``methods`` named ``method`` (case-insensitive); ValueError listing the valid names."""
    if isinstance(method, str):
        for name, value in methods.items():
            if name.lower() == method.lower():
                return value
    raise ValueError(f"{argument}={method!r} is not one of {', '.join(repr(m) for m in methods)}")


def check_frames(frames, name: str = "frames"):
    """A stack of K frames, shape (K, *spatial), dtype uint8, uint16 or float32 (float64 becomes float32).

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
            raise TypeError(f"{name} has dtype {frames.dtype}; supported: uint8, uint16, float32 (float64 is converted)")
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


def check_pixel_map(a, name: str, spatial: tuple[int, ...], planes: int | None = None):
    """A per-pixel float map of shape ``spatial`` or, when ``planes`` is given, also (planes, *spatial).

    Returns (float32 array or device array, per_plane flag). Non-finite values are refused: calibration
    data (dark frames, flat fields) must be finite.
    """
    allowed = [tuple(spatial)] + ([(planes, *spatial)] if planes else [])
    a = as_float32(a, name)
    if not is_device_array(a):
        bad = ~np.isfinite(a)
        if bad.any():
            raise ValueError(f"{name} contains NaN or inf at {int(bad.sum())} pixels")
    if tuple(a.shape) not in allowed:
        wanted = " or ".join("(" + ", ".join(map(str, s)) + ")" for s in allowed)
        raise ValueError(f"{name} has shape {_shape(a)}, expected {wanted} to match the frames")
    return a, tuple(a.shape) != tuple(spatial)


def check_last_axis(a, name: str, size: int = 3, allow_single: bool = True):
    """An array with ``size`` channels on its last axis, float32 (NumPy input converted, NaN allowed)."""
    a = as_float32(a, name)
    if a.ndim == 0 or a.shape[-1] != size:
        raise ValueError(f"{name} must have {size} channels on its last axis, got shape {_shape(a)}")
    if a.ndim == 1 and not allow_single:
        raise ValueError(f"{name} must be an image (..., {size}), got a single colour {_shape(a)}")
    return a


def check_wavelengths(wavelengths, bands: int, name: str = "wavelengths") -> np.ndarray:
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
