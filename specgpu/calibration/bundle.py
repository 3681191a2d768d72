"""Automatic calibration: the paper's two feedback loops (Section 2, Fig. 8) and the calibration bundle.

- Loop (a), camera plus reference white (:func:`camera_loop`): adjust the illuminant sequence until the camera's
  outputs on a white of known reflectance match a target sequence. With the white's reflectance as the target,
  the converged sequence is the reciprocal of the system's sensitivity (lamp times camera V) without knowing V;
  the converged outputs per band also give the V estimate the planner uses.
- Loop (b), spectroradiometer (:func:`spectral_loop`): adjust one pattern until the measured spectrum matches a
  target spectral irradiance (for colorimetry and spectral rendering).

:func:`calibrate` runs the whole procedure on a rig through the capture path (driver, ring buffer, assembler) and
returns a :class:`CalibrationBundle`: the lamp's per-column power and the
column-wavelength map (from the spectroradiometer), the V estimate and the 1/V sequence (loop (a)), the dark
level and the flat field (from the camera). The bundle is the planner's model of the rig::

    O_k = t * sum_lambda R(lambda) E_k(lambda) rho(lambda) dlambda
    E_k(lambda) = sum_c (n_kc / rows) P_c g(lambda - lambda_c)

with ``n_kc`` the mirror counts, ``P_c`` the column power, ``g`` the unit-area Gaussian slit function,
``rho`` the responsivity (DN per second per unit irradiance per nm, on reflectance 1 at the spot centre after
flat fielding) and ``t`` the exposure.

The procedure is written once against :class:`CalibrationRig`, the little a calibration needs from a rig (capture
a mean frame stack at an exposure, measure a loaded pattern's spectrum, the light's model and the camera's limits);
:class:`TwinCalibrationRig` is the digital twin's and :class:`specgpu.hardware.rig.HardwareCalibrationRig` a real
rig's (DLPC900 light, GenICam camera, Ocean spectrometer). :func:`oracle_calibration` builds the same bundle from the twin's ground
truth, for tests that need the model to be exact.

A bundle is saved as a versioned ``.npz`` with a content hash (:func:`save_calibration`); loading checks the
format, version and hash, and, when given the rig, that the rig is the one calibrated (a stale bundle is refused).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Protocol, runtime_checkable

import numpy as np

from specgpu.core.numerics import fit_levels
from specgpu.io.tables import content_hash, load_npz, save_npz
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import interpolation_matrix, white_plate_scene

__all__ = [
    "CalibrationBundle",
    "CalibrationRig",
    "TwinCalibrationRig",
    "as_calibration_rig",
    "LoopResult",
    "calibrate",
    "camera_loop",
    "spectral_loop",
    "oracle_calibration",
    "calibration_error",
    "save_calibration",
    "load_calibration",
    "rig_fingerprint",
    "capture_mean",
    "distribute_counts",
    "MIRRORS_OFF_TOLERANCE",
]

#: Longest exposure a plan picks (and the longest calibration measures the dark level at) unless told otherwise, s: long enough for the narrow bands of the paper's
#: rig to use most of the camera's range, short enough that lamp drift within a sequence stays negligible.
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


@dataclass(frozen=True)
class LoopResult:
    """Outcome of a feedback loop.

    Attributes
    ----------
    patterns : numpy.ndarray
        (K, columns) int32 final mirror counts.
    outputs : numpy.ndarray
        Final measurement: (K,) camera outputs (DN, dark-subtracted, flat-fielded, spot centre) for loop (a);
        (samples,) spectral irradiance (W m^-2 nm^-1) for loop (b).
    targets : numpy.ndarray
        What ``outputs`` was driven towards, same shape.
    iterations : int
        Adjustments made (measurements after the first).
    converged : bool
        Whether ``residual <= tolerance`` was reached within the iteration bound.
    residual : float
        Final value of the criterion: loop (a) the RMS relative error ``(O - T) / T`` over the bands that can
        reach their target; loop (b) the RMS of ``measured - target`` over the target's support divided by the
        target's maximum.
    tolerance : float
    history : tuple of float
        The criterion after every measurement, the first before any adjustment.
    clipped : numpy.ndarray
        (K,) bool: loop (a) bands that cannot reach the target with every mirror on (excluded from the criterion).
    """

    patterns: np.ndarray
    outputs: np.ndarray
    targets: np.ndarray
    iterations: int
    converged: bool
    residual: float
    tolerance: float
    history: tuple
    clipped: np.ndarray

    def summary(self) -> dict:
        """Plain-data summary for reports and bundle metadata."""
        return {"iterations": int(self.iterations), "converged": bool(self.converged),
                "residual": float(self.residual), "tolerance": float(self.tolerance),
                "history": [float(h) for h in self.history], "clipped": int(np.sum(self.clipped))}


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


def _measure_probe_lines(windowed, probe_cols, width, col_wl, col_power, inst_resp, grid, half):
    """:func:`measure_line_shapes` on readings restricted to each probe's window (samples outside are dropped)."""
    spectra = [s for s, _ in windowed]
    masks = [m for _, m in windowed]
    return measure_line_shapes(spectra, probe_cols, width, col_wl, col_power, inst_resp, grid, half, masks=masks)


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

    def emitted(self, patterns) -> np.ndarray:
        """(..., G) estimated spectral irradiance of mirror-count patterns (..., C), W m^-2 nm^-1."""
        n = np.asarray(patterns, np.float64)
        return (n / self.rows) @ self.column_matrix.T

    def forward_matrix(self, patterns, wavelengths, exposure_s: float) -> np.ndarray:
        """(K, B) model camera output (DN above dark, flat-fielded) per unit reflectance sampled at
        ``wavelengths`` (linear interpolation, constant beyond the ends, as the twin's scenes), for each pattern.

        ``O = F @ R`` for a reflectance ``R`` on ``wavelengths``.
        """
        n = np.atleast_2d(np.asarray(patterns, np.float64))
        dl = float(self.wavelengths[1] - self.wavelengths[0])
        prod = (n / self.rows) @ self.system_matrix.T  # (K, G): I V in DN/s per nm
        return exposure_s * dl * prod @ interpolation_matrix(self.wavelengths, np.asarray(wavelengths, np.float64))

    def flat_ratio(self, patterns) -> np.ndarray | None:
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


