"""Response plans: frames whose spectra are target response functions times an illuminant, a tristimulus imager
(eq. (7)-(11): the CIE colour-matching functions, output XYZ) and a camera simulator (a real camera's RGB
sensitivities, output RGB), negative lobes split into two frames; and the steady plan, one pattern emitting a
target spectral irradiance (spectral rendering).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import colour
import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.numerics import fit_levels
from specgpu.core.spectra import DEFAULT_CMFS, XYZ_weights, resolve_cmfs, resolve_illuminant_sd
from specgpu.core.validate import BadArgument
from specgpu.planning.basis import BasisTable
from specgpu.planning.plans import Plan, _base, _design_frames, _on_grid, _quantize
from specgpu.rig.scene import interpolation_matrix

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle

__all__ = ["plan_tristimulus", "camera_sensitivities", "plan_camera_simulator", "plan_steady_state"]


def _illuminant_on(illuminant, grid):
    sd = resolve_illuminant_sd(illuminant)
    return np.interp(grid, sd.wavelengths, sd.values, left=0.0, right=0.0), getattr(sd, "name", str(illuminant))


def _response_plan(bundle, method, responses, W, labels, output, illuminant, observer, correction, basis, m,
                   level, max_exposure_s, params):
    """responses: (P, G) signed target products I V; W: (P, G) weights giving the ideal outputs from a
    reflectance on the light grid. Negative lobes get their own frame (symmetric split)."""
    grid = bundle.wavelengths
    frames, where = [], []
    for p, r in enumerate(responses):
        for sign in (1.0, -1.0):
            part = np.clip(sign * r, 0.0, None)
            if part.max() > 1e-9 * np.abs(r).max():
                frames.append(part)
                where.append((p, sign))
    patterns, targets = _design_frames(bundle, frames)
    F = bundle.forward_matrix(patterns, grid, 1.0)  # (K, G) per second
    a = np.array([F[k] @ frames[k] / (frames[k] @ frames[k]) for k in range(len(frames))])
    D = np.zeros((len(responses), len(frames)))
    for k, (p, sign) in enumerate(where):
        D[p, k] = sign / a[k]
    if correction == "diagonal":
        white = np.ones(grid.size)
        k = (W @ white) / (D @ F @ white)
        A = k[:, None] * D
    elif correction == "span":
        if basis is None:
            raise ValueError("correction='span' needs a basis")
        if basis.centred:
            raise ValueError("correction='span' needs an uncentred basis")
        phi = interpolation_matrix(grid, basis.wavelengths) @ basis.first(m)  # constant beyond the basis range
        phi = phi * basis.singular_values[:m]  # weight components by their share of the training energy
        DFphi = D @ F @ phi
        A = (W @ phi) @ np.linalg.pinv(DFphi) @ D
    else:
        raise ValueError(f"correction must be one of diagonal, span, got {correction!r}")
    params = {**params, "correction": correction, "frames": [[int(p), float(s)] for p, s in where]}
    if correction == "span":
        params["m"] = int(m)
    return _base(bundle, method, patterns, targets, A, level, max_exposure_s, output=output,
                 output_wavelengths=np.zeros(0), output_labels=labels, illuminant=illuminant, observer=observer,
                 params=params)


def plan_tristimulus(bundle: CalibrationBundle, *, illuminant: str = "D65", cmfs=DEFAULT_CMFS,
                     correction: str = "diagonal",
                     basis: BasisTable | None = None, m: int = 3, level: float = 0.9,
                     max_exposure_s: float | None = None) -> Plan:
    """Tristimulus imager (eq. (7)-(11)): three frames with ``I_x V = E_T x``, ``I_y V = E_T y``, ``I_z V = E_T z``.

    Parameters
    ----------
    bundle : CalibrationBundle
    illuminant : str or colour.SpectralDistribution
        E_T: any of ``colour.SDS_ILLUMINANTS`` (``"D65"``, ``"A"`` ...) or a spectrum.
    cmfs : str or colour.MultiSpectralDistributions
        Observer.
    correction : {"diagonal", "span"}
        ``"diagonal"``: ``A = diag(k)``, k making the perfect white exact (the paper's). ``"span"``: the 3 x 3
        least-squares decoder over the first ``m`` functions of ``basis`` (weighted by their energy): exact on
        their span when m = 3.
    basis, m
        For ``"span"``.
    level, max_exposure_s
        As :func:`plan_narrowband`.

    Returns
    -------
    Plan
        Output ``"XYZ"`` with Y = 1 for the perfect white, over the light's wavelength range (colour-science's
        ``sd_to_XYZ`` with the observer trimmed to that range, divided by 100).
    """
    grid = bundle.wavelengths
    E, name = _illuminant_on(illuminant, grid)
    cm = resolve_cmfs(cmfs)
    xyz = np.stack([np.interp(grid, cm.wavelengths, cm.values[:, i], left=0.0, right=0.0) for i in range(3)])
    W = XYZ_weights(grid, illuminant, cm)
    return _response_plan(bundle, "tristimulus", E * xyz, W, ("X", "Y", "Z"), "XYZ", str(name), cm.name,
                          correction, basis, m, level, max_exposure_s, {})


def camera_sensitivities(name: str):
    """RGB sensitivities colour-science ships (``colour.MSDS_CAMERA_SENSITIVITIES``), by name."""
    table = colour.MSDS_CAMERA_SENSITIVITIES
    if name not in table:
        raise BadArgument(f"unknown camera {name!r}; valid cameras: {', '.join(table)}")
    return table[name]


def plan_camera_simulator(bundle: CalibrationBundle, *, camera: str = "Nikon 5100 (NPL)", illuminant: str = "D65",
                          correction: str = "diagonal",
                          basis: BasisTable | None = None, m: int = 3, level: float = 0.9,
                          max_exposure_s: float | None = None) -> Plan:
    """Camera simulator: frames with ``I V = E R_c`` for a camera's response functions R_c under illuminant E,
    so the monochrome rig records what that camera would (negative lobes, if any, split into two frames).

    Parameters
    ----------
    camera : str or colour.MultiSpectralDistributions
        A name of ``colour.MSDS_CAMERA_SENSITIVITIES`` or any multi-spectral response set.
    illuminant, correction, basis, m, level, max_exposure_s
        As :func:`plan_tristimulus`.

    Returns
    -------
    Plan
        Output ``"RGB"``, normalized so the perfect white has G = 1 (the second channel).
    """
    msds = camera_sensitivities(camera) if isinstance(camera, str) else camera
    if not isinstance(msds, colour.MultiSpectralDistributions):
        raise TypeError(f"camera must be a name or colour.MultiSpectralDistributions, not {type(camera).__name__}")
    grid = bundle.wavelengths
    E, name = _illuminant_on(illuminant, grid)
    vals = np.asarray(msds.values, np.float64)
    R = np.stack([np.interp(grid, msds.wavelengths, vals[:, i], left=0.0, right=0.0) for i in range(vals.shape[1])])
    resp = E * R
    dl = float(grid[1] - grid[0])
    ref = resp[min(1, len(resp) - 1)].sum() * dl
    if not ref > 0:
        raise ValueError("camera responses under the illuminant are zero over the light's range")
    W = resp * dl / ref
    labels = tuple(str(x) for x in msds.labels)
    return _response_plan(bundle, "camera", resp, W, labels, "RGB", str(name), str(msds.name), correction, basis,
                          m, level, max_exposure_s, {})


# ---- steady state ----------------------------------------------------------------------------------------------
def plan_steady_state(bundle: CalibrationBundle, spectrum: ArrayLike, wavelengths: ArrayLike | None = None, *,
                      fit: str = "scale", level: float = 0.9,
                      max_exposure_s: float | None = None) -> Plan:
    """One pattern emitting a target spectral irradiance, every frame (spectral rendering, paper Section 3).

    Parameters
    ----------
    spectrum : array_like or colour.SpectralDistribution or str
        Target spectral irradiance (W m^-2 nm^-1) on ``wavelengths``; an illuminant name is taken from
        ``colour.SDS_ILLUMINANTS`` (relative, use ``fit="scale"``).
    fit : {"scale", "absolute"}
        ``"scale"``: the largest multiple of the target the lamp can give; ``"absolute"``: as given (clipped
        where the lamp cannot).

    Returns
    -------
    Plan
        K = 1, ``A = 1 / c_white``: output ``"relative"``, the signal relative to a perfect white under it.
    """
    grid = bundle.wavelengths
    if isinstance(spectrum, str) or hasattr(spectrum, "values"):
        if wavelengths is not None:
            raise ValueError("wavelengths must not be given with a named or colour spectrum")
        target, name = _illuminant_on(spectrum, grid)
    else:
        s = np.asarray(spectrum, np.float64)
        w = grid if wavelengths is None else np.asarray(wavelengths, np.float64)
        if s.ndim != 1 or s.shape != w.shape or np.any(s < 0) or not np.all(np.isfinite(s)):
            raise ValueError(f"spectrum must be finite, non-negative and match wavelengths {w.shape}")
        target, name = _on_grid(s, w, grid), "custom"
    if not target.max() > 0:
        raise ValueError("spectrum is zero over the light's range")
    if fit == "scale":
        f = fit_levels(bundle.column_matrix, target / target.max(), upper=None)
        scale = 1.0 / f.max()
        f, target = f * scale, target / target.max() * scale
    elif fit == "absolute":
        f = fit_levels(bundle.column_matrix, target)
    else:
        raise ValueError(f"fit must be one of scale, absolute, got {fit!r}")
    patterns = _quantize(f, bundle.rows)[None]
    resp = bundle.forward_matrix(patterns, grid, 1.0).sum()
    if not resp > 0:
        raise ValueError("the steady illuminant gives no camera signal in the calibration model")
    return _base(bundle, "steady", patterns, target[None], np.array([[1.0 / resp]]), level, max_exposure_s,
                 output="relative", output_wavelengths=np.zeros(0), output_labels=("relative",),
                 illuminant=str(name), observer="", params={"fit": fit})
