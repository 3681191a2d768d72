"""Basis plans (eq. (5), (6)): frames that project the reflectance on the first m functions of a basis, with
one bias frame (``biased``, m + 1 frames) or each function's positive and negative parts apart (``symmetric``,
2m - 1 frames). With ``D`` the paper's combination (m x K), ``A = Phi_out (D F Phi)^-1 D``: exactly the paper's
decoder when the frames are ideal, and exact for every spectrum in the basis span when they are not (quantized
mirrors, slit blur): ``D F Phi`` is the m x m matrix the ideal design makes the identity.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu.planning.basis import BasisTable
from specgpu.planning.plans import Plan, _base, _design_frames, _on_grid
from specgpu.rig.scene import interpolation_matrix

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle

__all__ = ["plan_symmetric_basis", "plan_biased_basis"]


def _basis_functions(basis: BasisTable, m: int):
    if not isinstance(basis, BasisTable):
        raise TypeError(f"basis must be a BasisTable, not {type(basis).__name__}")
    if basis.centred:
        raise ValueError("basis plans need an uncentred basis (a mean term would make recovery affine)")
    return basis.first(m)


def _basis_plan(bundle, basis, m, method, frames, D_rows, output_wavelengths, level, max_exposure_s, extra):
    """frames: list of (B,) non-negative spectra on the basis grid; D_rows: function(a) -> (m, K) combination."""
    wl = basis.wavelengths
    phi = basis.first(m)
    grid = bundle.wavelengths
    products = [_on_grid(f, wl, grid) for f in frames]
    patterns, targets = _design_frames(bundle, products)
    F = bundle.forward_matrix(patterns, wl, 1.0)  # (K, B) per second
    # a_k: the scale by which frame k realizes its spectrum (least-squares projection of its model row on it).
    a = np.array([F[k] @ frames[k] / (frames[k] @ frames[k]) for k in range(len(frames))])
    D = D_rows(a)
    G = D @ F @ phi  # (m, m): the identity for ideal frames
    cond = np.linalg.cond(G)
    if not cond < 1e8:
        raise ValueError(f"{method}: the projections do not determine the {m} coefficients (condition {cond:.1e})")
    ow = wl if output_wavelengths is None else np.asarray(output_wavelengths, np.float64).reshape(-1)
    if ow.min() < wl[0] - 1e-9 or ow.max() > wl[-1] + 1e-9:
        raise ValueError(f"output_wavelengths must lie within the basis range {wl[0]:g}-{wl[-1]:g} nm")
    phi_out = interpolation_matrix(ow, wl) @ phi
    A = phi_out @ np.linalg.solve(G, D)
    params = {"m": int(m), "basis_source": basis.source, "cumulative_variance": float(basis.cumulative_variance[m - 1]),
              **extra}
    return _base(bundle, method, patterns, targets, A, level, max_exposure_s, output="reflectance",
                 output_wavelengths=ow, output_labels=tuple(f"{x:g}nm" for x in ow), illuminant="", observer="",
                 params=params)


def plan_symmetric_basis(bundle: CalibrationBundle, basis: BasisTable, *, m: int = 5,
                         output_wavelengths: ArrayLike | None = None, level: float = 0.9,
                         max_exposure_s: float | None = None) -> Plan:
    """Symmetric basis design (eq. (5), (6)): ``S_j = S_j+ - S_j-``, 2m - 1 frames (one for the non-negative S_1).

    Parameters
    ----------
    bundle : CalibrationBundle
    basis : BasisTable
        Uncentred basis; its grid is the design grid.
    m : int
        Basis functions used, >= 1 (paper: 5).
    output_wavelengths : array_like, optional
        Where to output reflectance (default the basis grid), within the basis range.
    level, max_exposure_s
        As :func:`plan_narrowband`.
    """
    phi = _basis_functions(basis, m)
    frames, where = [phi[:, 0].clip(0, None)], [(0, 1.0)]
    if np.any(phi[:, 0] < -1e-12):
        frames.append((-phi[:, 0]).clip(0, None))
        where.append((0, -1.0))
    for j in range(1, m):
        for sign in (1.0, -1.0):
            part = (sign * phi[:, j]).clip(0, None)
            if np.any(part > 0):
                frames.append(part)
                where.append((j, sign))

    def D_rows(a):
        D = np.zeros((m, len(frames)))
        for k, (j, sign) in enumerate(where):
            D[j, k] = sign / a[k]
        return D

    return _basis_plan(bundle, basis, m, "symmetric", frames, D_rows, output_wavelengths, level, max_exposure_s,
                       {"frames": [[int(j), float(s)] for j, s in where]})


def plan_biased_basis(bundle: CalibrationBundle, basis: BasisTable, *, m: int = 5, output_wavelengths=None,
                      level: float = 0.9,
                      max_exposure_s: float | None = None) -> Plan:
    """Biased basis design (eq. (5), (6)): frames ``S_j + K`` (K the smallest bias making every function
    non-negative) and one bias frame ``K``: m + 1 frames. Parameters as :func:`plan_symmetric_basis`."""
    phi = _basis_functions(basis, m)
    bias = float(max(0.0, (-phi).max()))
    frames = [phi[:, j] + bias for j in range(m)]
    frames = [np.clip(f, 0.0, None) for f in frames]
    frames.append(np.full(phi.shape[0], 1.0))

    def D_rows(a):
        D = np.zeros((m, m + 1))
        for j in range(m):
            D[j, j] = 1.0 / a[j]
            D[j, m] = -bias / a[m]
        return D

    return _basis_plan(bundle, basis, m, "biased", frames, D_rows, output_wavelengths, level, max_exposure_s,
                       {"bias": bias})
