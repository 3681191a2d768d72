"""Named estimator and design configurations and the plans they make: the paper's methods beside Wiener decoders
and optimal illuminants (:data:`STUDY_METHODS`, :func:`study_plans`), with the errors they are judged by without
a capture: on known spectra (:func:`chart_error`) and on a chart the prior has not seen, by leaving one training
set out at a time (:func:`cross_validated_error`). ``specgpu demo``'s estimator rows and
``tools/studies/estimator_study.py`` plan with them.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from specgpu.planning.design import plan_optimal
from specgpu.planning.estimators import expected_error, forward, output_weights, wiener_decoder, with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.priors import HELD_OUT_CHART, Prior, prior_from_spectra, training_database, training_spectra
from specgpu.planning.registry import make_plan

__all__ = ["STUDY_METHODS", "study_plans", "training_sets", "cross_validated_error", "chart_error"]


#: Rows of the estimator study: name -> (method, keyword arguments, estimator). Optimal plans take the design's
#: own keywords (frames, objective, exposure_s, max_exposure_s). Designs expose at most 0.1 s: past it a lab's
#: room light (3 lux, the ambient frame) fills the white's headroom above the designed level, for a gain of 1 %
#: in expected RMSE on the prior (0.0090 at 0.22 s against 0.0091 at 0.1 s for optimal-9).
STUDY_METHODS = {
    "narrowband-31": ("narrowband", {"step_nm": 10.0}, "projection"),
    "biased-6": ("biased", {"m": 5}, "projection"),
    "symmetric-9": ("symmetric", {"m": 5}, "projection"),
    "tristimulus-D65": ("tristimulus", {"illuminant": "D65"}, "projection"),
    "wiener-6": ("biased", {"m": 5}, "wiener"),
    "wiener-9": ("symmetric", {"m": 5}, "wiener"),
    "optimal-9": ("optimal", {"frames": 9, "max_exposure_s": 0.1}, "wiener"),
    "optimal-6": ("optimal", {"frames": 6, "max_exposure_s": 0.1}, "wiener"),
    "optimal-3": ("optimal", {"frames": 3, "objective": "dEab", "exposure_s": 0.1}, "wiener"),
}


def study_plans(description, bundle, prior, basis, *, methods=None, training=None,
                chart: str = HELD_OUT_CHART, starts: int = 4, iterations: int = 300,
                sets: dict | None = None) -> dict:
    """The plans of :data:`STUDY_METHODS` (or the named subset), every one with the camera's noise model and its
    expected error on the prior recorded. A colour objective (optimal-3) weighs the error by the colours of
    ``training`` (default: :func:`training_spectra` without ``chart``, the evaluation chart); ``starts`` and
    ``iterations``: the designs' starting points and L-BFGS-B iterations
    (:func:`specgpu.planning.design.design_optimal`). With ``sets`` (the prior's spectra by set,
    :func:`training_sets`) every Wiener plan also records ``expected["rmse_cv"]``, its
    :func:`cross_validated_error`."""
    def noise_at(t):
        return NoiseModel.from_rig(description, t)

    ow = np.arange(400.0, 700.0 + 1e-9, 10.0)
    plans = {}
    for name in (methods or STUDY_METHODS):
        method, kw, est = STUDY_METHODS[name]
        if method == "optimal":
            tr = None
            if kw.get("objective", "rmse") != "rmse":
                tr = training_spectra(chart, prior.wavelengths) if training is None else training
            plans[name] = plan_optimal(bundle, prior, noise_at, output_wavelengths=ow, training=tr, starts=starts,
                                       iterations=iterations, **kw)
            continue
        args = (basis,) if method in ("biased", "symmetric") else ()
        extra = {"output_wavelengths": ow} if method in ("biased", "symmetric") else {}
        plan = make_plan(method, bundle, *args, **kw, **extra)
        plans[name] = with_estimator(plan, bundle, est, prior=prior, noise=noise_at(plan.exposure_s))
    if sets is not None:
        for name, plan in plans.items():
            if plan.params.get("estimator") == "wiener":
                cv = cross_validated_error(plan, bundle, sets, prior, noise_at(plan.exposure_s))
                plans[name] = replace(plan, params={**plan.params,
                                                    "expected": {**plan.params["expected"], "rmse_cv": cv["rmse"]}})
    return plans


def training_sets(chart: str = HELD_OUT_CHART, wavelengths=None) -> dict:
    """:func:`training_database`'s spectra by set: name -> (N, B)."""
    db = training_database(chart, wavelengths)
    names = np.array([label.split("/")[0] for label in db.labels])
    return {n: db.reflectance[names == n] for n in dict.fromkeys(names)}


def cross_validated_error(plan, bundle, sets: dict, prior: Prior, noise: NoiseModel) -> dict:
    """The expected RMSE of a Wiener plan on a chart the prior has not seen, by leaving one training set out at a
    time: for each set, the Wiener decoder of the plan's frames learnt from the other sets and its mismatch on
    that set's spectra; the mean over sets (each set weighs the same, as a new chart is one more set) of their
    mean squared mismatch, plus the noise part of the plan's own decoder on the whole prior. Returns ``{"rmse",
    "mismatch": {set: RMS mismatch}}``; fewer than two sets is a one-line error."""
    if len(sets) < 2:
        raise ValueError(f"cross-validation needs at least two training sets, got {len(sets)}")
    wl = prior.wavelengths
    F = forward(bundle, plan, wl)
    W = output_weights(plan, wl)
    per = {}
    for name, held in sets.items():
        rest = np.concatenate([r for n, r in sets.items() if n != name])
        A = wiener_decoder(F, W, prior_from_spectra(rest, wl), noise)
        per[name] = float(np.mean((np.asarray(held, np.float64) @ (W - A @ F).T) ** 2))
    noise_part = float(expected_error(plan.A, F, W, prior, noise)["noise"].mean())
    return {"rmse": float(math.sqrt(np.mean(list(per.values())) + noise_part)),
            "mismatch": {n: math.sqrt(v) for n, v in per.items()}}


def chart_error(plan, bundle, spectra, wavelengths, noise: NoiseModel | None = None) -> float:
    """The RMSE a reflectance plan's decoder is expected to reach on known spectra (N, B) on ``wavelengths``:
    the exact mean squared mismatch over them plus the noise at their own signal (no capture needed)."""
    r = np.asarray(spectra, np.float64)
    F = forward(bundle, plan, wavelengths)
    W = output_weights(plan, wavelengths)
    noise = noise or NoiseModel.from_params(plan.params["noise"])
    err = r @ (W - plan.A @ F).T
    N = np.diag(noise.covariance(F, prior_from_spectra(r, wavelengths)))
    return float(math.sqrt((err ** 2).mean() + ((plan.A ** 2) @ N).mean()))
