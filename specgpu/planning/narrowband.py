"""Narrow-band plans (eq. (2)-(4)): one band per frame, every mirror on in its columns (``narrowband``), or each
column's level proportional to ``1 / (lamp V)`` so every band gives the same output on a white (``reciprocal``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu.planning.plans import Plan, _band_masks, _base, _check_centres, _quantize

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle

__all__ = ["plan_narrowband", "plan_reciprocal_narrowband"]


def plan_narrowband(bundle: CalibrationBundle, *, centres: ArrayLike | None = None, step_nm: float = 10.0,
                    bandwidth_nm: float | None = None,
                    start_nm: float = 400.0, stop_nm: float = 700.0, level: float = 0.9,
                    max_exposure_s: float | None = None) -> Plan:
    """Narrow-band sequence (eq. (2)-(4)): every mirror on in the columns within ``bandwidth_nm / 2`` of each centre.

    Parameters
    ----------
    bundle : CalibrationBundle
    centres : array_like, optional
        Band centres, nm (default ``start_nm`` to ``stop_nm`` every ``step_nm``: 31 bands at 10 nm, 61 at 5).
    step_nm, bandwidth_nm : float
        Spacing and full width of the bands, nm (width defaults to the spacing).
    level : float
        Fraction of the range above dark the brightest frame reaches on a perfect white, (0, 1].
    max_exposure_s : float, optional
        Longest exposure, s (default :data:`DEFAULT_MAX_EXPOSURE_S`). The capture runs at a frame rate of at
        most ``1 / (exposure + switch time)``, recorded as ``params["max_frame_rate_hz"]``.

    Returns
    -------
    Plan
        ``A = diag(1 / c_i)``, output reflectance at the centres.
    """
    c, bw = _check_centres(centres, step_nm, bandwidth_nm, start_nm, stop_nm)
    masks = _band_masks(bundle, c, bw)
    patterns = np.where(masks, bundle.rows, 0).astype(np.int32)
    return _narrow(bundle, "narrowband", c, bw, patterns, level, max_exposure_s)


def _narrow(bundle, method, c, bw, patterns, level, max_exposure_s):
    resp = bundle.forward_matrix(patterns, bundle.wavelengths, 1.0).sum(axis=1)  # c_i per second, eq. (3)
    if np.any(resp <= 0):
        raise ValueError(f"band at {c[np.argmin(resp)]:g} nm gives no camera signal in the calibration model")
    targets = bundle.emitted(patterns)
    return _base(bundle, method, patterns, targets, np.diag(1.0 / resp), level, max_exposure_s,
                 output="reflectance", output_wavelengths=c, output_labels=tuple(f"{x:g}nm" for x in c),
                 illuminant="", observer="", params={"bandwidth_nm": bw, "centres_nm": c.tolist()})


def plan_reciprocal_narrowband(bundle: CalibrationBundle, *, centres: ArrayLike | None = None, step_nm: float = 10.0,
                               bandwidth_nm: float | None = None,
                               start_nm: float = 400.0, stop_nm: float = 700.0, level: float = 0.9,
                               max_exposure_s: float | None = None) -> Plan:
    """Narrow bands shaped as ``1 / (lamp V)`` (eq. (4), last remark): each column's level is a common factor
    over its response, so every band gives the same output on a white and the frame reads the reflectance.

    The common factor is the largest that keeps every column within its mirrors (the weakest column full).
    Parameters as :func:`plan_narrowband`.
    """
    c, bw = _check_centres(centres, step_nm, bandwidth_nm, start_nm, stop_nm)
    masks = _band_masks(bundle, c, bw)
    col_resp = bundle.system_matrix.sum(axis=0)  # DN/s per full column on reflectance 1
    used = masks.any(axis=0)
    if np.any(col_resp[used] <= 0):
        raise ValueError("a band column gives no camera signal in the calibration model")
    # Each column contributes a common amount; a band of fewer columns gets proportionally more per column, so
    # every band (25 or 26 columns at 10 nm) gives the same total.
    with np.errstate(divide="ignore"):
        share = np.where(masks, 1.0 / (col_resp * masks.sum(axis=1, keepdims=True)), 0.0)
    levels = share / share.max()
    patterns = _quantize(levels, bundle.rows)
    return _narrow(bundle, "reciprocal", c, bw, patterns, level, max_exposure_s)
