"""Decoders beyond the paper's projections: Wiener (LMMSE) and smoothness-regularised least squares, and the
expected error of any decoder on a prior.

Every estimator here is still one per-pixel linear map ``y = A (o - dark) * gain``, so the
device kernels do not change; only the host decides A.

Notation (per plan): the calibration's forward model gives ``F`` (K x B), the frames' output in DN above dark per
unit reflectance on the prior's grid (``o = F r + noise``); ``W`` (P x B) maps a reflectance on that grid to the
plan's outputs (interpolation for reflectance outputs, colour-matching weights for XYZ).

- **Prior** (:class:`specgpu.planning.priors.Prior`): the training spectra's second moment ``S = E[r r^T]`` and
  mean ``mu``; the best *linear* map through the origin is ``A = W S F^T (F S F^T + N)^-1``.
- **Noise** (:class:`specgpu.planning.noise.NoiseModel`): per frame, in DN^2, ``var o_k = o_k / g + s_read^2 +
  (l o_k)^2``, at the expected signal over the prior.
- **Expected error** (:func:`expected_error`) of *any* linear decoder A on the prior:
  ``E = W S W^T - A F S W^T - W S F^T A^T + A (F S F^T + N) A^T``; its diagonal per output, its mean the MSE.
- **Smooth** (:func:`smooth_decoder`): for users with no training set, ``A = W (F^T N^-1 F + C^-1)^-1 F^T N^-1``:
  least squares regularised by the norm of a smooth prior C (a flat level plus squared-exponential variation).

The per-pixel uncertainty of the outputs is :mod:`specgpu.planning.uncertainty`'s.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.spectra import XYZ_weights
from specgpu.planning.noise import NoiseModel
from specgpu.planning.priors import Prior, smooth_prior

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan

__all__ = ["ESTIMATORS", "forward", "output_weights", "interp_rows", "wiener_decoder", "smooth_decoder",
           "expected_error", "with_estimator"]

#: Estimator names: the plan's own decoder, Wiener (LMMSE) on a training prior, smoothness-regularised LS.
ESTIMATORS = ("projection", "wiener", "smooth")


# ---- forward model and output weights ----------------------------------------------------------------------------
def forward(bundle, plan, wavelengths) -> np.ndarray:
    """(K, B) model output (DN above dark, flat-fielded) of the plan's frames per unit reflectance on
    ``wavelengths``, at the plan's exposure."""
    return bundle.forward_matrix(plan.patterns, wavelengths, plan.exposure_s)


def output_weights(plan, wavelengths) -> np.ndarray:
    """(P, B) matrix W giving the plan's ideal outputs from a reflectance on ``wavelengths``: interpolation for a
    reflectance plan, colour-matching weights for an XYZ plan; other outputs have no Wiener form (ValueError)."""
    wl = np.asarray(wavelengths, np.float64)
    if plan.output == "reflectance":
        return interp_rows(plan.output_wavelengths, wl)
    if plan.output == "XYZ":
        return XYZ_weights(wl, plan.illuminant or "D65", plan.observer or "CIE 1931 2 Degree Standard Observer")
    raise ValueError(f"a {plan.output!r} plan ({plan.method}) has no estimator other than its projection")


def interp_rows(points, grid) -> np.ndarray:
    """(P, B) rows that linearly interpolate a function on ``grid`` at ``points`` (constant beyond the ends)."""
    p = np.asarray(points, np.float64)
    g = np.asarray(grid, np.float64)
    return np.stack([np.interp(p, g, e) for e in np.eye(g.size)], axis=1)


# ---- decoders ----------------------------------------------------------------------------------------------------
def wiener_decoder(F: ArrayLike, W: ArrayLike, prior: Prior, noise: NoiseModel) -> np.ndarray:
    """LMMSE decoder (P, K) through the origin: ``W S F^T (F S F^T + N)^-1``."""
    F = np.asarray(F, np.float64)
    S = prior.moment
    M = F @ S @ F.T + noise.covariance(F, prior)
    return np.linalg.solve(M, F @ S @ np.asarray(W, np.float64).T).T


def smooth_decoder(F, W, noise: NoiseModel, wavelengths, *, correlation_nm: float = 40.0) -> np.ndarray:
    """Smoothness-regularised least squares (P, K) for users with no training set:
    ``W argmin_r |N^-1/2 (F r - o)|^2 + r^T C^-1 r`` with C the :func:`smooth_prior`'s second moment, i.e.
    ``W (F^T N^-1 F + C^-1)^-1 F^T N^-1`` (computed in the equivalent form ``W C F^T (F C F^T + N)^-1``)."""
    return wiener_decoder(F, W, smooth_prior(wavelengths, correlation_nm=correlation_nm), noise)