# ---- files ----------------------------------------------------------------------------------------------------
def save_calibration(path, bundle: CalibrationBundle) -> str:
    """Save a bundle as a versioned, hashed ``.npz``; return its hash (equal to ``bundle.hash``)."""
    digest = save_npz(path, CALIBRATION_FORMAT, CALIBRATION_VERSION, bundle._arrays(),
                      json.loads(json.dumps(bundle._meta())))
    if digest != bundle.hash:  # the file must be the bundle a plan will reference by hash
        raise RuntimeError(f"{path}: saved content hash {digest[:12]} differs from the bundle's {bundle.hash[:12]}")
    return digest


def load_calibration(path, *, rig: RigDescription | None = None) -> CalibrationBundle:
    """Load a bundle; refuse (one-line ``ValueError`` naming the file) an unknown version, a corrupt file, or,
    when ``rig`` is given, a bundle made on another rig configuration."""
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


# ---- capture helpers ------------------------------------------------------------------------------------------
def distribute_counts(levels, masks, rows: int) -> np.ndarray:
    """Patterns with a total mirror count ``level * rows * (columns in mask)`` spread evenly over each mask's
    columns (the remainder one mirror at a time), so a band's power is set in steps of one mirror, not one row.

    Parameters
    ----------
    levels : (K,) float in [0, 1]
    masks : (K, C) bool
    rows : int

    Returns
    -------
    (K, C) int32 mirror counts in [0, rows].
    """
    levels = np.clip(np.asarray(levels, np.float64), 0.0, 1.0)
    masks = np.asarray(masks, bool)
    out = np.zeros(masks.shape, np.int32)
    for k in range(masks.shape[0]):
        cols = np.flatnonzero(masks[k])
        total = int(round(levels[k] * rows * cols.size))
        base, extra = divmod(total, max(cols.size, 1))
        out[k, cols] = base
        if extra:
            # Spread the extra mirrors evenly across the band rather than bunching them at one end.
            pick = cols[np.round(np.linspace(0, cols.size - 1, extra)).astype(int)]
            out[k, pick] += 1
    return np.minimum(out, rows)


class _NoiseSeeds:
    """Fresh temporal noise for every capture on the same camera: the twin keys a frame's noise by (seed, frame
    id) and every capture restarts at frame 0, so repeated captures would otherwise repeat their noise."""

    def __init__(self, seed: int):
        self._seq = np.random.SeedSequence([int(seed), 0xCA11B])

    def next(self) -> int:
        return int(self._seq.spawn(1)[0].generate_state(1, np.uint64)[0] >> np.uint64(1))


def capture_mean(rig, patterns, repeats: int, *, noise_seed: int | None = None) -> np.ndarray:
    """(K, H, W) float64 mean of ``repeats`` captured sequences of ``patterns`` on a twin rig.

    Goes through the capture path (twin driver, ring buffer, assembler) without fault injection.
    ``noise_seed`` gives the frames fresh temporal noise (the camera's fixed pattern is unchanged).
    """
    from specgpu.capture.session import capture_sequences
    from specgpu.capture.twin import TwinDriver
    from specgpu.rig.twin import FaultSchedule

    patterns = np.atleast_2d(np.asarray(patterns, np.int32))
    k = patterns.shape[0]
    if noise_seed is not None:
        rig.seed = int(noise_seed)
    driver = TwinDriver(rig, patterns=patterns, n_frames=k * int(repeats), faults=FaultSchedule(), pacing="free")
    acc = np.zeros((k, *rig.camera.shape))
    count = 0

    def add(seq):
        nonlocal count
        acc[...] += seq.frames
        count += 1

    capture_sequences(driver, k, on_sequence=add)
    if count == 0:
        raise RuntimeError("capture_mean: no complete sequence was captured")
    return acc / count


