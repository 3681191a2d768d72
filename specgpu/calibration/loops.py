"""The paper's two feedback loops (Section 2, Fig. 8).

- Loop (a), camera plus reference white (:func:`camera_loop`): adjust the illuminant sequence until the camera's
  outputs on a white of known reflectance match a target sequence. With the white's reflectance as the target,
  the converged sequence is the reciprocal of the system's sensitivity (lamp times camera V) without knowing V;
  the converged outputs per band also give the V estimate the planner uses.
- Loop (b), spectroradiometer (:func:`spectral_loop`): adjust one pattern until the measured spectrum matches a
  target spectral irradiance (for colorimetry and spectral rendering).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from specgpu.calibration.bundle import CalibrationBundle
from specgpu.calibration.rigs import (
    NoiseSeeds,
    as_calibration_rig,
    centre_window,
    distribute_counts,
)
from specgpu.core.numerics import fit_levels

__all__ = ["LoopResult", "camera_loop", "spectral_loop"]


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


def camera_loop(rig, masks: ArrayLike, targets: ArrayLike, *, flat_field: ArrayLike | None = None,
                dark: ArrayLike | None = None, initial_levels: ArrayLike | None = None, repeats: int = 8,
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
    win = centre_window(shape)
    seeds = NoiseSeeds(noise_seed)
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


def spectral_loop(rig, target: ArrayLike, wavelengths: ArrayLike | None = None, *,
                  bundle: CalibrationBundle | None = None, initial=None,
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
        if bundle is not None and bundle.light_kind == "led":
            # a few broad primaries overlap: what the levels make in the model, plus the reading's shortfall, fitted
            # by all of them at once (bounded least squares), where a column-by-column ratio oscillates
            short = np.interp(bundle.wavelengths, inst, t_inst - meas, left=0.0, right=0.0)
            f = fit_levels(bundle.column_matrix, np.maximum(bundle.column_matrix @ f + short, 0.0))
            it += 1
            continue
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
