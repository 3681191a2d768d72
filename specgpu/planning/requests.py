"""A plan as ``specgpu plan`` asks for it: the method's plan with the chosen decoder (the method's own, Wiener on
a training prior, or smoothness-regularised least squares), the camera's noise model and the expected error
recorded; the optimal design and the Hadamard plan made the same way."""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import replace

import numpy as np

from specgpu.calibration.bundle import load_calibration, oracle_calibration, rig_fingerprint
from specgpu.engine.guided import flat_variance_reduction
from specgpu.planning.bound import design_bound
from specgpu.planning.budget import budget_plan
from specgpu.planning.design import denoise_params
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.priors import default_prior, training_spectra
from specgpu.planning.registry import make_plan
from specgpu.rig.config import load_rig

__all__ = ["estimated_plan", "requested_bound"]


def _quiet(desc):
    return nullcontext()


def estimated_plan(method, bundle, args, kwargs, estimator, training, training_only, exclude_chart, frames,
                   objective, target, exposure_ms, bands, illuminant, output_step_nm, rig_path, smooth_nm=40.0,
                   progress=_quiet, sequence_ms=None, extra_frames=0, denoise_radius=None):
    """The plan of ``method`` with the chosen decoder, the camera's noise model and its expected error recorded.

    ``args`` / ``kwargs`` go to :func:`~specgpu.planning.registry.make_plan`; ``frames``, ``objective``, ``target``
    and ``exposure_ms`` to the optimal design, ``bands`` to the Hadamard plan; ``progress(description)`` gives a
    context manager shown around the slow steps. A plan without a noise model is made only where no ``rig_path``
    names the custom rig the calibration was made on and nothing needs one. ``sequence_ms``: the time budget of
    one sequence with ``extra_frames`` frames more (:func:`specgpu.planning.budget.budget_plan`); every plan
    records the camera's read-out floor of the frame period. ``denoise_radius``: the decoder (and the optimal
    design) made for the noise ``recover --denoise`` leaves with that radius (the wiener or smooth estimator,
    or the optimal design; :func:`specgpu.planning.design.plan_optimal`).
    """
    if denoise_radius is not None and method != "optimal" and estimator == "projection":
        raise ValueError(f"--denoise designs the decoder for the filtered noise: the {method} plan's own decoder "
                         "has no noise to design for; give --estimator wiener (or smooth)")
    description = load_rig(rig_path)
    sequence_s = None if sequence_ms is None else float(sequence_ms) / 1e3
    plain = method not in ("optimal", "hadamard") and estimator == "projection" and not training
    if plain and rig_path is None and bundle.rig and bundle.rig != rig_fingerprint(description):
        if sequence_s is not None:
            raise ValueError("a time budget needs the rig the calibration was made on (its camera's read-out): "
                             "give that rig's description with --rig")
        return make_plan(method, bundle, *args, **kwargs)  # no --rig for a custom rig's camera: no noise model
    if bundle.rig and bundle.rig != rig_fingerprint(description):
        raise ValueError(f"{'--rig ' + str(rig_path) if rig_path else 'the default rig'} is not the rig the "
                         "calibration was made on: give that rig's description with --rig (its camera's noise "
                         "model is needed)")

    def noise_at(t):
        return NoiseModel.from_rig(description, t)

    floor = description.camera.min_frame_period_s

    prior = None
    if method == "optimal" or estimator == "wiener" or training or training_only:
        with progress("building the training prior"):
            prior = default_prior(exclude_chart, training_files=training, builtin=not training_only)
    if method == "optimal":
        tr = None
        if objective.lower() != "rmse":
            tr = training_spectra(exclude_chart, prior.wavelengths, training_files=training,
                                  builtin=not training_only)
        with progress(f"designing {frames} illuminants"):
            return budget_plan("optimal", bundle, sequence_s, prior, noise_at, frames=frames, objective=objective,
                               illuminant=illuminant, training=tr,
                               output_wavelengths=np.arange(400.0, 700.0 + 1e-9, output_step_nm), target=target,
                               exposure_s=None if exposure_ms is None else exposure_ms / 1e3,
                               min_frame_period_s=floor, extra_frames=extra_frames, denoise_radius=denoise_radius)
    if method == "hadamard":
        args, kwargs = (), {"bands": bands}
    plan = budget_plan(method, bundle, sequence_s, *args, min_frame_period_s=floor, extra_frames=extra_frames,
                       **kwargs)
    if denoise_radius is None:
        return with_estimator(plan, bundle, estimator, prior=prior, noise=noise_at(plan.exposure_s),
                              correlation_nm=smooth_nm)
    denoise = denoise_params(denoise_radius)
    plan = replace(plan, params={**plan.params, "denoise": denoise})
    camera = noise_at(plan.exposure_s)
    return with_estimator(plan, bundle, estimator, prior=prior, noise=camera, correlation_nm=smooth_nm,
                          decoder_noise=camera.averaged(denoise["variance_reduction"]))


def requested_bound(calib, rig_path, frames, sequence_ms, exclude_chart, starts=8, progress=_quiet,
                    denoise_radius=None):
    """:func:`~specgpu.planning.bound.design_bound` as ``specgpu bound`` asks for it: the calibration file
    ``calib`` (None: the oracle calibration of the rig), the rig (``rig_path``, None: the default; its camera's
    noise and read-out), the default prior without ``exclude_chart``; ``denoise_radius``: the limit where
    ``recover --denoise`` with that radius flattens the shot and read noise."""
    description = load_rig(rig_path)
    if calib is None:
        bundle = oracle_calibration(description)
    else:
        bundle = load_calibration(calib)
        if bundle.rig and bundle.rig != rig_fingerprint(description):
            raise ValueError(f"{'--rig ' + str(rig_path) if rig_path else 'the default rig'} is not the rig "
                             f"{calib} was made on: give that rig's description with --rig")
    with progress("building the training prior"):
        prior = default_prior(exclude_chart)
    with progress(f"designing {frames} illuminants ({starts} starts)"):
        return design_bound(bundle, prior, lambda t: NoiseModel.from_rig(description, t), frames=int(frames),
                            sequence_s=float(sequence_ms) / 1e3,
                            min_frame_period_s=description.camera.min_frame_period_s, starts=starts,
                            averaged=1.0 if denoise_radius is None else flat_variance_reduction(denoise_radius))
