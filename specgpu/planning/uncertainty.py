"""Per-pixel uncertainty of a recovery: the standard deviation of every output (:func:`sigma_map`), the
covariance of linear combinations of them (XYZ, :func:`output_covariance`) and its propagation to dE2000
(:func:`delta_E_sigma`).

``var y_b = gain^2 sum_k A_bk^2 (o_k / g + s_read^2 + (l o_k)^2) + m_b`` with ``o_k`` each frame's own signal above
dark at the pixel: :func:`specgpu.engine.linear_map.apply_linear` computes it with ``A^2 / g`` as the matrix,
``gain^2`` as the gain and, per frame sample, ``x + g l^2 (x - g s_read^2)^2`` where ``x = o - (dark - g s_read^2)``
(:meth:`specgpu.planning.noise.NoiseModel.light_square`; the stream's sigma kernels square the samples on the
device). The light's term is the frame's own: its fluctuation scales the whole frame, so it grows with the pixel's
signal squared, and a multiplexed plan (Hadamard: about half the light in every frame) has bright frames whose
fluctuation its decoder's differences do not cancel. ``m_b``, the prior's mismatch
``diag((W - A F) S (W - A F)^T)``, is a constant per output added on the host.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import colour
import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.numerics import live_gain
from specgpu.core.spectra import DEFAULT_CMFS, white_point_XYZ
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.warp_map import apply_linear_warped
from specgpu.planning.correction import ambient_index
from specgpu.planning.noise import NoiseModel

if TYPE_CHECKING:
    from specgpu.planning.plans import Plan

__all__ = ["sigma_map", "frame_variance", "output_covariance", "frame_covariance", "variance_rows",
           "ambient_variance", "constant_covariance", "constant_variance", "delta_E_sigma"]


def sigma_map(frames: ArrayLike, plan: Plan, dark: ArrayLike, gain: ArrayLike, *, sequences: int = 1,
              light: bool = True, ambient_dark=None,
              device=None) -> np.ndarray:
    """(H, W, P) standard deviation of each output per pixel (float32), from the frames (K, H, W) the outputs
    were recovered from (the mean of ``sequences`` sequences): ``var y = gain^2 sum_k A^2 (o / g + s_read^2 +
    (l o)^2) / S + m`` (:func:`frame_variance`), plus the prior's mismatch ``m`` on the host. ``light=False``
    leaves out the light's frame-to-frame fluctuation (a decoder rescaled per sequence by a white reference's
    gains divides each frame's fluctuation out). A plan with an ambient frame: ``dark`` is that frame (what the
    recovery subtracted) and ``ambient_dark`` the calibration's dark level under it (:func:`frame_variance`)."""
    var = frame_variance(frames, plan, dark, gain, sequences=sequences, light=light, ambient_dark=ambient_dark,
                         device=device)
    var += constant_variance(plan).astype(np.float32)  # in place, float32: as cheap as the recovery itself
    np.maximum(var, 0.0, out=var)
    return np.sqrt(var, out=var)


def frame_variance(frames, plan, dark, gain, *, A=None, sequences: int = 1, light: bool = True, ambient_dark=None,
                   shifts=None, device=None) -> np.ndarray:
    """(H, W, P) float32: the part of each output's variance the frames' noise makes, for the decoder ``A`` (the
    plan's by default) applied to the mean of ``sequences`` sequences (no constant term): each frame's shot, read
    and dark noise and, with ``light``, the light's fluctuation at the frame's own signal.

    A plan with an ambient frame (``plan --ambient``) has that frame subtracted instead of a dark level: ``dark``
    is the ambient frame and ``ambient_dark`` (required) the calibration's dark level at the exposure. Its own
    noise is then in every output, ``(sum_k A_k)^2`` times, and the room light it holds adds shot noise to every
    frame: ``var y = gain^2 [sum_k A_k^2 (s_k / g + (l s_k)^2) + (sum_k A_k^2 + (sum_k A_k)^2) (a / g +
    s_read^2)]`` with ``s_k`` each frame above the ambient frame and ``a`` the ambient frame above the dark level
    (:func:`variance_rows`, :func:`ambient_variance`).

    ``shifts`` (a motion-compensated recovery's, :func:`specgpu.engine.warp_map.apply_linear_warped`): each
    frame's variance sampled bilinearly where that frame saw the pixel, NaN outside the field. Interpolation
    averages up to four sensor pixels' noise, so this is an upper bound of the compensated outputs' variance (at
    most 4 times it, at half-pixel shifts in both directions)."""
    A = np.asarray(plan.A if A is None else A, np.float64)
    return _noise_products(frames, plan, dark, gain, (A, A), sequences, device, light, ambient_dark, shifts)