def expected_error(A: ArrayLike, F: ArrayLike, W: ArrayLike, prior: Prior, noise: NoiseModel) -> dict:
    """Expected error of a decoder (P, K) on the prior: ``{"mse": (P,) total, "mismatch": (P,) the part with no
    noise, "noise": (P,) the part from the noise, "rmse": sqrt(mean mse)}``."""
    A = np.asarray(A, np.float64)
    F = np.asarray(F, np.float64)
    W = np.asarray(W, np.float64)
    S = prior.moment
    bias = W - A @ F
    mismatch = np.einsum("pb,bc,pc->p", bias, S, bias)
    noise_part = np.einsum("pk,kl,pl->p", A, noise.covariance(F, prior), A)
    mse = mismatch + noise_part
    return {"mse": mse, "mismatch": mismatch, "noise": noise_part, "rmse": float(math.sqrt(max(mse.mean(), 0.0)))}


def with_estimator(plan: Plan, bundle: CalibrationBundle, estimator: str, *, prior: Prior | None = None,
                   noise: NoiseModel,
                   correlation_nm: float = 40.0, decoder_noise: NoiseModel | None = None):
    """The plan with its decoder replaced by ``estimator`` (:data:`ESTIMATORS`), with the noise model and the
    expected error recorded in ``params`` (``"estimator"``, ``"noise"``, ``"expected"``: RMSE, per-output
    mismatch variance). ``"projection"`` keeps the decoder and records its expected error when a prior is given.

    ``decoder_noise``: build the Wiener or smooth decoder for this noise instead of ``noise`` (the noise left after
    a spatial filter, :meth:`NoiseModel.averaged`); ``noise``, the camera's own, stays the plan's noise model (the
    per-pixel sigma maps come from it) and the expected error is stated at both (``expected["rmse"]`` at ``noise``,
    ``expected["rmse_at_decoder_noise"]``), ``params["decoder_noise"]`` recording the other."""
    est = str(estimator).lower()
    if est not in ESTIMATORS:
        raise ValueError(f"unknown estimator {estimator!r}; valid: {', '.join(ESTIMATORS)}")
    if est == "wiener" and prior is None:
        raise ValueError("the wiener estimator needs a training prior")
    if decoder_noise is not None and est == "projection":
        raise ValueError("a decoder for another noise needs the wiener or smooth estimator (projection has none)")
    params = dict(plan.params)
    params["estimator"] = est
    params["noise"] = noise.as_params()
    params.pop("decoder_noise", None)
    if decoder_noise is not None:
        params["decoder_noise"] = decoder_noise.as_params()
    built_for = noise if decoder_noise is None else decoder_noise
    A = plan.A
    if est == "projection" and plan.output not in ("reflectance", "XYZ"):
        prior = None  # RGB / relative outputs: the decoder stays and no expected error can be stated
    if est != "projection" or prior is not None:
        wl = prior.wavelengths if prior is not None else np.arange(400.0, 700.0 + 1e-9, 5.0)
        F = forward(bundle, plan, wl)
        W = output_weights(plan, wl)
        if est == "wiener":
            A = wiener_decoder(F, W, prior, built_for)
        elif est == "smooth":
            A = smooth_decoder(F, W, built_for, wl, correlation_nm=correlation_nm)
            params["smooth_correlation_nm"] = float(correlation_nm)
            if prior is None:  # the expected error on the smoothness prior itself
                prior = smooth_prior(wl, correlation_nm=correlation_nm)
        if prior is not None:
            e = expected_error(A, F, W, prior, noise)
            bias = W - A @ F
            # what no frame shows: the prior's mismatch alone (the light's fluctuation is each frame's own, per
            # pixel: sigma_map adds it from the frames' signal)
            mismatch = bias @ prior.moment @ bias.T
            params["expected"] = {"rmse": e["rmse"], "mismatch_var": e["mismatch"].tolist(),
                                  "noise_var": e["noise"].tolist(), "mismatch_cov": mismatch.ravel().tolist(),
                                  "prior": prior.source, "n_training": prior.n}
            if decoder_noise is not None:
                params["expected"]["rmse_at_decoder_noise"] = expected_error(A, F, W, prior, decoder_noise)["rmse"]
    return replace(plan, A=np.asarray(A, np.float64), params=params)
