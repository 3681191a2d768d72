"""The band checks every cube format shares: a cube to write, and the wavelength order of a cube read."""

from __future__ import annotations

import numpy as np

__all__ = ["check_cube", "wavelength_order"]


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