def output_covariance(frames, plan, dark, gain, M, *, sequences: int = 1, light: bool = True, ambient_dark=None,
                      device=None) -> np.ndarray:
    """(H, W, Q, Q) covariance of ``M y`` per pixel (M: (Q, P), e.g. the XYZ weights of a reflectance plan):
    each entry ``sum_k (MA)_ik (MA)_jk var o_k`` is linear in the frames' sample variances (one apply_linear pass
    over the Q (Q + 1) / 2 products), plus ``M C M^T`` with C the plan's constant covariance (the mismatch)."""
    M = np.asarray(M, np.float64)
    cov = frame_covariance(frames, plan, dark, gain, M, sequences=sequences, light=light, ambient_dark=ambient_dark,
                           device=device)
    return cov + M @ constant_covariance(plan) @ M.T


def frame_covariance(frames, plan, dark, gain, M, *, A=None, sequences: int = 1, light: bool = True,
                     ambient_dark=None, device=None) -> np.ndarray:
    """(H, W, Q, Q) float64: the frames' noise part of the covariance of ``M y`` for the decoder ``A`` (the plan's
    by default), without the constant ``M C M^T``."""
    M = np.asarray(M, np.float64)
    MA = M @ (plan.A if A is None else np.asarray(A, np.float64))
    Q = M.shape[0]
    pairs = [(i, j) for i in range(Q) for j in range(i, Q)]
    left = np.stack([MA[i] for i, _ in pairs])
    right = np.stack([MA[j] for _, j in pairs])
    v = np.asarray(_noise_products(frames, plan, dark, gain, (left, right), sequences, device, light, ambient_dark),
                   np.float64)
    cov = np.empty(v.shape[:-1] + (Q, Q))
    for n, (i, j) in enumerate(pairs):
        cov[..., i, j] = cov[..., j, i] = v[..., n]
    return cov


def variance_rows(left, right, ambient: int | None = None) -> np.ndarray:
    """(R, K) the rows whose products with the frames' sample variances give ``cov(left @ o, right @ o)`` per
    pixel: ``left * right``; with an ambient frame (index ``ambient``, subtracted from every frame) its column is
    ``sum_k left_k right_k + (sum_k left_k) (sum_k right_k)`` (its noise in every output, and the room light's
    shot noise it stands for in every frame; :func:`frame_variance`)."""
    L = np.array(left, np.float64, ndmin=2)
    R = np.array(right, np.float64, ndmin=2)
    if ambient is None:
        return L * R
    L[:, ambient] = 0.0
    R[:, ambient] = 0.0
    rows = L * R
    rows[:, ambient] = rows.sum(axis=1) + L.sum(axis=1) * R.sum(axis=1)
    return rows


def ambient_variance(ambient_frame, dark, noise: NoiseModel) -> np.ndarray:
    """(H, W) float32 ``g`` times the variance of an ambient frame's sample: its signal above the dark level
    (floored at 0; the room light's shot noise) plus ``g s_read^2``: the ambient frame's "sample" in the variance
    products of :func:`frame_variance` (the stream writes the same into that frame's plane)."""
    a = np.asarray(ambient_frame, np.float32) - np.asarray(dark, np.float32)
    np.maximum(a, np.float32(0.0), out=a)
    a += np.float32(noise.gain_e_per_dn * noise.read_var_dn2)
    return a


def _noise_products(frames, plan, dark, gain, pair, sequences, device, light=True, ambient_dark=None, shifts=None):
    """``gain^2 sum_k rows_k var(o_k) / S`` per pixel, ``rows = variance_rows(*pair)``: the frames' samples above
    the shifted dark ``dark - g s_read^2`` through apply_linear with ``rows / g`` (linear in the frames), or, with
    the light's fluctuation, the samples first mapped to ``x + q (x - c)^2`` (:meth:`NoiseModel.light_square`, as
    the stream's kernels). With an ambient frame (``dark`` is that frame): the samples above it, squared for the
    light, and the ambient frame's own sample :func:`ambient_variance`. ``shifts``: sampled where each frame saw the
    pixel (:func:`specgpu.engine.warp_map.apply_linear_warped`; not with an ambient frame)."""
    if "noise" not in plan.params:
        raise ValueError(f"the {plan.method} plan records no noise model; re-plan it with specgpu plan --rig RIG.toml "
                         "(the rig the calibration was made on) to record one")
    if not (isinstance(sequences, (int, np.integer)) and sequences >= 1):
        raise ValueError(f"sequences must be an integer >= 1, got {sequences!r}")
    noise = NoiseModel.from_params(plan.params["noise"])
    amb = ambient_index(plan)
    rows = variance_rows(*pair, ambient=amb)
    matrix = rows / noise.gain_e_per_dn / sequences
    g = None if gain is None else live_gain(gain) ** 2  # NaN where a pixel has no response
    if shifts is not None and amb is not None:
        raise ValueError(f"the {plan.method} plan subtracts its ambient frame from fixed pixels: its noise model has "
                         "no motion-compensated form")

    def apply(x, d):
        if shifts is None:
            return apply_linear(x, matrix, d, g, device=device)
        # a frame no output reads (a broadband reference frame) adds no noise, wherever it saw the pixel
        return apply_linear_warped(x, matrix, shifts, d, g, device=device,
                                   read=np.flatnonzero(np.any(matrix != 0, axis=0)))

    if amb is not None:
        if ambient_dark is None:
            raise ValueError(f"the {plan.method} plan subtracts its ambient frame: its noise model needs the "
                             "calibration's dark level under it (ambient_dark)")
        x = np.asarray(frames, np.float32) - np.asarray(dark, np.float32)
        if light and noise.light_rms > 0:
            q = np.float32(noise.light_square()[0])
            x += q * (x * x)
        x[amb] = ambient_variance(dark, ambient_dark, noise)
        return np.asarray(apply_linear(x, matrix, None, g, device=device), np.float32)
    d = np.asarray(dark, np.float32) - np.float32(noise.gain_e_per_dn * noise.read_var_dn2)
    if light and noise.light_rms > 0:
        q, c = (np.float32(v) for v in noise.light_square())
        x = np.asarray(frames, np.float32) - d
        s = x - c
        s *= s
        s *= q
        x += s
        return np.asarray(apply(x, None), np.float32)
    return np.asarray(apply(frames, d), np.float32)


