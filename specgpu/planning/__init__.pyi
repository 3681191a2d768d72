"""Public names of :mod:`specgpu.planning`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .basis import BasisTable, load_basis, load_reflectances, pca_basis, save_basis
from .basis_plans import plan_biased_basis, plan_symmetric_basis
from .bound import Bound, design_bound
from .budget import budget_plan
from .correction import WhiteReference, corrected_decoder, subtracting_ambient, with_ambient_frame, with_drift_probes
from .design import OBJECTIVES, design_optimal, plan_hadamard, plan_optimal
from .equal_time import EQUAL_TIME, equal_time_bounds, equal_time_plans
from .estimators import ESTIMATORS, expected_error, wiener_decoder, with_estimator
from .narrowband import plan_narrowband, plan_reciprocal_narrowband
from .noise import NoiseModel
from .plans import PLAN_FORMAT, Plan, load_plan, save_plan
from .priors import Prior, default_prior, prior_from_spectra, smooth_prior
from .reference_frames import with_reference_frames
from .registry import PLAN_METHODS, make_plan
from .response import plan_camera_simulator, plan_steady_state, plan_tristimulus
from .uncertainty import delta_E_sigma, sigma_map

__all__ = [
    "BasisTable",
    "Bound",
    "budget_plan",
    "corrected_decoder",
    "default_prior",
    "delta_E_sigma",
    "design_bound",
    "design_optimal",
    "EQUAL_TIME",
    "equal_time_bounds",
    "equal_time_plans",
    "ESTIMATORS",
    "expected_error",
    "load_basis",
    "load_plan",
    "load_reflectances",
    "make_plan",
    "NoiseModel",
    "OBJECTIVES",
    "pca_basis",
    "Plan",
    "plan_biased_basis",
    "plan_camera_simulator",
    "PLAN_FORMAT",
    "plan_hadamard",
    "PLAN_METHODS",
    "plan_narrowband",
    "plan_optimal",
    "plan_reciprocal_narrowband",
    "plan_steady_state",
    "plan_symmetric_basis",
    "plan_tristimulus",
    "Prior",
    "prior_from_spectra",
    "save_basis",
    "save_plan",
    "sigma_map",
    "smooth_prior",
    "subtracting_ambient",
    "WhiteReference",
    "wiener_decoder",
    "with_ambient_frame",
    "with_drift_probes",
    "with_estimator",
    "with_reference_frames",
]
