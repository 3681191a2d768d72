"""Wavelength grids, spectral tables and interop with colour-science objects (host side, float64).

colour-science is the source of colorimetric data: colour-matching functions (``colour.MSDS_CMFS``) and
illuminant spectra (``colour.SDS_ILLUMINANTS``).

One definition of the reference white serves every XYZ, Lab and dE of the package: the white is the XYZ of the
perfect reflecting diffuser integrated with the very weights the reflectance is integrated with
(:func:`white_point_XYZ` is ``XYZ_weights(...).sum(axis=1)``), so a perfect white is L* = 100, a* = b* = 0 on
any grid, under any illuminant, for either observer. Two integrations (:data:`INTEGRATIONS`):

- ``"rectangle"`` (the default): the rectangle rule on the cube's own grid, illuminant and colour-matching
  functions sampled at its wavelengths, nothing outside the grid counted;
- ``"ASTM E308"``: the tables of ASTM E308 as colour-science builds them (``sd_to_XYZ(method="ASTM E308")``):
  1 and 5 nm grids integrated against the 360-780 nm functions, 10 and 20 nm grids through the ASTM E2022
  weighting factors, the weight outside the grid added to its end bands. It is what colorimetry software and
  instruments report; it needs a grid of 1, 5, 10 or 20 nm intervals on wavelengths that are multiples of
  the interval (of 10 nm for 10 and 20 nm), and refuses another in one line.
"""

from __future__ import annotations

import functools
import warnings
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.validate import BadArgument, validate_method

if TYPE_CHECKING:
    import colour

__all__ = [
    "DEFAULT_CMFS",
    "OBSERVERS",
    "spectral_shape",
    "resolve_cmfs",
    "resolve_illuminant_sd",
    "white_point_XYZ",
    "XYZ_weights",
    "INTEGRATIONS",
    "ASTM_E308_INTERVALS",
    "WHITE_WAVELENGTHS",
    "resolve_integration",
]

DEFAULT_CMFS = "CIE 1931 2 Degree Standard Observer"
#: The observers XYZ, Lab and dE can be made for: colour-matching functions with an illuminant white-point table
#: (read from colour-science on first use, by the module's ``__getattr__``)
OBSERVERS: tuple[str, ...]
#: How reflectance is integrated to XYZ (the keys; the CLI's ``--integration`` takes the short spellings too)
INTEGRATIONS = {"rectangle": "rectangle", "ASTM E308": "ASTM E308", "astm-e308": "ASTM E308"}
#: The measurement intervals (nm) ASTM E308 has tables for
ASTM_E308_INTERVALS = (1, 5, 10, 20)
#: The grid of a white asked for by name with no grid (an XYZ integrated elsewhere): colour-science's default
#: spectral shape, 360-780 nm at 1 nm
WHITE_WAVELENGTHS = np.arange(360.0, 781.0, 1.0)


@functools.cache
def _observers() -> tuple[str, ...]:
    import colour  # colour-science takes seconds to import: loaded by the first function that needs its tables

    return tuple(name for name in colour.CCS_ILLUMINANTS if name in colour.MSDS_CMFS and "Observer" in name)


def __getattr__(name: str):
    # OBSERVERS is read from colour-science's tables, so it is made on first use (PEP 562), not at import
    if name == "OBSERVERS":
        return _observers()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def resolve_integration(integration: str) -> str:
    """The canonical name of an integration of :data:`INTEGRATIONS` (case-insensitive); ValueError listing them."""
    return validate_method(integration, INTEGRATIONS, "integration")


def spectral_shape(wavelengths: np.ndarray) -> colour.SpectralShape:
    """The colour-science shape of an evenly spaced wavelength grid (nm)."""
    import colour
    w = np.asarray(wavelengths, dtype=np.float64)
    interval = float(w[1] - w[0]) if w.size > 1 else 1.0
    return colour.SpectralShape(float(w[0]), float(w[-1]), interval)


def resolve_cmfs(cmfs) -> colour.MultiSpectralDistributions:
    """Colour-matching functions by name (a key of ``colour.MSDS_CMFS``) or as given."""
    import colour
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
    import colour
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