def constant_covariance(plan) -> np.ndarray:
    """(P, P) the output covariance no frame shows: the prior's mismatch (zero when the plan records no expected
    error). A plan saved before the light's fluctuation was taken per pixel recorded it, at the prior's mean
    signal, in ``constant_cov`` beside the mismatch: that is used as it is (the sigma then errs high by the light
    at the prior's signal; re-plan to drop it)."""
    P = plan.A.shape[0]
    expected = plan.params.get("expected", {})
    c = expected.get("mismatch_cov", expected.get("constant_cov"))
    return np.zeros((P, P)) if c is None else np.asarray(c, np.float64).reshape(P, P)


def constant_variance(plan) -> np.ndarray:
    """(P,) the diagonal of :func:`constant_covariance`."""
    return np.diag(constant_covariance(plan)).copy()


def delta_E_sigma(XYZ, XYZ_sigma_cov, illuminant: str = "D65", observer: str | None = None, *,
                  wavelengths: ArrayLike | None = None,
                  integration: str = "rectangle") -> np.ndarray:
    """First-order propagation of an XYZ covariance (..., 3, 3) to dE2000 (..., ): the colour difference of a
    small perturbation is (to first order) its CIEDE2000 metric at the colour, ``dE^2 = dLab^T G dLab``; the
    sigma is ``sqrt(trace(G J C J^T))`` with J the XYZ -> Lab Jacobian at each pixel (analytic) and G the local
    CIEDE2000 metric (its diagonal along L*, a*, b*, by finite differences of colour-science's ``delta_E``; the
    stream's ``delta_e_sigma`` kernel computes the same on the device). The white is
    :func:`specgpu.core.spectra.white_point_XYZ`'s for ``illuminant`` (a name, or the white as xy or XYZ),
    ``observer`` (None: the CIE 1931 2 degree observer), ``wavelengths`` and ``integration``: the grid and
    integration the XYZ was made with."""
    xyz = np.asarray(XYZ, np.float64)
    C = np.asarray(XYZ_sigma_cov, np.float64)
    shape = xyz.shape[:-1]
    x = xyz.reshape(-1, 3)
    C = C.reshape(-1, 3, 3)
    # the XYZ -> Lab Jacobian analytically (CIE 1976: f(t) = t^(1/3) above (24/116)^3, linear below), in float64
    white = white_point_XYZ(illuminant, observer or DEFAULT_CMFS, wavelengths=wavelengths, integration=integration)
    lab = colour.XYZ_to_Lab(x, colour.XYZ_to_xy(white))
    eps = 216.0 / 24389.0
    t = x / white
    d = np.where(t > eps, (1.0 / 3.0) / np.cbrt(np.maximum(t, eps)) ** 2, 841.0 / 108.0) / white  # df/dX, dY, dZ
    J = np.zeros((x.shape[0], 3, 3))
    J[:, 0, 1] = 116.0 * d[:, 1]
    J[:, 1, 0], J[:, 1, 1] = 500.0 * d[:, 0], -500.0 * d[:, 1]
    J[:, 2, 1], J[:, 2, 2] = 200.0 * d[:, 1], -200.0 * d[:, 2]
    covLab = J @ C @ np.transpose(J, (0, 2, 1))
    # local CIEDE2000 metric: dE(lab, lab + e_i) ~ sqrt(G_ii) for unit steps along L, a, b
    step = 0.5
    diag = np.empty((x.shape[0], 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = step
        diag[:, i] = (np.asarray(colour.delta_E(lab, lab + e, method="CIE 2000"), np.float64) / step) ** 2
    var = np.einsum("ni,nii->n", diag, covLab)
    return np.sqrt(np.maximum(var, 0.0)).reshape(shape).astype(np.float32)
