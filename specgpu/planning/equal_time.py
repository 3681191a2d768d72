"""Methods compared at equal sequence time (:data:`EQUAL_TIME`): the paper's designs, their Wiener decoders and
the photon-limited optimal designs, each made within one budget per frame count (9 frames in 60 ms, 6 in 40 ms,
3 in 20 ms: video rate), and the limit of any design of that frame count at that budget
(:func:`equal_time_bounds`). Used by ``specgpu demo``'s Table 1 and ``tools/studies/budget_study.py``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from specgpu.planning.bound import design_bound
from specgpu.planning.budget import budget_plan
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.rig.config import RigDescription

__all__ = ["EQUAL_TIME", "equal_time_plans", "equal_time_bounds", "row_name"]

#: budget (ms) -> frames, and the rows made within it: name -> (method, keyword arguments, estimator). The
#: 3-frame design minimises dE*ab under D65 (a colour imager), the others the reflectance RMSE.
EQUAL_TIME = {
    60.0: (9, {"symmetric-9": ("symmetric", {"m": 5}, "projection"),
               "wiener-9": ("symmetric", {"m": 5}, "wiener"),
               "optimal-9": ("optimal", {"frames": 9}, "wiener")}),
    40.0: (6, {"biased-6": ("biased", {"m": 5}, "projection"),
               "wiener-6": ("biased", {"m": 5}, "wiener"),
               "optimal-6": ("optimal", {"frames": 6}, "wiener")}),
    20.0: (3, {"tristimulus-D65": ("tristimulus", {"illuminant": "D65"}, "projection"),
               "optimal-3": ("optimal", {"frames": 3, "objective": "dEab"}, "wiener")}),
}


def row_name(name: str, budget_ms: float) -> str:
    """The name of a row at a budget: ``optimal-9@60ms``."""
    return f"{name}@{budget_ms:g}ms"


def equal_time_plans(description: RigDescription, bundle: CalibrationBundle, prior, basis, *, training=None,
                     extra_frames: int = 0, budgets=None,
                     starts: int = 1, iterations: int = 100, denoise_radius: int | None = None,
                     rows=None) -> dict:
    """The plans of :data:`EQUAL_TIME` (``budgets``: a subset of its keys; ``rows``: of its row names, such as
    ``"optimal-9"``; None: all), each within its budget with
    ``extra_frames`` frames more per sequence (an ambient frame), named by :func:`row_name`, every one with the
    camera's noise model and its expected error on ``prior`` recorded. ``training``: the spectra of a colour
    objective's weighting (the prior's own set); ``starts``, ``iterations``: the designs' search;
    ``denoise_radius``: each optimal row also designed for ``recover --denoise`` at that radius
    (:func:`specgpu.planning.design.plan_optimal`), named ``<name>+denoise``."""

    def noise_at(t):
        return NoiseModel.from_rig(description, t)

    floor = description.camera.min_frame_period_s
    ow = np.arange(400.0, 700.0 + 1e-9, 10.0)
    plans = {}
    for T in (EQUAL_TIME if budgets is None else budgets):
        _, made_rows = EQUAL_TIME[T]
        for name, (method, kw, est) in made_rows.items():
            if rows is not None and name not in rows:
                continue
            if method == "optimal":
                tr = training if kw.get("objective", "rmse") != "rmse" else None
                made = {name: None}
                if denoise_radius is not None:
                    made[f"{name}+denoise"] = int(denoise_radius)
                for label, radius in made.items():
                    plans[row_name(label, T)] = budget_plan(
                        "optimal", bundle, T / 1e3, prior, noise_at, output_wavelengths=ow, training=tr,
                        starts=starts, iterations=iterations, min_frame_period_s=floor, extra_frames=extra_frames,
                        denoise_radius=radius, **kw)
                continue
            args = (basis,) if method in ("biased", "symmetric") else ()
            extra = {"output_wavelengths": ow} if method in ("biased", "symmetric") else {}
            plan = budget_plan(method, bundle, T / 1e3, *args, min_frame_period_s=floor,
                               extra_frames=extra_frames, **kw, **extra)
            plans[row_name(name, T)] = with_estimator(plan, bundle, est, prior=prior, noise=noise_at(plan.exposure_s))
    return plans


def equal_time_bounds(description: RigDescription, bundle: CalibrationBundle, prior, *, extra_frames: int = 0,
                      budgets=None, starts: int = 4,
                      iterations: int = 300, averaged: float = 1.0) -> dict:
    """budget (ms) -> :class:`~specgpu.planning.bound.Bound` of :data:`EQUAL_TIME`'s frame count at that budget
    (``extra_frames`` frames of the budget left to an ambient frame; ``averaged``: the shot and read noise as a
    mean over that many pixels, where a filter flattens it)."""
    out = {}
    for T in (EQUAL_TIME if budgets is None else budgets):
        K, _ = EQUAL_TIME[T]
        per = (T / 1e3) * K / (K + extra_frames)  # the share of the budget the K designed frames get
        out[T] = design_bound(bundle, prior, lambda t: NoiseModel.from_rig(description, t), frames=K,
                              sequence_s=per, min_frame_period_s=description.camera.min_frame_period_s,
                              starts=starts, iterations=iterations, averaged=averaged)
    return out