def white_point_XYZ(illuminant: str = "D65", observer=DEFAULT_CMFS, *, wavelengths: ArrayLike | None = None,
                    integration: str = "rectangle") -> np.ndarray:
    """The reference white of XYZ, Lab and dE: the XYZ of the perfect reflecting diffuser (float64, (3,)).

    For an illuminant given by name or spectrum it is the sum of :func:`XYZ_weights`' rows on ``wavelengths``,
    the integral of a reflectance of 1 with the very weights a cube on that grid is integrated with (Y = 1), so
    that a perfect white is exactly L* = 100, a* = b* = 0. Every Lab and dE of the package takes its white from
    here.

    Parameters
    ----------
    illuminant : str, colour.SpectralDistribution or array_like
        A name of ``colour.SDS_ILLUMINANTS`` (``"D65"``, ``"A"`` ...) or a spectrum; or the white given outright,
        as chromaticity ``xy`` (2,) or ``XYZ`` (3,), used as given (``wavelengths`` and ``integration`` unused).
    observer : str or colour.MultiSpectralDistributions
        The observer's colour-matching functions.
    wavelengths : array_like, (B,), optional
        The grid the XYZ was integrated on (evenly spaced, nm); None: :data:`WHITE_WAVELENGTHS`.
    integration : str
        ``"rectangle"`` or ``"ASTM E308"`` (:data:`INTEGRATIONS`), as the XYZ was integrated.

    Examples
    --------
    >>> import numpy as np
    >>> from specgpu.core.spectra import white_point_XYZ
    >>> white_point_XYZ("D65", wavelengths=np.arange(400, 701, 10)).round(4).tolist()
    [0.9494, 1.0, 1.0871]
    """
    import colour
    if isinstance(illuminant, (str, colour.SpectralDistribution)):
        if isinstance(illuminant, str) and isinstance(observer, str) \
                and not any(o.lower() == observer.lower() for o in _observers()):
            raise ValueError(f"observer={observer!r} has no illuminant table; try one of {list(_observers())}")
        grid = WHITE_WAVELENGTHS if wavelengths is None else wavelengths
        return XYZ_weights(grid, illuminant, observer, integration=integration).sum(axis=1)
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


def XYZ_weights(wavelengths: ArrayLike, illuminant: str = "D65", cmfs=DEFAULT_CMFS, *,
                integration: str = "rectangle") -> np.ndarray:
    """The 3 x B matrix W with XYZ = W . R for reflectance R sampled at ``wavelengths``.

    ``"rectangle"``: the weights of colour-science's ``msds_to_XYZ_integration`` on the grid itself (illuminant
    and colour-matching functions aligned to the grid, rectangle rule, nothing outside the grid counted).
    ``"ASTM E308"``: the weights of colour-science's ``sd_to_XYZ(method="ASTM E308")`` (see the module's
    notes), so ``W . R`` equals its XYZ. Either is normalised so that the perfect reflecting diffuser has
    Y = 1 (colour-science scales the same quantity to 100); the rows' sums are the white of
    :func:`white_point_XYZ`.

    Parameters
    ----------
    wavelengths : array_like, (B,)
        Evenly spaced wavelengths in nm.
    illuminant : str or colour.SpectralDistribution
        A name of ``colour.SDS_ILLUMINANTS`` or a spectral distribution.
    cmfs : str or colour.MultiSpectralDistributions
        A name of ``colour.MSDS_CMFS`` or colour-matching functions.
    integration : str
        ``"rectangle"`` (default) or ``"ASTM E308"`` (:data:`INTEGRATIONS`, case-insensitive).

    Returns
    -------
    ndarray, (3, B), float64
        Rows X, Y, Z; each row sums to the white's tristimulus value (Y's row to 1).

    Raises
    ------
    ValueError
        A grid outside the colour-matching functions, an unknown integration, or an ASTM E308 integration on a
        grid it has no table for (:class:`specgpu.core.validate.BadArgument`: the caller's choice, a usage error
        on the command line).

    Examples
    --------
    >>> import numpy as np
    >>> from specgpu.core import XYZ_weights
    >>> W = XYZ_weights(np.arange(400, 701, 10), "D65")
    >>> W.shape
    (3, 31)
    >>> W.sum(axis=1).round(4).tolist()
    [0.9494, 1.0, 1.0871]
    >>> XYZ_weights(np.arange(400, 701, 10), "D65", integration="ASTM E308").sum(axis=1).round(4).tolist()
    [0.9505, 1.0, 1.0888]
    """
    w = np.asarray(wavelengths, dtype=np.float64)
    integration = resolve_integration(integration)
    if isinstance(illuminant, str) and isinstance(cmfs, str):  # by name: computed once per grid (~1.4 ms each)
        return _XYZ_weights_named(tuple(w.tolist()), illuminant, cmfs, integration).copy()
    return _XYZ_weights(w, illuminant, cmfs, integration)


