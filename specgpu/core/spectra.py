"""Wavelength grids, spectral tables and interop with colour-science objects (host side, float64).

colour-science is the source of colorimetric data: colour-matching functions (``colour.MSDS_CMFS``),
illuminant spectra (``colour.SDS_ILLUMINANTS``) and chromaticities (``colour.CCS_ILLUMINANTS``).
"""

from __future__ import annotations

import functools

import colour
import numpy as np

from specgpu.core.validate import BadArgument

__all__ = [
    "DEFAULT_CMFS",
    "OBSERVERS",
    "spectral_shape",
    "resolve_cmfs",
    "resolve_illuminant_sd",
    "white_point_XYZ",
    "XYZ_weights",
]

DEFAULT_CMFS = "CIE 1931 2 Degree Standard Observer"
#: The observers XYZ, Lab and dE can be made for: colour-matching functions with an illuminant white-point table
OBSERVERS = tuple(name for name in colour.CCS_ILLUMINANTS if name in colour.MSDS_CMFS and "Observer" in name)


def spectral_shape(wavelengths: np.ndarray) -> colour.SpectralShape:
    """The colour-science shape of an evenly spaced wavelength grid (nm)."""
    w = np.asarray(wavelengths, dtype=np.float64)
    interval = float(w[1] - w[0]) if w.size > 1 else 1.0
    return colour.SpectralShape(float(w[0]), float(w[-1]), interval)


def resolve_cmfs(cmfs) -> colour.MultiSpectralDistributions:
    """Colour-matching functions by name (a key of ``colour.MSDS_CMFS``) or as given."""
    if isinstance(cmfs, colour.MultiSpectralDistributions):
        return cmfs
    if isinstance(cmfs, str):
        for name in colour.MSDS_CMFS:
            if name.lower() == cmfs.lower():
                return colour.MSDS_CMFS[name]
        observers = [n for n in colour.MSDS_CMFS if "Observer" in n]
        raise BadArgument(f"cmfs={cmfs!r} is not a known observer; try one of {observers}")
    raise TypeError(f"cmfs must be a name or colour.MultiSpectralDistributions, not {type(cmfs).__name__}")


def resolve_illuminant_sd(illuminant) -> colour.SpectralDistribution:
    """An illuminant spectrum by name (a key of ``colour.SDS_ILLUMINANTS``, e.g. ``"D65"``, ``"A"``) or as given."""
    if isinstance(illuminant, colour.SpectralDistribution):
        return illuminant
    if isinstance(illuminant, str):
        for name in colour.SDS_ILLUMINANTS:
            if name.lower() == illuminant.lower():
                return colour.SDS_ILLUMINANTS[name]
        raise BadArgument(
            f"illuminant={illuminant!r} has no spectrum in colour.SDS_ILLUMINANTS (e.g. 'D65', 'A', 'D50', 'FL2')"
        )
    raise TypeError(
        f"illuminant must be a name or colour.SpectralDistribution, not {type(illuminant).__name__}"
    )


def white_point_XYZ(illuminant="D65", observer: str = DEFAULT_CMFS) -> np.ndarray:
    """Reference white XYZ with Yn = 1 (float64, shape (3,)).

    Parameters
    ----------
    illuminant : str or array_like
        A name of ``colour.CCS_ILLUMINANTS[observer]`` (``"D65"``, ``"A"`` ...), chromaticity ``xy`` (2,), or a
        white ``XYZ`` (3,) used as given.
    observer : str
        The observer whose chromaticity table names are looked up.
    """
    if isinstance(illuminant, str):
        if observer not in colour.CCS_ILLUMINANTS:
            raise ValueError(f"observer={observer!r} has no illuminant table; try {list(colour.CCS_ILLUMINANTS)}")
        table = colour.CCS_ILLUMINANTS[observer]
        for name, xy in table.items():
            if name.lower() == illuminant.lower():
                return np.asarray(colour.xy_to_XYZ(xy), dtype=np.float64)
        raise ValueError(f"illuminant={illuminant!r} is not in colour.CCS_ILLUMINANTS[{observer!r}] "
                         f"(e.g. 'D65', 'A', 'D50', 'E')")
    value = np.asarray(illuminant, dtype=np.float64)
    if value.shape == (2,):
        if not np.all(np.isfinite(value)) or value[1] <= 0:
            raise ValueError(f"illuminant chromaticity xy={value.tolist()} is not valid (y must be > 0)")
        return np.asarray(colour.xy_to_XYZ(value), dtype=np.float64)
    if value.shape == (3,):
        if not np.all(np.isfinite(value)) or np.any(value <= 0):
            raise ValueError(f"illuminant white XYZ={value.tolist()} must be finite and positive")
        return value
    raise ValueError(f"illuminant must be a name, xy (2,) or white XYZ (3,), got shape {value.shape}")


def XYZ_weights(wavelengths, illuminant="D65", cmfs=DEFAULT_CMFS) -> np.ndarray:
    """The 3 x B matrix W with XYZ = W . R for reflectance R sampled at ``wavelengths``.

    The weights are those of colour-science's ``msds_to_XYZ_integration`` (illuminant and colour-matching
    functions aligned to the grid, rectangle rule), normalised so that the perfect reflecting diffuser has
    Y = 1 (colour-science scales the same quantity to 100).

    Parameters
    ----------
    wavelengths : array_like, (B,)
        Evenly spaced wavelengths in nm.
    illuminant : str or colour.SpectralDistribution
        A name of ``colour.SDS_ILLUMINANTS`` or a spectral distribution.
    cmfs : str or colour.MultiSpectralDistributions
        A name of ``colour.MSDS_CMFS`` or colour-matching functions.

    Returns
    -------
    ndarray, (3, B), float64
        Rows X, Y, Z; each row sums to the white's tristimulus value (Y's row to 1).

    Examples
    --------
    >>> import numpy as np
    >>> from specgpu.core import XYZ_weights
    >>> W = XYZ_weights(np.arange(400, 701, 10), "D65")
    >>> W.shape
    (3, 31)
    >>> W.sum(axis=1).round(4).tolist()
    [0.9494, 1.0, 1.0871]
    """
    w = np.asarray(wavelengths, dtype=np.float64)
    if isinstance(illuminant, str) and isinstance(cmfs, str):  # by name: computed once per grid (~1.4 ms each)
        return _XYZ_weights_named(tuple(w.tolist()), illuminant, cmfs).copy()
    return _XYZ_weights(w, illuminant, cmfs)


@functools.lru_cache(maxsize=64)
def _XYZ_weights_named(wavelengths: tuple, illuminant: str, cmfs: str) -> np.ndarray:
    return _XYZ_weights(np.asarray(wavelengths), illuminant, cmfs)


def _XYZ_weights(w: np.ndarray, illuminant, cmfs) -> np.ndarray:
    shape = spectral_shape(w)
    try:
        cmfs_sd = resolve_cmfs(cmfs).copy().align(shape)
        illum_sd = resolve_illuminant_sd(illuminant).copy().align(shape)
    except AssertionError:  # colour-science asserts when the grid lies outside the tables
        domain = resolve_cmfs(cmfs).shape
        raise ValueError(f"wavelengths {w.min():g}-{w.max():g} nm lie outside the colour-matching functions' "
                         f"{domain.start:g}-{domain.end:g} nm") from None
    cmf = np.asarray(cmfs_sd.values, dtype=np.float64)  # (B, 3)
    E = np.asarray(illum_sd.values, dtype=np.float64)  # (B,)
    dw = shape.interval
    k = 1.0 / np.sum(E * cmf[:, 1] * dw)
    return (k * E[:, None] * cmf * dw).T
