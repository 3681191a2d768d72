"""The calibration bundle: what calibration knows about the rig, and its file.

A :class:`CalibrationBundle` is the planner's model of the rig: the lamp's per-column power and the
column-wavelength map (from the spectroradiometer), the V estimate and the 1/V sequence (loop (a)), the dark
level and the flat field (from the camera)::

    O_k = t * sum_lambda R(lambda) E_k(lambda) rho(lambda) dlambda
    E_k(lambda) = sum_c (n_kc / rows) P_c g(lambda - lambda_c)

with ``n_kc`` the mirror counts, ``P_c`` the column power, ``g`` the unit-area line shape of a column (the
Gaussian slit function, or the shape measured by :func:`measure_line_shapes`), ``rho`` the responsivity (DN per
second per unit irradiance per nm, on reflectance 1 at the spot centre after flat fielding) and ``t`` the
exposure.

A bundle is saved as a versioned ``.npz`` with a content hash (:func:`save_calibration`); loading checks the
format, version and hash, and, when given the rig, that the rig is the one calibrated (a stale bundle is refused):
:func:`rig_fingerprint` names what a calibration depends on. :func:`oracle_calibration` builds the bundle a perfect
calibration would give from the twin's ground truth, for tests that need the model to be exact, and
:func:`calibration_error` measures how far a bundle's model is from that truth.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike

from specgpu.calibration.rigs import distribute_counts
from specgpu.io.tables import content_hash, load_npz, save_npz
from specgpu.rig.config import RigDescription
from specgpu.rig.lights import light_kind, light_summary
from specgpu.rig.scene import interpolation_matrix, white_plate_scene
from specgpu.rig.twin import TwinRig

__all__ = [
    "CALIBRATION_FORMAT",
    "CALIBRATION_VERSION",
    "DEFAULT_MAX_EXPOSURE_S",
    "CalibrationBundle",
    "calibration_error",
    "load_calibration",
    "measure_line_shapes",
    "oracle_calibration",
    "primary_lines",
    "rig_fingerprint",
    "save_calibration",
]

#: Longest exposure a plan picks (and the longest calibration measures the dark level at) unless told otherwise,
#: s: long enough for the narrow bands of the paper's rig to use most of the camera's range, short enough that lamp
#: drift within a sequence stays negligible.
DEFAULT_MAX_EXPOSURE_S = 0.25

CALIBRATION_FORMAT = "specgpu.calibration"
CALIBRATION_VERSION = 1


def rig_fingerprint(description: RigDescription) -> str:
    """SHA-256 of what a calibration depends on: light, camera (less exposure and frame rate, which plans
    choose), spectroradiometer, the seed (the camera's fixed pattern) and the bench's imperfections
    (``[realism]``). Scene, pacing, faults and ``[drift]`` (the change since calibration) are left out."""
    d = description.to_dict()
    cam = {k: v for k, v in d["camera"].items() if k not in ("exposure_s", "frame_rate_hz")}
    key = {"light": d["light"], "camera": cam, "spectroradiometer": d["spectroradiometer"], "seed": description.seed}
    if description.realism.any:  # the bench's imperfections are set-up; [drift] (time since calibration) is not
        key["realism"] = description.realism.to_dict()
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()


def _gaussian_columns(grid, centres, fwhm) -> np.ndarray:
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2)))
    return np.exp(-0.5 * ((grid[:, None] - centres[None, :]) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))


def _tabulated_columns(grid, centres, offsets, shapes) -> np.ndarray:
    """(G, C) unit-area columns from line shapes (C, X) tabulated on uniform ``offsets`` (linear between, 0 beyond)."""
    x = (grid[:, None] - centres[None, :] - offsets[0]) / (offsets[1] - offsets[0])  # (G, C) fractional index
    i0 = np.floor(x).astype(np.int64)
    f = x - i0
    n = offsets.size
    cols = np.arange(centres.size)[None, :]
    v0 = np.where((i0 >= 0) & (i0 < n), shapes[cols, np.clip(i0, 0, n - 1)], 0.0)
    v1 = np.where((i0 + 1 >= 0) & (i0 + 1 < n), shapes[cols, np.clip(i0 + 1, 0, n - 1)], 0.0)
    out = (1.0 - f) * v0 + f * v1
    area = out.sum(axis=0) * (grid[1] - grid[0])
    return out / np.where(area > 0, area, 1.0)[None, :]


def measure_line_shapes(spectra, probe_columns, probe_width: int, column_wavelengths, column_power, instrument,
                        grid, half_width_nm: float, smoothing: float = 3e-3,
                        masks=None) -> tuple[np.ndarray, np.ndarray]:
    """Each column's line shape from the spectroradiometer's readings of narrow probes, without a model of it.

    A probe lights ``probe_width`` columns from ``probe_columns[i]``; its reading is the instrument's bandpass
    (``instrument``: (samples, G) response on ``grid``) applied to the sum of those columns' lines. The line is
    solved for on 1 nm offsets within ``half_width_nm`` (non-negative least squares with a small second-difference
    penalty, ``smoothing`` relative to the data), re-centred on its centroid (the column map already holds it) and
    normalised to unit area; every column takes the line of its wavelength, linear between the probes' centres.

    Returns (offsets (X,), shapes (C, X)).
    """
    from scipy.optimize import nnls

    offsets = np.arange(-float(half_width_nm), float(half_width_nm) + 0.5, 1.0)
    n = offsets.size
    eye = np.eye(n)
    d2 = np.diff(eye, 2, axis=0)
    lines, where = [], []
    for i, (s, c0) in enumerate(zip(spectra, probe_columns)):
        cols = np.arange(int(c0), int(c0) + int(probe_width))
        # emitted (G, X): each offset's unit impulse, placed at every lit column and weighted by its power
        emit = np.zeros((grid.size, n))
        for c in cols:
            emit += column_power[c] * np.stack([np.interp(grid - column_wavelengths[c], offsets, eye[j], left=0.0,
                                                          right=0.0) for j in range(n)], axis=1)
        a = instrument @ emit
        if masks is not None:  # only the samples near the probe, with a constant background beside the line
            a = np.hstack([a[masks[i]], np.ones((int(masks[i].sum()), 1))])
            s = s[masks[i]]
        else:
            a = np.hstack([a, np.zeros((a.shape[0], 1))])
        scale = float(np.max(s)) if np.max(s) > 0 else 1.0
        lam = smoothing * float(np.linalg.norm(a)) / np.sqrt(n)
        reg = np.hstack([lam * d2, np.zeros((n - 2, 1))])
        h, _ = nnls(np.vstack([a / scale, reg / scale]), np.concatenate([s / scale, np.zeros(n - 2)]))
        h = h[:n]
        if not h.sum() > 0:
            continue
        h = h / h.sum()
        mu = float(h @ offsets)
        h = np.interp(offsets + mu, offsets, h, left=0.0, right=0.0)  # centroid to 0
        lines.append(h / (h.sum() * (offsets[1] - offsets[0])))
        where.append(float(np.mean(column_wavelengths[cols])))
    if len(lines) < 2:
        raise ValueError("calibrate: fewer than 2 probe readings to measure the line shape from")
    lines, where = np.array(lines), np.array(where)
    order = np.argsort(where)
    lines, where = lines[order], where[order]
    shapes = np.stack([np.interp(column_wavelengths, where, lines[:, j]) for j in range(n)], axis=1)
    return offsets, shapes


def primary_lines(grid, spectra, fwhm_nm: float):
    """Broad primaries (an LED array's) as a bundle holds them: from their spectra (G, C) on ``grid``, each one's
    centroid (nm), power (its integral) and unit-area shape tabulated on 1 nm offsets from the centroid, within
    four times ``fwhm_nm``. Returns (centroids (C,), powers (C,), (offsets (X,), shapes (C, X)))."""
    grid = np.asarray(grid, np.float64)
    e = np.asarray(spectra, np.float64)
    power = e.sum(axis=0) * float(grid[1] - grid[0])
    centroid = (grid @ e) / e.sum(axis=0)
    half = float(np.ceil(min(150.0, 4.0 * fwhm_nm)))
    offsets = np.arange(-half, half + 0.5, 1.0)
    shapes = np.stack([np.interp(centroid[c] + offsets, grid, e[:, c] / power[c], left=0.0, right=0.0)
                       for c in range(e.shape[1])])
    return centroid, power, (offsets, shapes)


@dataclass(frozen=True)
class CalibrationBundle:
    """What calibration knows about the rig; the planner's forward model (see the module docstring).

    Attributes
    ----------
    wavelengths : numpy.ndarray
        (G,) the light's uniform grid, nm.
    column_wavelengths : numpy.ndarray
        (C,) centre wavelength of each DMD column, nm (the column-wavelength map).
    column_power : numpy.ndarray
        (C,) irradiance of each column with all its mirrors on, W m^-2 (the lamp through guide and grating).
    slit_fwhm_nm : float
        Full width at half maximum of one column's band, nm.
    rows : int
        Mirrors per column (the intensity steps).
    responsivity : numpy.ndarray
        (G,) the V estimate: DN per second per (W m^-2 nm^-1) per nm on a reflectance of 1, at the spot centre
        after flat fielding.
    exposure_s : float
        Exposure (s) the dark level was measured at.
    dark : numpy.ndarray
        (H, W) float32 dark level (DN) at ``exposure_s``.
    dark_rate_dn_per_s : float
        Growth of the dark level with exposure, DN/s (dark current).
    flat_field : numpy.ndarray
        (H, W) float32 gain making a uniform white read the same as at the spot centre.
    max_code : int
        Top ADC code.
    min_exposure_s, max_exposure_s : float
        Exposure range the rig allows (light switch time; frame period less switch time).
    white_reflectance : float
        Reflectance of the reference white used by loop (a).
    reciprocal_patterns : numpy.ndarray
        (Kb, C) int32: loop (a)'s converged sequence (equal outputs on the white: the 1/V sequence).
    reciprocal_bands : numpy.ndarray
        (Kb, 2) band edges (nm) of those patterns.
    reports : dict
        Plain-data reports of the loops (iterations, residuals) and of the source.
    rig : str
        :func:`rig_fingerprint` of the rig calibrated.
    """

    wavelengths: np.ndarray
    column_wavelengths: np.ndarray
    column_power: np.ndarray
    slit_fwhm_nm: float
    rows: int
    responsivity: np.ndarray
    exposure_s: float
    dark: np.ndarray
    dark_rate_dn_per_s: float
    flat_field: np.ndarray
    max_code: int
    min_exposure_s: float
    max_exposure_s: float
    white_reflectance: float
    reciprocal_patterns: np.ndarray
    reciprocal_bands: np.ndarray
    reports: dict = field(default_factory=dict)
    rig: str = ""
    #: (L, H, W) flat fields measured with L bands (wavelength-dependent field: a light guide's spot is bluer on
    #: axis, lenses vignette by wavelength) and their (L,) centroid wavelengths; None: ``flat_field`` at every
    #: wavelength. See :meth:`flat_ratio`.
    flat_fields: np.ndarray | None = None
    flat_wavelengths: np.ndarray | None = None
    #: (C, X) unit-area line shape of each column, tabulated on the uniform ``line_offsets_nm`` (X,) from the
    #: column's centre (measured from the spectroradiometer's probe scans, the instrument's bandpass taken out);
    #: None: a Gaussian of ``slit_fwhm_nm``. See :func:`measure_line_shapes`.
    line_offsets_nm: np.ndarray | None = None
    line_shapes: np.ndarray | None = None

    def __post_init__(self):
        for k in ("wavelengths", "column_wavelengths", "column_power", "responsivity", "dark", "flat_field",
                  "reciprocal_patterns", "reciprocal_bands"):
            kind = np.asarray(getattr(self, k)).dtype.kind
            if kind not in "biuf":
                raise ValueError(f"{k} must hold real numbers, got dtype {np.asarray(getattr(self, k)).dtype}")
        for k in ("slit_fwhm_nm", "exposure_s", "dark_rate_dn_per_s", "min_exposure_s", "max_exposure_s",
                  "white_reflectance", "rows", "max_code"):
            v = getattr(self, k)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not np.isfinite(v):
                raise ValueError(f"{k} must be a finite number, got {v!r}")
        if not isinstance(self.reports, dict) or not isinstance(self.rig, str):
            raise ValueError("reports must be a mapping and rig a string")
        g = np.asarray(self.wavelengths, np.float64)
        if g.ndim != 1 or g.size < 2 or not np.allclose(np.diff(g), g[1] - g[0]) or g[1] <= g[0]:
            raise ValueError("calibration wavelengths must be a uniform increasing grid")
        cw = np.asarray(self.column_wavelengths, np.float64)
        cp = np.asarray(self.column_power, np.float64)
        if cw.ndim != 1 or cp.shape != cw.shape or np.any(np.diff(cw) <= 0) or not np.all(np.isfinite(cw)):
            raise ValueError("column_wavelengths must be increasing and column_power of the same length")
        if np.any(cp < 0) or not np.all(np.isfinite(cp)):
            raise ValueError("column_power must be finite and non-negative")
        rho = np.asarray(self.responsivity, np.float64)
        if rho.shape != g.shape or np.any(rho < 0) or not np.all(np.isfinite(rho)):
            raise ValueError(f"responsivity must be (G={g.size},) finite and non-negative")
        # all zero: no frame gives a signal, and every plan would divide by zero (no design, no decoder)
        for k, v, where in (("column_power", cp, "column"), ("responsivity", rho, "wavelength")):
            if not np.any(v > 0):
                raise ValueError(f"{k} is zero at every {where}: the light and camera model gives no signal")
        dark = np.asarray(self.dark, np.float32)
        flat = np.asarray(self.flat_field, np.float32)
        if dark.ndim != 2 or flat.shape != dark.shape:
            raise ValueError(f"dark and flat_field must be (H, W) of one shape, got {dark.shape}, {flat.shape}")
        if not (np.all(np.isfinite(dark)) and np.all(np.isfinite(flat)) and np.all(flat > 0)):
            raise ValueError("dark must be finite and flat_field finite and positive")
        if dark.size and (dark.min() < 0 or dark.max() > self.max_code):
            raise ValueError(f"dark must lie in 0-{self.max_code} DN, got {dark.min():g}-{dark.max():g}")
        rp = np.asarray(self.reciprocal_patterns)
        if rp.size and (not np.all(np.isfinite(rp)) or np.any(rp != np.round(rp)) or rp.min() < 0
                        or rp.max() > self.rows):
            raise ValueError(f"reciprocal_patterns must be integer mirror counts in [0, {self.rows}]")
        rp = rp.astype(np.int32).reshape(-1, cw.size)
        rb = np.asarray(self.reciprocal_bands, np.float64).reshape(-1, 2)
        if rp.shape[0] != rb.shape[0] or not np.all(np.isfinite(rb)):
            raise ValueError("reciprocal_patterns and reciprocal_bands must have one row per band, bands finite")
        if not (self.slit_fwhm_nm > 0 and self.rows >= 1 and self.exposure_s > 0 and self.max_code >= 1
                and 0 < self.min_exposure_s <= self.max_exposure_s):
            raise ValueError("calibration scalars out of range (slit, rows, exposure, max code, exposure limits)")
        if (self.flat_fields is None) != (self.flat_wavelengths is None):
            raise ValueError("flat_fields and flat_wavelengths go together")
        if self.flat_fields is not None:
            ff = np.asarray(self.flat_fields, np.float32)
            fw = np.asarray(self.flat_wavelengths, np.float64).reshape(-1)
            if ff.ndim != 3 or ff.shape[1:] != dark.shape or ff.shape[0] != fw.size or fw.size < 1:
                raise ValueError(f"flat_fields must be (L, H, W) with L flat_wavelengths, got {ff.shape}, {fw.shape}")
            if not (np.all(np.isfinite(ff)) and np.all(ff > 0)) or np.any(np.diff(fw) <= 0):
                raise ValueError("flat_fields must be finite and positive, flat_wavelengths increasing")
            object.__setattr__(self, "flat_fields", ff)
            object.__setattr__(self, "flat_wavelengths", fw)
        if (self.line_shapes is None) != (self.line_offsets_nm is None):
            raise ValueError("line_shapes and line_offsets_nm go together")
        if self.line_shapes is not None:
            ls = np.asarray(self.line_shapes, np.float64)
            lo = np.asarray(self.line_offsets_nm, np.float64).reshape(-1)
            if ls.ndim != 2 or ls.shape != (cw.size, lo.size) or lo.size < 3 \
                    or not np.allclose(np.diff(lo), lo[1] - lo[0]) or lo[1] <= lo[0]:
                raise ValueError(f"line_shapes must be (C={cw.size}, X) on a uniform increasing line_offsets_nm (X,), "
                                 f"got {ls.shape}, {lo.shape}")
            if not np.all(np.isfinite(ls)) or np.any(ls < 0) or np.any(ls.sum(axis=1) <= 0):
                raise ValueError("line_shapes must be finite, non-negative and non-zero per column")
            object.__setattr__(self, "line_shapes", ls)
            object.__setattr__(self, "line_offsets_nm", lo)
        for k, v in (("wavelengths", g), ("column_wavelengths", cw), ("column_power", cp), ("responsivity", rho),
                     ("dark", dark), ("flat_field", flat), ("reciprocal_patterns", rp), ("reciprocal_bands", rb)):
            object.__setattr__(self, k, v)

    # ---- identity ---------------------------------------------------------------------------------------------
    def _arrays(self) -> dict:
        arrays = {"wavelengths": self.wavelengths, "column_wavelengths": self.column_wavelengths,
                  "column_power": self.column_power, "responsivity": self.responsivity, "dark": self.dark,
                  "flat_field": self.flat_field, "reciprocal_patterns": self.reciprocal_patterns,
                  "reciprocal_bands": self.reciprocal_bands}
        if self.flat_fields is not None:  # only then: bundles without them keep their hash
            arrays["flat_fields"] = self.flat_fields
            arrays["flat_wavelengths"] = self.flat_wavelengths
        if self.line_shapes is not None:  # likewise
            arrays["line_shapes"] = self.line_shapes
            arrays["line_offsets_nm"] = self.line_offsets_nm
        return arrays

    def _meta(self) -> dict:
        return {"slit_fwhm_nm": float(self.slit_fwhm_nm), "rows": int(self.rows), "exposure_s": float(self.exposure_s),
                "dark_rate_dn_per_s": float(self.dark_rate_dn_per_s), "max_code": int(self.max_code),
                "min_exposure_s": float(self.min_exposure_s), "max_exposure_s": float(self.max_exposure_s),
                "white_reflectance": float(self.white_reflectance), "reports": self.reports, "rig": self.rig}

    @cached_property
    def hash(self) -> str:
        """Content hash (SHA-256 hex): what a plan records to tie itself to this calibration."""
        return content_hash(self._arrays(), json.loads(json.dumps(self._meta())))

    @property
    def frame_shape(self) -> tuple[int, int]:
        return tuple(self.dark.shape)

    @property
    def columns(self) -> int:
        return self.column_wavelengths.size

    @property
    def light(self) -> dict:
        """What calibration recorded of the light: ``{}`` for the DMD; for an LED array or the OL490 its ``kind``,
        ``rows``, ``exposure_quantum_s`` and (LEDs) ``primaries_nm``, the measured centroids."""
        r = self.reports.get("light") if isinstance(self.reports, dict) else None
        return r if isinstance(r, dict) else {}

    @property
    def light_kind(self) -> str:
        """``"dmd"``, ``"led"`` or ``"ol490"``: the kind of light calibrated."""
        return str(self.light.get("kind", "dmd"))

    def whole_periods(self, exposure_s: float) -> float:
        """``exposure_s`` rounded down to whole periods of the light's PWM or grey levels (at least one), so the
        levels a plan sets are the levels an exposure sees; unchanged for the DMD."""
        q = float(self.light.get("exposure_quantum_s", 0.0))
        if q <= 0:
            return float(exposure_s)
        return max(1, int(np.floor(float(exposure_s) / q + 1e-9))) * q

    # ---- the forward model ------------------------------------------------------------------------------------
    @cached_property
    def column_matrix(self) -> np.ndarray:
        """(G, C) estimated spectral irradiance (W m^-2 nm^-1) of each column with all mirrors on: the column's
        power times its line shape (the measured table when the bundle has one, else a Gaussian slit)."""
        if self.line_shapes is None:
            return _gaussian_columns(self.wavelengths, self.column_wavelengths, self.slit_fwhm_nm) * self.column_power
        return _tabulated_columns(self.wavelengths, self.column_wavelengths, self.line_offsets_nm,
                                  self.line_shapes) * self.column_power

    @cached_property
    def system_matrix(self) -> np.ndarray:
        """(G, C) ``rho(lambda) * M(lambda, c)``: DN/s per nm that each full column gives on reflectance 1.
        A pattern's product ``I V`` is ``system_matrix @ (n / rows)``."""
        return self.column_matrix * self.responsivity[:, None]

    def emitted(self, patterns: ArrayLike) -> np.ndarray:
        """(..., G) estimated spectral irradiance of mirror-count patterns (..., C), W m^-2 nm^-1."""
        n = np.asarray(patterns, np.float64)
        return (n / self.rows) @ self.column_matrix.T

    def forward_matrix(self, patterns: ArrayLike, wavelengths: ArrayLike, exposure_s: float) -> np.ndarray:
        """(K, B) model camera output (DN above dark, flat-fielded) per unit reflectance sampled at
        ``wavelengths`` (linear interpolation, constant beyond the ends, as the twin's scenes), for each pattern.

        ``O = F @ R`` for a reflectance ``R`` on ``wavelengths``.
        """
        n = np.atleast_2d(np.asarray(patterns, np.float64))
        dl = float(self.wavelengths[1] - self.wavelengths[0])
        prod = (n / self.rows) @ self.system_matrix.T  # (K, G): I V in DN/s per nm
        return exposure_s * dl * prod @ interpolation_matrix(self.wavelengths, np.asarray(wavelengths, np.float64))

    def flat_ratio(self, patterns: ArrayLike) -> np.ndarray | None:
        """(K, H, W) float32 per-pattern correction of the flat field, ``flat(lambda_k) / flat_field``, at each
        pattern's response centroid ``lambda_k`` (linear between the measured bands, constant beyond); None when
        the bundle has one flat field. Multiply a pattern's dark-subtracted frame by it before decoding."""
        if self.flat_fields is None:
            return None
        n = np.atleast_2d(np.asarray(patterns, np.float64))
        prod = (n / self.rows) @ self.system_matrix.T
        total = prod.sum(axis=1)
        lam = np.where(total > 0, (prod @ self.wavelengths) / np.where(total > 0, total, 1.0), np.nan)
        fw, ff = self.flat_wavelengths, self.flat_fields
        out = np.ones((n.shape[0], *self.dark.shape), np.float32)
        for k, lk in enumerate(lam):
            if not np.isfinite(lk):
                continue  # an all-off pattern (ambient frame): nothing to correct
            if fw.size == 1 or lk <= fw[0]:
                f = ff[0]
            elif lk >= fw[-1]:
                f = ff[-1]
            else:
                j = int(np.searchsorted(fw, lk)) - 1
                a = (lk - fw[j]) / (fw[j + 1] - fw[j])
                f = (1 - a) * ff[j] + a * ff[j + 1]
            out[k] = f / self.flat_field
        return out

    def linearize(self, signal) -> np.ndarray:
        """Dark-subtracted output (DN) corrected for the sensor's compression near full well measured by
        calibration (``reports["linearity_c_per_dn2"]``: ``y = s (1 - c s^2)``, solved for ``s``); float32."""
        y = np.asarray(signal, np.float32)
        c = float(self.reports.get("linearity_c_per_dn2", 0.0)) if isinstance(self.reports, dict) else 0.0
        if c <= 0:
            return y
        s = y.copy()
        for _ in range(3):  # fixed point: s = y / (1 - c s^2); c s^2 is at most a few per cent
            s = y / (1.0 - np.float32(c) * s * s)
        return s.astype(np.float32)

    def dark_at(self, exposure_s: float) -> np.ndarray:
        """(H, W) float32 dark level (DN) for an exposure (s): the measured level plus its change from the
        calibration exposure, interpolated between the exposures calibration measured it at
        (``reports["dark_exposures_s"]``; straight on beyond the ends), or, in a bundle without them, the dark
        current times the change."""
        return (self.dark + np.float32(self._dark_change(float(exposure_s)))).astype(np.float32)

    def _dark_change(self, t: float) -> float:
        ts, lv = self.dark_table
        if ts is None:
            return self.dark_rate_dn_per_s * (t - self.exposure_s)

        def level(x):
            if x <= ts[0] or x >= ts[-1]:  # straight on from the nearest segment
                i = 0 if x <= ts[0] else ts.size - 2
                return lv[i] + (lv[i + 1] - lv[i]) / (ts[i + 1] - ts[i]) * (x - ts[i])
            return float(np.interp(x, ts, lv))
        return float(level(t) - level(self.exposure_s))

    @property
    def dark_table(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(exposures s, mean dark levels DN) calibration measured, increasing; (None, None) when it recorded fewer
        than two."""
        r = self.reports if isinstance(self.reports, dict) else {}
        try:
            ts = np.asarray(r["dark_exposures_s"], np.float64)
            lv = np.asarray(r["dark_levels_dn"], np.float64)
        except (KeyError, TypeError, ValueError):
            return None, None
        if ts.ndim != 1 or ts.shape != lv.shape or ts.size < 2 or np.any(np.diff(ts) <= 0) \
                or not (np.all(np.isfinite(ts)) and np.all(np.isfinite(lv))):
            return None, None
        return ts, lv

    @property
    def dark_range_s(self) -> tuple[float, float]:
        """(shortest, longest) exposure (s) the dark level was measured at (the two-point measurement of a bundle
        without a table: the calibration exposure and a quarter of it, no shorter than the light allows)."""
        ts, _ = self.dark_table
        if ts is not None:
            return float(ts[0]), float(ts[-1])
        return min(self.exposure_s, max(self.min_exposure_s, self.exposure_s / 4)), float(self.exposure_s)

    @property
    def mirrors_off_light(self) -> bool | None:
        """Whether calibration found light on the object with every mirror off (room light, the DMD's off-state)
        above :data:`MIRRORS_OFF_TOLERANCE`; None when it could not tell (no capped-lens dark, an older bundle)."""
        r = self.reports if isinstance(self.reports, dict) else {}
        v = r.get("mirrors_off_light")
        return v if isinstance(v, bool) else None

    def check_rig(self, description: RigDescription, name: str = "calibration") -> None:
        """Refuse a bundle made on another rig (or the same rig with other light or camera parameters)."""
        if self.rig and self.rig != rig_fingerprint(description):
            raise ValueError(f"{name} is stale: it was made on another rig configuration ({self.rig[:12]} != "
                             f"{rig_fingerprint(description)[:12]}); recalibrate")


def save_calibration(path: str | os.PathLike[str], bundle: CalibrationBundle) -> str:
    """Save a bundle as a versioned, hashed ``.npz`` (format ``specgpu.calibration``); return its hash.

    Parameters
    ----------
    path : str or os.PathLike
        The file to write (``.npz``).
    bundle : CalibrationBundle

    Returns
    -------
    str
        The file's content hash (SHA-256, hex), equal to ``bundle.hash``: plans made on the bundle reference it.

    Raises
    ------
    RuntimeError
        The written content's hash differs from the bundle's.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> from specgpu.calibration import oracle_calibration, save_calibration
    >>> bundle = oracle_calibration()
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     digest = save_calibration(pathlib.Path(folder) / "calibration.npz", bundle)
    >>> digest == bundle.hash
    True
    """
    digest = save_npz(path, CALIBRATION_FORMAT, CALIBRATION_VERSION, bundle._arrays(),
                      json.loads(json.dumps(bundle._meta())))
    if digest != bundle.hash:  # the file must be the bundle a plan will reference by hash
        raise RuntimeError(f"{path}: saved content hash {digest[:12]} differs from the bundle's {bundle.hash[:12]}")
    return digest


def load_calibration(path: str | os.PathLike[str], *, rig: RigDescription | None = None) -> CalibrationBundle:
    """Load a bundle saved by :func:`save_calibration`.

    Parameters
    ----------
    path : str or os.PathLike
        The bundle's ``.npz`` file.
    rig : RigDescription, optional
        The rig the bundle will be used on: a bundle made on another rig configuration (another
        :func:`rig_fingerprint`) is refused as stale.

    Returns
    -------
    CalibrationBundle

    Raises
    ------
    ValueError
        One line naming the file: not found, not a calibration bundle, an unknown version, a corrupt file (content
        that does not match its hash), dark levels or flat-field gains the camera cannot give, or a stale bundle.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> from specgpu.calibration import load_calibration, oracle_calibration, save_calibration
    >>> from specgpu.rig.config import RigDescription
    from specgpu.rig.lights import light_kind, light_summary
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = pathlib.Path(folder) / "calibration.npz"
    ...     digest = save_calibration(path, oracle_calibration())
    ...     bundle = load_calibration(path, rig=RigDescription())
    >>> bundle.hash == digest
    True
    """
    arrays, meta, _, digest = load_npz(path, CALIBRATION_FORMAT, (CALIBRATION_VERSION,))
    try:
        bundle = CalibrationBundle(**arrays, **meta)
        same = bundle.hash == digest  # the hash re-reads every field: a wrong type fails here too
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{path}: invalid calibration bundle ({exc})") from None
    if not same:
        raise ValueError(f"{path}: corrupt calibration file (content does not match its hash)")
    _check_levels(path, bundle)
    if rig is not None:
        bundle.check_rig(rig, str(path))
    return bundle


def _check_levels(path, bundle: CalibrationBundle) -> None:
    """Refuse a bundle whose dark level or flat field could not come from its camera (a hand-made file): a
    recovery from it would be silently wrong everywhere."""
    dark = np.asarray(bundle.dark, np.float64)
    if not np.all(np.isfinite(dark)) or dark.min(initial=0) < -bundle.max_code or \
            dark.max(initial=0) > bundle.max_code:
        raise ValueError(f"{path}: invalid calibration: dark levels {dark.min():.3g}-{dark.max():.3g} DN lie "
                         f"outside the camera's 0-{bundle.max_code} codes; recalibrate")
    flat = np.asarray(bundle.flat_field, np.float64)
    if not np.all(np.isfinite(flat)) or flat.min(initial=1) <= 0 or flat.max(initial=1) > 1e6:
        raise ValueError(f"{path}: invalid calibration: its flat field holds NaN, inf, zero, negative or huge gains "
                         f"({flat.min():.3g}-{flat.max():.3g}); recalibrate")


def oracle_calibration(description: RigDescription | None = None, *, white_reflectance: float = 0.99,
                       band_step_nm: float = 10.0) -> CalibrationBundle:
    """The bundle a perfect calibration would give, read from the twin's ground truth (no measurement).

    For tests: with it, the planner's forward model equals the twin's noise-free physics (exactly, when the
    light's second-order leakage is off), so plans can be checked to float precision.
    """
    d = description if description is not None else RigDescription()
    if d.light.second_order_leakage != 0:
        raise ValueError("oracle_calibration needs light.second_order_leakage = 0 (the model has no second order)")
    rig = TwinRig(d, scene=white_plate_scene(d.camera.roi_height, d.camera.roi_width))
    light, cam = rig.light, rig.camera
    p, cp = light.params, cam.params
    line = None
    if light_kind(p) == "led":  # broad primaries: each one's true spectrum, tabulated about its centroid
        col_wl, col_power, line = primary_lines(light.wavelengths, light.column_matrix, p.line_fwhm_nm)
    else:
        g = _gaussian_columns(light.wavelengths, light.column_wavelengths, p.line_fwhm_nm)
        peak = np.argmax(g, axis=0)
        col_power = light.column_matrix[peak, np.arange(p.columns)] / g[peak, np.arange(p.columns)]
        col_wl = light.column_wavelengths
    rho = cam.responsivity(light.wavelengths) / cp.gain_e_per_dn
    dark = ((cp.pedestal_e + cam.dark_electrons(cp.exposure_s) + cam.dsnu_e) / cp.gain_e_per_dn).astype(np.float32)
    flat = (1.0 / (rig.field * cam.prnu)).astype(np.float32)
    edges = np.arange(380.0, 780.0 - 1e-9, band_step_nm)
    bands = np.stack([edges, edges + band_step_nm], axis=1)
    pre = CalibrationBundle(light.wavelengths, col_wl, col_power, p.line_fwhm_nm, p.rows, rho,
                            cp.exposure_s, dark, cp.dark_current_e_per_s / cp.gain_e_per_dn, flat, cp.max_code,
                            light.minimum_exposure_s, rig.frame_period_s - p.switch_time_s, white_reflectance,
                            np.zeros((len(bands), p.columns), np.int32), bands,
                            line_offsets_nm=None if line is None else line[0],
                            line_shapes=None if line is None else line[1])
    # The 1/V sequence the camera loop would converge to: equal outputs on the white, the weakest band full.
    masks = np.stack([(col_wl >= a) & (col_wl < b) for a, b in bands])
    bands, masks = bands[masks.any(axis=1)], masks[masks.any(axis=1)]
    resp = np.array([pre.forward_matrix(distribute_counts([1.0], m[None], p.rows), [400.0, 700.0],
                                        cp.exposure_s).sum() for m in masks])
    centre = bands.mean(axis=1)
    inside = (centre >= 400) & (centre <= 700)
    levels = np.clip(resp[inside].min() / resp, 0, 1)
    return replace(pre, reciprocal_patterns=distribute_counts(levels, masks, p.rows), reciprocal_bands=bands,
                   reports={"source": "oracle", "mirrors_off_light": bool(d.realism.ambient_lux or (
                       d.realism.dmd_off_state and line is None)),  # an LED array has no off-state mirrors
                            **({"light": {**light_summary(p), "primaries_nm": [float(x) for x in col_wl]
                                          if line is not None else []}} if light_summary(p) else {})},
                   rig=rig_fingerprint(d))


def calibration_error(bundle: CalibrationBundle, description: RigDescription | None = None, *,
                      band_step_nm: float = 10.0, band_range_nm=(400.0, 700.0)) -> dict:
    """How far a bundle's model is from the twin's truth: for every band of ``band_step_nm`` (every mirror on),
    the response the model predicts on a flat reflectance at the spot centre (DN above the all-off level) against
    the twin's noise-free response, and the shift of the response's centroid wavelength.

    Returns ``{"bands": (B, 2), "relative": (B,) model/truth - 1, "centroid_nm": (B,) model - truth,
    "shape": (B,) RMS over the grid of the unit-area responses' difference relative to the true peak (the line
    shape's error), "rms_relative", "max_relative", "rms_centroid_nm", "max_centroid_nm", "rms_shape",
    "max_shape"}``. The twin's truth includes every ``[realism]`` effect
    that acts at the spot centre (slit, map, ripples, stray light, off-state, white error does not enter: the
    truth here is the light and camera, not the white). For an LED light every LED alone is a band (``bands``
    then holds its measured centroid twice): the error of each LED's measured spectrum.
    """
    d = description if description is not None else RigDescription()
    rig = TwinRig(d, scene=white_plate_scene(d.camera.roi_height, d.camera.roi_width))
    light, cam = rig.light, rig.camera
    edges = np.arange(band_range_nm[0], band_range_nm[1] - 1e-9, band_step_nm)
    bands = np.stack([edges, edges + band_step_nm], axis=1)
    masks = np.stack([(bundle.column_wavelengths >= a) & (bundle.column_wavelengths < b) for a, b in bands])
    if bundle.light_kind == "led":  # fixed primaries: each LED alone is a band, at its measured centroid
        masks = np.eye(bundle.columns, dtype=bool)
        bands = np.repeat(bundle.column_wavelengths[:, None], 2, axis=1)
    pats = distribute_counts(np.ones(len(masks)), masks, bundle.rows)
    true_e = light.pattern_to_spectrum(pats) - light.offset_spectrum[None, :]
    true_prod = true_e * (cam.responsivity(light.wavelengths) / cam.params.gain_e_per_dn)[None, :]
    if cam.realism is not None and cam.realism.nonlinearity:
        pass  # the non-linearity depends on the level, not the band: left to the error budget
    model_prod = (pats / bundle.rows) @ bundle.system_matrix.T
    wl = bundle.wavelengths
    t_sum, m_sum = true_prod.sum(axis=1), model_prod.sum(axis=1)
    rel = m_sum / t_sum - 1.0
    cen = (model_prod @ wl) / m_sum - (true_prod @ light.wavelengths) / t_sum
    um, ut = model_prod / m_sum[:, None], true_prod / t_sum[:, None]
    shape = np.sqrt(np.mean((um - ut) ** 2, axis=1)) / ut.max(axis=1)
    return {"bands": bands, "relative": rel, "centroid_nm": cen, "shape": shape,
            "rms_relative": float(np.sqrt(np.mean(rel**2))), "max_relative": float(np.max(np.abs(rel))),
            "rms_centroid_nm": float(np.sqrt(np.mean(cen**2))), "max_centroid_nm": float(np.max(np.abs(cen))),
            "rms_shape": float(np.sqrt(np.mean(shape**2))), "max_shape": float(np.max(shape))}