def _centre_window(shape, fraction: float = 0.25):
    h, w = shape
    dh, dw = max(1, int(h * fraction / 2)), max(1, int(w * fraction / 2))
    return slice(h // 2 - dh, h // 2 + dh), slice(w // 2 - dw, w // 2 + dw)


def _rig(description, scene, exposure_s=None, seed=None):
    """A twin rig on ``scene``; with ``exposure_s``, the frame rate is lowered if the exposure needs it."""
    from specgpu.rig.twin import TwinRig

    d = description
    if exposure_s is not None:
        cam = d.camera
        rate = min(cam.frame_rate_hz, 1.0 / (float(exposure_s) + d.light.switch_time_s + 1e-6))
        d = replace(d, camera=replace(cam, exposure_s=float(exposure_s), frame_rate_hz=rate))
    return TwinRig(d, scene=scene, seed=seed)


# ---- the rig interface of calibration -------------------------------------------------------------------------
@runtime_checkable
class CalibrationRig(Protocol):
    """What the calibration procedure reads from a rig (twin or hardware), and nothing more.

    Attributes
    ----------
    light
        The light source: ``params`` (columns, rows, ``line_fwhm_nm``, ``switch_time_s``), ``wavelengths`` (its
        uniform grid, nm), ``column_wavelengths``, ``minimum_exposure_s`` (s), ``load_sequence((K, C))`` and
        ``check_pattern``.
    spectroradiometer
        ``wavelengths`` (nm, the instrument's output grid) and ``params.bandwidth_nm``.
    exposure_s : float
        The calibration exposure (s): the dark level is measured at it; other exposures are asked for by value.
    frame_shape : tuple of int
        (H, W) of the camera's frames.
    max_code : int
        Top ADC code of the frames (DN).
    frame_period_s : float
        Frame period at the calibration exposure (s); the longest exposure is this less the light's switch time.
    max_spectrum : numpy.ndarray or None
        (G,) the light's spectral irradiance with every mirror on (W m^-2 nm^-1) when the rig knows it (the twin);
        ``None`` on hardware, where calibration uses the spectroradiometer's all-on reading instead.
    """

    light: object
    spectroradiometer: object
    exposure_s: float
    frame_shape: tuple
    max_code: int
    frame_period_s: float
    max_spectrum: np.ndarray | None

    def capture_mean(self, patterns, repeats: int, *, exposure_s: float | None = None,
                     noise_seed: int | None = None) -> np.ndarray:
        """(K, H, W) float64 mean of ``repeats`` captured sequences of ``patterns`` (K, C) mirror counts, at
        ``exposure_s`` (the calibration exposure by default). ``noise_seed`` gives simulated frames fresh temporal
        noise; real frames always have it, so hardware ignores it."""

    def measure_spectrum(self, pattern_index: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Show loaded pattern ``pattern_index`` and read the spectroradiometer: (wavelengths nm, W m^-2 nm^-1)."""

    def zero_spectrometer(self) -> None:
        """Take the spectroradiometer's dark reading with the light off (a no-op where there is none)."""

    # Optional: ``capture_dark(repeats, *, exposure_s=None, noise_seed=None)`` -> (H, W) mean of frames with no
    # light reaching the sensor (lens capped, shutter closed). With it, calibration tells the camera's own dark
    # level from the light the object receives with every mirror off (room light, the DMD's off-state): see
    # :func:`calibrate` step (6). A rig without it is assumed to have such light (plans then add an ambient frame).


class TwinCalibrationRig:
    """The digital twin as a :class:`CalibrationRig`: one :class:`~specgpu.rig.twin.TwinRig` per exposure, all
    looking at the same scene (the reference white), frames through the twin driver, ring buffer and assembler.

    Parameters
    ----------
    description : RigDescription, optional
        The rig (the paper's by default).
    scene
        What the camera sees (a white plate of reflectance 0.99 by default).
    rig : TwinRig, optional
        Use this twin (its description and scene) for the calibration exposure instead of building one.
    """

    def __init__(self, description: RigDescription | None = None, *, scene=None, rig=None):
        if rig is not None:
            self.rig = rig
            self.description = rig.description
            self._scene = rig.scene
        else:
            d = description if description is not None else RigDescription()
            self.description = d
            self._scene = scene if scene is not None else white_plate_scene(d.camera.roi_height, d.camera.roi_width)
            self.rig = _rig(d, self._scene)
        self._by_exposure: dict[float, object] = {}
        #: The rig's own clock (s): it runs on through every capture and spectrum reading of the calibration, so
        #: the lamp drifts during the procedure as on a bench; :func:`calibrate` records where it ended.
        self.clock_s = float(self.rig.clock_start_s)

    # the rig at each exposure; the calibration exposure's is ``rig`` itself (its spectroradiometer too)
    def _at(self, exposure_s):
        if exposure_s is None:
            return self.rig
        t = float(exposure_s)
        if t not in self._by_exposure:
            self._by_exposure[t] = _rig(self.description, self._scene, t)
        return self._by_exposure[t]

    @property
    def light(self):
        return self.rig.light

    @property
    def spectroradiometer(self):
        return self.rig.spectroradiometer

    @property
    def exposure_s(self) -> float:
        return self.rig.exposure_s

    @property
    def frame_shape(self) -> tuple:
        return tuple(self.rig.camera.shape)

    @property
    def max_code(self) -> int:
        return int(self.rig.camera.params.max_code)

    @property
    def frame_period_s(self) -> float:
        return self.rig.frame_period_s

    @property
    def max_spectrum(self) -> np.ndarray:
        return self.rig.light.max_spectrum

    def capture_mean(self, patterns, repeats: int, *, exposure_s: float | None = None,
                     noise_seed: int | None = None) -> np.ndarray:
        rig = self._at(exposure_s)
        if rig.clock_start_s != self.clock_s:
            rig.set_clock(self.clock_s)
        out = capture_mean(rig, patterns, repeats, noise_seed=noise_seed)
        self.clock_s += np.atleast_2d(patterns).shape[0] * int(repeats) * rig.frame_period_s
        return out

    #: Seconds one spectroradiometer reading takes on the rig's clock (integration and read-out).
    SPECTRUM_READ_S = 0.2

    def measure_spectrum(self, pattern_index: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        d = self.description
        power = 1.0 + (d.light.drift_per_hour + d.realism.lamp_output_drift_per_hour) * self.clock_s / 3600.0
        self.clock_s += self.SPECTRUM_READ_S
        return self.rig.measure_spectrum(pattern_index, power=max(power, 0.0))

    def zero_spectrometer(self) -> None:
        """The twin's spectroradiometer has no dark offset."""

    def capture_dark(self, repeats: int, *, exposure_s: float | None = None,
                     noise_seed: int | None = None) -> np.ndarray:
        """(H, W) float64 mean of ``repeats`` frames with no light reaching the sensor (the lens capped): the
        camera's own dark level (offset, dark current) at ``exposure_s``. The twin renders a black object."""
        t = self.exposure_s if exposure_s is None else float(exposure_s)
        capped = self.__dict__.setdefault("_capped", {})
        if t not in capped:
            h, w = self.frame_shape
            capped[t] = _rig(self.description, white_plate_scene(h, w, reflectance=0.0), t)
        rig = capped[t]
        out = capture_mean(rig, np.zeros((1, rig.light.params.columns), np.int32), repeats, noise_seed=noise_seed)[0]
        self.clock_s += int(repeats) * rig.frame_period_s
        return out


def as_calibration_rig(rig) -> CalibrationRig:
    """``rig`` as a :class:`CalibrationRig`: a TwinRig is wrapped, a CalibrationRig passed through."""
    from specgpu.rig.twin import TwinRig

    if isinstance(rig, TwinRig):
        return TwinCalibrationRig(rig=rig)
    if isinstance(rig, CalibrationRig):
        return rig
    raise TypeError(f"a calibration needs a TwinRig or a CalibrationRig, got {type(rig).__name__}")


# ---- loop (a) -------------------------------------------------------------------------------------------------
def camera_loop(rig, masks, targets, *, flat_field=None, dark=None, initial_levels=None, repeats: int = 8,
                tolerance: float = 0.01, max_iterations: int = 10, noise_seed: int = 0,
                exposure_s: float | None = None) -> LoopResult:
    """Loop (a): adjust each pattern's power until the camera output on the rig's scene matches its target.

    Each pattern k lights the DMD columns of ``masks[k]`` at a common level (set in single-mirror steps by
    :func:`distribute_counts`); its output is the dark-subtracted, flat-fielded mean over the central quarter of
    the frame, averaged over ``repeats`` captured sequences. Update: ``level <- level * T / O`` (the output is
    linear in the level), clipped to [0, 1]; a pattern that would need more than every mirror is marked clipped.

    Parameters
    ----------
    rig : TwinRig or CalibrationRig
        Looking at the reference white.
    masks : (K, C) bool
    targets : (K,) float
        Wanted outputs, DN above dark.
    flat_field, dark : (H, W), optional
        Gain and dark maps (ones / zeros when not given).
    initial_levels : (K,) float in (0, 1], optional
        Start (every mirror on by default).
    repeats, tolerance, max_iterations, noise_seed
        Sequences averaged per measurement; convergence bound on the RMS relative error; adjustment bound;
        seed of the frames' temporal noise (simulated rigs).
    exposure_s : float, optional
        Exposure of the captures, s (the rig's calibration exposure by default).

    Returns
    -------
    LoopResult
    """
    masks = np.asarray(masks, bool)
    targets = np.asarray(targets, np.float64)
    k = masks.shape[0]
    if targets.shape != (k,) or np.any(targets <= 0):
        raise ValueError(f"targets must be ({k},) positive outputs in DN")
    if not 0 < tolerance < 1:
        raise ValueError(f"tolerance must lie in (0, 1), got {tolerance!r}")
    rig = as_calibration_rig(rig)
    rows = rig.light.params.rows
    shape = rig.frame_shape
    levels = np.ones(k) if initial_levels is None else np.clip(np.asarray(initial_levels, np.float64), 1e-4, 1.0)
    flat = np.ones(shape) if flat_field is None else np.asarray(flat_field, np.float64)
    dk = np.zeros(shape) if dark is None else np.asarray(dark, np.float64)
    win = _centre_window(shape)
    seeds = _NoiseSeeds(noise_seed)
    history = []
    it = 0
    while True:
        patterns = distribute_counts(levels, masks, rows)
        frames = rig.capture_mean(patterns, repeats, exposure_s=exposure_s, noise_seed=seeds.next())
        out = np.array([np.mean(((f - dk) * flat)[win]) for f in frames])
        actual = patterns.sum(axis=1) / (rows * np.maximum(masks.sum(axis=1), 1))  # level after quantization
        with np.errstate(divide="ignore", invalid="ignore"):
            wanted = np.where(out > 0, actual * targets / out, 1.0)
        clipped = wanted > 1.0
        rel = (out - targets) / targets
        resid = float(np.sqrt(np.mean(rel[~clipped] ** 2))) if np.any(~clipped) else float("inf")
        history.append(resid)
        if resid <= tolerance or it >= max_iterations:
            break
        levels = np.clip(wanted, 0.0, 1.0)
        it += 1
    return LoopResult(patterns, out, targets, it, resid <= tolerance, resid, float(tolerance), tuple(history),
                      clipped)


# ---- loop (b) -------------------------------------------------------------------------------------------------
def spectral_loop(rig, target, wavelengths=None, *, bundle: CalibrationBundle | None = None, initial=None,
                  tolerance: float = 0.005, max_iterations: int = 20, averages: int = 2) -> LoopResult:
    """Loop (b): adjust one pattern until the spectroradiometer's reading matches a target spectrum.

    Parameters
    ----------
    rig : TwinRig, CalibrationRig or HardwareRig
        Anything with ``light``, ``spectroradiometer`` and ``measure_spectrum``.
    target : array_like
        Spectral irradiance, W m^-2 nm^-1, >= 0, on ``wavelengths`` (the light's grid by default).
    bundle : CalibrationBundle, optional
        Model for the first guess (bounded least squares on the estimated lamp); without it, or with
        ``initial``, the loop starts from ``initial`` (mirror counts) or half of every mirror.
    tolerance : float
        Bound on ``rms(measured - target) / max(target)`` over the target's support, less a margin of the
        slit width plus the instrument's bandwidth at the support's edges.
    max_iterations, averages
        Adjustment bound; spectroradiometer readings averaged per measurement.

    Returns
    -------
    LoopResult
        ``patterns`` (1, C), ``outputs`` the last reading and ``targets`` the target, on the instrument grid.
    """
    light = rig.light
    p = light.params
    t = np.asarray(target, np.float64)
    src = light.wavelengths if wavelengths is None else np.asarray(wavelengths, np.float64)
    if t.ndim != 1 or t.shape != src.shape or np.any(t < 0) or not np.all(np.isfinite(t)):
        raise ValueError(f"target must be finite, non-negative and match wavelengths {src.shape}, got {t.shape}")
    if not 0 < tolerance < 1:
        raise ValueError(f"tolerance must lie in (0, 1), got {tolerance!r}")
    inst = rig.spectroradiometer.wavelengths
    t_inst = np.interp(inst, src, t, left=0.0, right=0.0)
    # Judge the match where the target is reachable: away (by the slit plus the instrument's bandpass) from
    # where it drops to zero, since no light source can follow a step narrower than its own band.
    edge = p.line_fwhm_nm + rig.spectroradiometer.params.bandwidth_nm
    zero_at = inst[t_inst <= 0]
    support = t_inst > 0
    if zero_at.size:
        support &= np.min(np.abs(inst[:, None] - zero_at[None, :]), axis=1) > edge
    if not support.any():
        raise ValueError("target is zero (or narrower than the light's band) everywhere")
    if initial is not None:
        f = light.check_pattern(initial, "initial") / p.rows
    elif bundle is not None:
        f = fit_levels(bundle.column_matrix, np.interp(bundle.wavelengths, src, t, left=0.0, right=0.0))
    else:
        f = np.full(p.columns, 0.5)
    col = light.column_wavelengths if bundle is None else bundle.column_wavelengths
    history = []
    it = 0
    while True:
        n = np.clip(np.rint(f * p.rows), 0, p.rows).astype(np.int32)
        light.load_sequence(n[None])
        meas = np.mean([rig.measure_spectrum(0)[1] for _ in range(averages)], axis=0)
        resid = float(np.sqrt(np.mean((meas - t_inst)[support] ** 2)) / t_inst[support].max())
        history.append(resid)
        if resid <= tolerance or it >= max_iterations:
            break
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(meas > 0, t_inst / meas, 2.0)
        ratio = np.where(t_inst > 0, ratio, 0.0)
        # Columns off (f = 0) but wanted get a small start so the multiplicative update can raise them.
        f = np.where((f == 0) & (np.interp(col, inst, t_inst) > 0), 1.0 / p.rows, f)
        f = np.clip(f * np.interp(col, inst, ratio), 0.0, 1.0)
        it += 1
    clipped = np.array([bool(np.any(n == p.rows))])
    return LoopResult(n[None], meas, t_inst, it, resid <= tolerance, resid, float(tolerance), tuple(history),
                      clipped)


# ---- the whole procedure --------------------------------------------------------------------------------------
def calibrate(description: RigDescription | None = None, *, white_reflectance: float = 0.99,
              white_uncertainty: float = 0.01,
              band_step_nm: float = 10.0, band_range_nm=(380.0, 780.0), equalize_range_nm=(400.0, 700.0),
              repeats: int = 8, tolerance: float = 0.01, max_iterations: int = 10, perturbation: float = 0.0,
              spectral_check: bool = True, seed: int = 0, rig: CalibrationRig | None = None,
              line_shape: str = "gaussian") -> CalibrationBundle:
    """Calibrate a rig (the twin described by ``description``, or the real one ``rig``) and return its bundle.

    Steps: (1) dark level at two exposures (dark current); (2) spectroradiometer: column-wavelength map from
    the centroids of narrow probe patterns (linear fit) and lamp power per column from the all-on spectrum;
    (3) flat field from a broadband pattern on the reference white; (4) loop (a) on the white with
    ``band_step_nm`` bands over ``band_range_nm``, the target being the white's reflectance times the level the
    weakest band in ``equalize_range_nm`` reaches with every mirror on: the converged sequence is the 1/V
    sequence, and the outputs per band give the responsivity V (per band, at the band's centroid, interpolated);
    (5) with ``spectral_check``, loop (b) on an equal-energy target, as a check of the lamp model (reported);
    (6) the all-off level of the white from the short exposure up to the longest a plan picks by default (what
    :meth:`CalibrationBundle.dark_at` interpolates) and, where the rig can cap its lens, the camera's own dark:
    the difference is light the object gets with every mirror off (room light, the DMD's off-state), which
    scales with the object's reflectance, so plans need an ambient frame where it is found
    (:func:`_dark_survey`).

    Parameters
    ----------
    description : RigDescription, optional
        The rig (the paper's by default). For the twin its camera exposure is the calibration exposure; the
        bundle records its :func:`rig_fingerprint` either way.
    white_reflectance : float
        Reflectance of the reference white plate, in (0, 1.5] (its certificate's value).
    white_uncertainty : float
        Relative standard uncertainty of that value, in [0, 0.2] (a PTFE standard's certificate: about 0.01).
        Every responsivity scales with it, so it is a scale uncertainty of every recovered reflectance; it is
        kept in the bundle's reports (``white_reflectance_uncertainty``) and written with every recovery.
    band_step_nm : float
        Width of loop (a)'s bands, nm, in [2, 50].
    repeats : int
        Sequences averaged per measurement (>= 1).
    tolerance, max_iterations : float, int
        Loop (a)'s convergence bound (RMS relative output error) and adjustment bound.
    perturbation : float
        Relative random spread, in [0, 0.9], applied to loop (a)'s starting levels (to exercise the loop).
    spectral_check : bool
        Run loop (b) once and report it.
    seed : int
        Seed of the frames' temporal noise (twin) and of the perturbation.
    line_shape : str
        ``"gaussian"`` (default): a Gaussian of the light's design FWHM; ``"measured"``: each column's line shape
        tabulated from the spectroradiometer's probe readings (:func:`measure_line_shapes`; no model of the slit;
        the Gaussian where the spectroradiometer gives no ``response_matrix``). On the lab twin the measured shape
        cuts the model's line-shape error tenfold (``tools/calibration_truth.py``) but changes no per-patch figure
        (loop (a) already pins each band's response) and moves the symmetric plan's per-pixel noise (its decoder is
        sensitive to the model's details), so it is not yet the default.
    rig : CalibrationRig, optional
        The rig to measure (e.g. :func:`specgpu.hardware.rig.open_calibration_rig` for real devices, looking at the
        reference white); by default the twin of ``description`` looking at a white plate of ``white_reflectance``.

    Returns
    -------
    CalibrationBundle
    """
    d = description if description is not None else RigDescription()
    if not 0 < white_reflectance <= 1.5:
        raise ValueError(f"white_reflectance must lie in (0, 1.5], got {white_reflectance!r}")
    if not 0 <= white_uncertainty <= 0.2:
        raise ValueError(f"white_uncertainty must lie in [0, 0.2], got {white_uncertainty!r}")
    if not 2 <= band_step_nm <= 50:
        raise ValueError(f"band_step_nm must lie in [2, 50], got {band_step_nm!r}")
    if not 0 <= perturbation <= 0.9:
        raise ValueError(f"perturbation must lie in [0, 0.9], got {perturbation!r}")
    if int(repeats) < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats!r}")
    if line_shape not in ("measured", "gaussian"):
        raise ValueError(f"line_shape must be 'measured' or 'gaussian', got {line_shape!r}")
    if rig is None:
        # The twin's white is what the certificate says, off by the bench's white_error (its truth).
        rig = TwinCalibrationRig(d, scene=white_plate_scene(
            d.camera.roi_height, d.camera.roi_width, reflectance=white_reflectance * (1.0 + d.realism.white_error)))
    else:
        rig = as_calibration_rig(rig)
    h, w = rig.frame_shape
    max_code = int(rig.max_code)
    light = rig.light
    p = light.params
    seeds = _NoiseSeeds(seed)
    t_cal = float(rig.exposure_s)
    zero = np.zeros((1, p.columns), np.int32)

    # (1) Dark level and dark current: two exposures.
    dark = rig.capture_mean(zero, 2 * repeats, noise_seed=seeds.next())[0]
    t_short = max(light.minimum_exposure_s, t_cal / 4)
    dark_short = rig.capture_mean(zero, 2 * repeats, exposure_s=t_short, noise_seed=seeds.next())[0]
    rate = float(np.mean(dark - dark_short) / (t_cal - t_short)) if t_cal > t_short else 0.0

    # (2) Spectroradiometer: column-wavelength map and lamp.
    rig.zero_spectrometer()
    probe_cols = np.linspace(16, p.columns - 24, 48).astype(int)
    probes = np.zeros((probe_cols.size, p.columns), np.int32)
    for i, c in enumerate(probe_cols):
        probes[i, c:c + 8] = p.rows
    light.load_sequence(probes)
    inst = rig.spectroradiometer.wavelengths
    cents, probe_spectra = [], []
    for i in range(probe_cols.size):
        s = np.mean([rig.measure_spectrum(i)[1] for _ in range(2)], axis=0)
        probe_spectra.append(s)
        peak = int(np.argmax(s))
        sel = np.abs(inst - inst[peak]) <= 6.0 + p.line_fwhm_nm  # the probe's band, not noise far away
        if not np.sum(s[sel]) > 0:
            raise ValueError(f"calibrate: the spectroradiometer sees no light from probe columns {probe_cols[i]}-"
                             f"{probe_cols[i] + 7}; check the light, the fibre and the instrument")
        cents.append(float(np.sum(inst[sel] * s[sel]) / np.sum(s[sel])))
    cents = np.array(cents)
    slope, icpt = np.polyfit(probe_cols + 3.5, cents, 1)
    # Non-parametric map: the straight line plus a smoothed interpolation of the probes' departures from it (a
    # grating's map is not straight in column position: bow), held at the ends' departure beyond the probes.
    resid = cents - (icpt + slope * (probe_cols + 3.5))
    if resid.size >= 5:
        resid = np.convolve(np.pad(resid, 2, mode="edge"), np.ones(5) / 5.0, mode="valid")
    col_wl = icpt + slope * np.arange(p.columns) + np.interp(np.arange(p.columns), probe_cols + 3.5, resid)
    if np.any(np.diff(col_wl) <= 0):  # a noisy reading must not fold the map: keep the straight line then
        col_wl = icpt + slope * np.arange(p.columns)
    local_slope = np.gradient(col_wl)
    light.load_sequence(np.full((1, p.columns), p.rows, np.int32))
    full = np.mean([rig.measure_spectrum(0)[1] for _ in range(4)], axis=0)
    col_power = np.interp(col_wl, inst, full) * np.abs(local_slope)
    grid = light.wavelengths
    # The slit FWHM is a design value of the light; the line's measured shape (below) replaces it in the model.
    slit = float(p.line_fwhm_nm)
    line = None
    response = getattr(rig.spectroradiometer, "response_matrix", None)
    if line_shape == "measured" and response is not None:
        # Only the readings near each probe: far away lie the DMD's off-state and stray background, not the line.
        half = 2.5 * p.line_fwhm_nm
        inst_resp = response(grid)
        windowed = []
        for s_i, c_i in zip(probe_spectra, cents):
            near = np.abs(inst - c_i) <= half + 2.0 * rig.spectroradiometer.params.bandwidth_nm
            windowed.append((s_i, near))
        line = _measure_probe_lines(windowed, probe_cols, 8, col_wl, col_power, inst_resp, grid, half)

    # (3) Flat field on the white: a broadband pattern at about half the range.
    win = _centre_window((h, w))
    n_probe = p.rows // 8
    while True:  # a probe level that does not saturate, to scale the flat-field pattern from
        probe = rig.capture_mean(np.full((1, p.columns), n_probe, np.int32), 2, noise_seed=seeds.next())[0]
        lvl = float(np.mean((probe - dark)[win]))
        if float(probe[win].max()) < 0.95 * max_code or n_probe == 1:
            break
        n_probe = max(1, n_probe // 4)
    if not lvl > 0:
        raise ValueError("calibrate: the white gives no signal; check the light and the camera")
    n_flat = int(min(p.rows, max(1, round(n_probe * 0.5 * max_code / lvl))))  # about half the range
    white_mean = rig.capture_mean(np.full((1, p.columns), n_flat, np.int32), 2 * repeats,
                                  noise_seed=seeds.next())[0] - dark
    small = _centre_window((h, w), 0.05)
    flat = (float(np.median(white_mean[small])) / np.maximum(white_mean, 1e-6)).astype(np.float32)
    # Wavelength-dependent flat field: the same on the white with 4 bands across 400-700 nm, each at a level that
    # does not saturate (the broadband flat stays the bundle's flat_field; the bands correct it per pattern).
    flat_bands, flat_wl = [], []
    flat_departure = 0.0
    for a, b in ((400.0, 475.0), (475.0, 550.0), (550.0, 625.0), (625.0, 700.0)):
        band = (col_wl >= a) & (col_wl < b)
        if not band.any():
            continue
        n_band = int(min(p.rows, max(1, round(n_flat * p.columns / band.sum() * 0.5))))
        while True:
            pat = np.where(band, n_band, 0).astype(np.int32)[None]
            m_band = rig.capture_mean(pat, 2 * repeats, noise_seed=seeds.next())[0]
            if float(m_band[win].max()) < 0.9 * max_code or n_band == 1:
                break
            n_band = max(1, n_band // 2)
        m_band = m_band - dark
        if not float(np.median(m_band[small])) > 0 or np.any(m_band <= 0):
            continue  # too dim to flat-field with (the broadband flat serves)
        # keep the smooth part of the band's departure from the broadband flat (the per-pixel part is noise here)
        from scipy.ndimage import gaussian_filter

        ratio = gaussian_filter((float(np.median(m_band[small])) / m_band) / flat, 6.0, mode="nearest")
        flat_bands.append((flat * ratio).astype(np.float32))
        flat_wl.append(float(col_wl[band].mean()))
        flat_departure = max(flat_departure, float(np.max(np.abs(ratio - 1.0))))
    if flat_bands and flat_departure < 0.005:
        flat_bands = []  # the field is the same at every wavelength to within the measurement: one flat serves

    # Linearity: a broadband ramp on the white up to near the full well; the light is linear in the mirror count,
    # so the departure of the output from a line is the sensor's: y = s (1 - c s^2), s the linear signal (DN).
    linearity_c = 0.0
    top = 0.92 * (max_code - float(np.mean(dark[small])))
    n_top = int(min(p.rows, max(1, n_probe * top / max(lvl, 1e-9))))
    if n_top >= 16:
        levels = np.unique(np.linspace(n_top / 8, n_top, 8).astype(int))
        ramp = rig.capture_mean(np.repeat(levels[:, None], p.columns, axis=1).astype(np.int32), repeats,
                                noise_seed=seeds.next())
        y = np.array([float(np.mean((f - dark)[small])) for f in ramp])
        x = levels.astype(np.float64)
        if np.all(y < 0.99 * max_code) and np.all(y > 0):
            coef = np.linalg.lstsq(np.stack([x, x**3], axis=1), y, rcond=None)[0]  # y = b1 x + b3 x^3
            if coef[0] > 0:
                linearity_c = float(max(0.0, -coef[1] / coef[0] ** 3))
                if linearity_c * (max_code - float(np.mean(dark[small]))) ** 2 < 0.002:
                    linearity_c = 0.0  # below 0.2 % at full well: within the ramp's noise, no correction

    # (4) Loop (a): bands on the white; target = white reflectance times an equalized level.
    lo, hi = band_range_nm
    edges = np.arange(lo, hi - 1e-9, band_step_nm)
    bands = np.stack([edges, np.minimum(edges + band_step_nm, hi)], axis=1)
    masks = np.stack([(col_wl >= a) & (col_wl < b) for a, b in bands])
    keep = masks.any(axis=1)
    bands, masks = bands[keep], masks[keep]
    full_out = rig.capture_mean(distribute_counts(np.ones(len(masks)), masks, p.rows), repeats,
                                noise_seed=seeds.next())
    full_out = np.array([np.mean(((f - dark) * flat)[win]) for f in full_out])
    centre = bands.mean(axis=1)
    inside = (centre >= equalize_range_nm[0]) & (centre <= equalize_range_nm[1])
    # Loop (a) runs at the exposure that lets the weakest band of the equalized range, every mirror on, reach
    # half the range above dark (the paper's dim blue end would otherwise sit a few DN above the noise).
    headroom = max_code - float(np.mean(dark))
    weakest = float(full_out[inside].min())
    if not weakest > 0:
        raise ValueError("calibrate: a band of the equalized range gives no signal on the white")
    t_a = float(np.clip(t_cal * 0.5 * headroom / weakest, t_cal, max(t_cal, DEFAULT_MAX_EXPOSURE_S)))
    dark_a = dark + rate * (t_a - t_cal)
    full_a = full_out * (t_a / t_cal)
    level = 0.97 * float(full_a[inside].min()) / white_reflectance  # output per unit reflectance
    targets = np.full(len(masks), level * white_reflectance)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x9E27]))
    start = np.clip(targets / np.maximum(full_a, 1e-9), 1e-3, 1.0)
    start = np.clip(start * (1 + perturbation * rng.uniform(-1, 1, start.size)), 1e-3, 1.0)
    loop_a = camera_loop(rig, masks, targets, flat_field=flat, dark=dark_a, initial_levels=start,
                         repeats=repeats, tolerance=tolerance, max_iterations=max_iterations,
                         noise_seed=seeds.next(), exposure_s=t_a)

    # V estimate: per band, output / (t * white * integral of the band's estimated emission), at its centroid.
    est = CalibrationBundle(grid, col_wl, col_power, slit, p.rows, np.ones_like(grid), t_cal, dark.astype(np.float32),
                            rate, flat, max_code, light.minimum_exposure_s, rig.frame_period_s - p.switch_time_s,
                            white_reflectance, loop_a.patterns, bands)
    if line is not None:
        est = replace(est, line_offsets_nm=line[0], line_shapes=line[1])
    e = est.emitted(loop_a.patterns)  # (K, G)
    power = e.sum(axis=1) * (grid[1] - grid[0])
    rho_band = loop_a.outputs / (t_a * white_reflectance * power)
    centroid = (e @ grid) / e.sum(axis=1)
    rho = np.interp(grid, centroid, rho_band)
    # Non-parametric refinement: make the model reproduce every band's measured output exactly (V varies inside a
    # band: sensor ripple, the light's slope), by correcting rho at each band's centroid by measured / modelled.
    dl = grid[1] - grid[0]
    for _ in range(6):
        modelled = t_a * white_reflectance * dl * (e * rho[None, :]).sum(axis=1)
        rho = rho * np.interp(grid, centroid, loop_a.outputs / modelled)
    # The light's frame-to-frame power fluctuation: 16 frames of the flat-field pattern in one sequence, the spread
    # of their centre means (the camera's own noise there is a few hundredths of a per cent). Drift correction
    # compares a reference white's gains with it (:func:`specgpu.planning.correction.corrected_decoder`).
    # A camera link that drops a frame loses the sequence: tried three times, then left unmeasured (no rule).
    fluctuation = None
    fluct_seed = seeds.next()
    for attempt in range(3):
        try:
            singles = rig.capture_mean(np.full((16, p.columns), n_flat, np.int32), 1, noise_seed=fluct_seed + attempt)
        except RuntimeError:
            continue
        levels = np.array([float(np.mean((f - dark)[small])) for f in singles])
        if np.all(levels > 0):
            fluctuation = float(np.std(levels, ddof=1) / np.mean(levels))
        break
    reports = {"source": "calibrated", "loop_a": loop_a.summary(), "band_step_nm": float(band_step_nm),
               "column_map": {"slope_nm": float(slope), "intercept_nm": float(icpt)},
               "level_dn_per_reflectance": level, "loop_a_exposure_s": t_a, "repeats": int(repeats)}
    reports["white_reflectance_uncertainty"] = float(white_uncertainty)
    reports["linearity_c_per_dn2"] = linearity_c
    if fluctuation is not None:
        reports["light_fluctuation"] = fluctuation
        reports["light_fluctuation_exposure_s"] = t_cal
    if hasattr(rig, "clock_s"):
        reports["rig_clock_end_s"] = float(rig.clock_s)
    reports["slit_model"] = "measured" if line is not None else "gaussian"
    bundle = replace(est, responsivity=rho, reports=reports, rig=rig_fingerprint(d))
    if flat_bands:
        bundle = replace(bundle, flat_fields=np.stack(flat_bands), flat_wavelengths=np.array(flat_wl))
        # the bands' response centroids (lamp and camera weight the band), now that the model knows them
        cent = []
        for a, b in ((400.0, 475.0), (475.0, 550.0), (550.0, 625.0), (625.0, 700.0)):
            band = (col_wl >= a) & (col_wl < b)
            if band.any():
                pr = bundle.system_matrix[:, band].sum(axis=1)
                cent.append(float(pr @ grid / pr.sum()))
        if len(cent) == len(flat_wl) and np.all(np.diff(cent) > 0):
            bundle = replace(bundle, flat_wavelengths=np.array(cent))

    # (5) Loop (b) check: an equal-energy spectrum at 40 % of the lamp's weakest point over the equalized range
    # (the lamp as the rig knows it, else as the spectroradiometer read it with every mirror on).
    if spectral_check:
        sel = (grid >= equalize_range_nm[0]) & (grid <= equalize_range_nm[1])
        lamp = rig.max_spectrum
        if lamp is None:
            lamp = np.interp(grid, inst, full)
        flat_target = np.where(sel, 0.4 * float(lamp[sel].min()), 0.0)
        initial = None
        if perturbation > 0:
            f = fit_levels(bundle.column_matrix, flat_target)
            initial = np.clip(np.rint(f * (1 + perturbation * rng.uniform(-1, 1, f.size)) * p.rows), 0, p.rows)
        loop_b = spectral_loop(rig, flat_target, bundle=bundle, initial=initial)
        bundle = replace(bundle, reports={**reports, "loop_b": loop_b.summary()})

    # (6) The dark level over the exposures plans use, and the light the object gets with every mirror off.
    survey = _dark_survey(rig, zero, repeats, seeds, {t_short: dark_short, t_cal: dark}, t_cal, win,
                          white_reflectance, level / t_a)
    return replace(bundle, reports={**bundle.reports, **survey})


#: Light on the object with every mirror off (room light, the DMD's off-state background) at or below this fraction
#: of the weakest equalized band's signal (every mirror on, same reflectance and exposure) counts as none: it
#: biases a reflectance by at most this much. Above it a plan needs an ambient frame.
MIRRORS_OFF_TOLERANCE = 1e-3


def _dark_survey(rig, zero, repeats, seeds, measured, t_cal, win, white_reflectance, band_dn_per_s) -> dict:
    """Step (6) of :func:`calibrate`: the all-off level on the white at the exposures plans use, and, where the rig
    can cap its lens (``capture_dark``), how much of it is light from the object rather than the camera's dark.

    The all-off frame of the white is the camera's dark (offset, dark current) plus the light that reaches the white
    with every mirror off (room light, the DMD's off-state and diffraction background). That light scales with the
    object's reflectance: a dark level measured on the white is too high for every darker object by the
    difference, and grows with exposure. Returns report entries (plain data):

    ``dark_exposures_s`` / ``dark_levels_dn``: exposures (from the calibration's short one up to the longest a
    plan picks by default) and the mean all-off level on the white at each (what :meth:`CalibrationBundle.dark_at`
    interpolates); with a capped lens, ``camera_dark_levels_dn`` at ``camera_dark_exposures_s``,
    ``mirrors_off_dn_per_s`` (the all-off light per unit reflectance at the spot centre, DN/s),
    ``mirrors_off_fraction`` (that light over the weakest equalized band's signal) and ``mirrors_off_light``
    (whether it exceeds :data:`MIRRORS_OFF_TOLERANCE`: then a plan needs an ambient frame); without,
    ``mirrors_off_light`` is None (not measured).
    """
    t_long = max(t_cal, DEFAULT_MAX_EXPOSURE_S)
    levels = dict(measured)
    for t in (float(np.sqrt(t_cal * t_long)), t_long):
        if t not in levels:
            levels[t] = rig.capture_mean(zero, 2 * repeats, exposure_s=t, noise_seed=seeds.next())[0]
    ts = sorted(levels)
    out = {"dark_exposures_s": [float(t) for t in ts],
           "dark_levels_dn": [float(np.mean(levels[t])) for t in ts], "mirrors_off_light": None}
    capture_dark = getattr(rig, "capture_dark", None)
    if capture_dark is None:
        return out
    capped_t = sorted({t_cal, t_long})
    capped = {t: capture_dark(2 * repeats, exposure_s=t, noise_seed=seeds.next()) for t in capped_t}
    out["camera_dark_exposures_s"] = [float(t) for t in capped_t]
    out["camera_dark_levels_dn"] = [float(np.mean(capped[t])) for t in capped_t]
    light = max(0.0, float(np.mean((levels[t_long] - capped[t_long])[win]))) / (t_long * white_reflectance)
    fraction = light / band_dn_per_s if band_dn_per_s > 0 else float("inf")
    out.update({"mirrors_off_dn_per_s": light, "mirrors_off_fraction": fraction,
                "mirrors_off_light": bool(fraction > MIRRORS_OFF_TOLERANCE)})
    return out


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
    truth here is the light and camera, not the white).
    """
    from specgpu.rig.twin import TwinRig

    d = description if description is not None else RigDescription()
    rig = TwinRig(d, scene=white_plate_scene(d.camera.roi_height, d.camera.roi_width))
    light, cam = rig.light, rig.camera
    edges = np.arange(band_range_nm[0], band_range_nm[1] - 1e-9, band_step_nm)
    bands = np.stack([edges, edges + band_step_nm], axis=1)
    masks = np.stack([(bundle.column_wavelengths >= a) & (bundle.column_wavelengths < b) for a, b in bands])
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


def oracle_calibration(description: RigDescription | None = None, *, white_reflectance: float = 0.99,
                       band_step_nm: float = 10.0) -> CalibrationBundle:
    """The bundle a perfect calibration would give, read from the twin's ground truth (no measurement).

    For tests: with it, the planner's forward model equals the twin's noise-free physics (exactly, when the
    light's second-order leakage is off), so plans can be checked to float precision.
    """
    from specgpu.rig.twin import TwinRig

    d = description if description is not None else RigDescription()
    if d.light.second_order_leakage != 0:
        raise ValueError("oracle_calibration needs light.second_order_leakage = 0 (the model has no second order)")
    rig = TwinRig(d, scene=white_plate_scene(d.camera.roi_height, d.camera.roi_width))
    light, cam = rig.light, rig.camera
    p, cp = light.params, cam.params
    g = _gaussian_columns(light.wavelengths, light.column_wavelengths, p.line_fwhm_nm)
    peak = np.argmax(g, axis=0)
    col_power = light.column_matrix[peak, np.arange(p.columns)] / g[peak, np.arange(p.columns)]
    rho = cam.responsivity(light.wavelengths) / cp.gain_e_per_dn
    dark = ((cp.pedestal_e + cam.dark_electrons(cp.exposure_s) + cam.dsnu_e) / cp.gain_e_per_dn).astype(np.float32)
    flat = (1.0 / (rig.field * cam.prnu)).astype(np.float32)
    edges = np.arange(380.0, 780.0 - 1e-9, band_step_nm)
    bands = np.stack([edges, edges + band_step_nm], axis=1)
    pre = CalibrationBundle(light.wavelengths, light.column_wavelengths, col_power, p.line_fwhm_nm, p.rows, rho,
                            cp.exposure_s, dark, cp.dark_current_e_per_s / cp.gain_e_per_dn, flat, cp.max_code,
                            light.minimum_exposure_s, rig.frame_period_s - p.switch_time_s, white_reflectance,
                            np.zeros((len(bands), p.columns), np.int32), bands)
    # The 1/V sequence the camera loop would converge to: equal outputs on the white, the weakest band full.
    masks = np.stack([(light.column_wavelengths >= a) & (light.column_wavelengths < b) for a, b in bands])
    resp = np.array([pre.forward_matrix(distribute_counts([1.0], m[None], p.rows), [400.0, 700.0],
                                        cp.exposure_s).sum() for m in masks])
    centre = bands.mean(axis=1)
    inside = (centre >= 400) & (centre <= 700)
    levels = np.clip(resp[inside].min() / resp, 0, 1)
    return replace(pre, reciprocal_patterns=distribute_counts(levels, masks, p.rows),
                   reports={"source": "oracle", "mirrors_off_light": bool(d.realism.ambient_lux or
                                                                          d.realism.dmd_off_state)},
                   rig=rig_fingerprint(d))