@functools.lru_cache(maxsize=64)
def _XYZ_weights_named(wavelengths: tuple, illuminant: str, cmfs: str, integration: str) -> np.ndarray:
    return _XYZ_weights(np.asarray(wavelengths), illuminant, cmfs, integration)


def _XYZ_weights(w: np.ndarray, illuminant, cmfs, integration: str) -> np.ndarray:
    if integration == "ASTM E308":
        return _ASTM_E308_weights(w, resolve_illuminant_sd(illuminant), resolve_cmfs(cmfs))
    shape = spectral_shape(w)
    try:
        cmfs_sd = resolve_cmfs(cmfs).copy().align(shape)
        illum_sd = resolve_illuminant_sd(illuminant).copy().align(shape)
    except AssertionError:  # colour-science asserts when the grid lies outside the tables
        domain = resolve_cmfs(cmfs).shape
        raise ValueError(f"wavelengths {w.min():g}-{w.max():g} nm lie outside the colour-matching functions' "
                         f"{domain.start:g}-{domain.end:g} nm") from None
    # read at the grid's own wavelengths: aligning a table of another interval can keep a sample of its own
    # (the ISO 7589 illuminants, 350-690 nm every 10 nm, aligned to 400-700 nm every 20 nm keep 690 nm)
    cmf = np.asarray(cmfs_sd[w], dtype=np.float64).reshape(w.size, 3)  # (B, 3)
    E = np.asarray(illum_sd[w], dtype=np.float64).reshape(w.size)  # (B,)
    dw = shape.interval
    k = 1.0 / np.sum(E * cmf[:, 1] * dw)
    return (k * E[:, None] * cmf * dw).T


def _ASTM_E308_weights(w: np.ndarray, illuminant, cmfs) -> np.ndarray:
    """The weights of colour-science's ASTM E308 XYZ, which is linear in the reflectance: for 10 and 20 nm its
    XYZ of the B unit spectra (one call over the identity), for 1 and 5 nm the rectangle weights it integrates
    with, folded onto the grid. The grid is checked first, so colour-science never reshapes it."""
    import colour
    step = float(w[1] - w[0]) if w.size > 1 else 0.0
    interval = int(round(step))
    if w.size < 2 or interval not in ASTM_E308_INTERVALS or abs(step - interval) > 1e-9 \
            or not np.allclose(np.diff(w), step, rtol=0, atol=1e-9):
        intervals = ", ".join(map(str, ASTM_E308_INTERVALS))
        raise BadArgument(f"integration 'ASTM E308' has tables for grids of {intervals} nm intervals, not "
                         f"wavelengths {w[0]:g}-{w[-1]:g} nm every {step:g} nm; use integration 'rectangle' or "
                         "resample the cube")
    base = min(interval, 10)
    if abs(w[0] / base - round(w[0] / base)) > 1e-9:
        raise BadArgument(f"integration 'ASTM E308' needs a {interval} nm grid on multiples of {base} nm, not one "
                         f"starting at {w[0]:g} nm; use integration 'rectangle' or resample the cube")
    inside = (w >= 360.0 - 1e-9) & (w <= 780.0 + 1e-9)
    if not inside.any():
        raise BadArgument(f"integration 'ASTM E308' covers 360-780 nm, not wavelengths {w[0]:g}-{w[-1]:g} nm")
    if interval in (1, 5):
        # colour-science integrates these by the rectangle rule against the 360-780 nm functions at the grid's
        # interval, the reflectance held at its end values beyond the grid: the rectangle weights of that range,
        # those beyond the grid added to its end bands (one call instead of one per band)
        full = np.arange(360.0, 780.0 + 1e-9, interval)
        W_full = _XYZ_weights(full, illuminant, cmfs, "rectangle")
        W = np.zeros((3, w.size))
        at = np.round((w[inside] - full[0]) / interval).astype(int)
        W[:, inside] = W_full[:, at]
        W[:, np.flatnonzero(inside)[0]] += W_full[:, :at[0]].sum(axis=1)
        W[:, np.flatnonzero(inside)[-1]] += W_full[:, at[-1] + 1:].sum(axis=1)
        return W
    unit = colour.MultiSpectralDistributions(np.eye(w.size), w)
    with warnings.catch_warnings():  # colour-science says where it trims the grid to its 360-780 nm range
        warnings.simplefilter("ignore")
        XYZ = colour.msds_to_XYZ(unit, cmfs, illuminant, method="ASTM E308")
    return np.asarray(XYZ, dtype=np.float64).T / 100.0
