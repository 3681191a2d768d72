"""Planning: basis tables, measurement plans (one registry for every method, the optimal design and Hadamard
included), the noise model and training priors, the estimators, per-pixel uncertainty and drift correction."""

from __future__ import annotations

from specgpu.planning.basis import (
    BasisTable,
    COLORCHECKER_24_SETS,
    DEFAULT_WAVELENGTHS,
    REFLECTANCE_SETS,
    ReflectanceDatabase,
    evaluation_exclusions,
    load_basis,
    load_reflectances,
    pca_basis,
    read_reflectance_csv,
    save_basis,
)
from specgpu.planning.plans import (
    PLAN_FORMAT,
    Plan,
    load_plan,
    save_plan,
)
from specgpu.planning.registry import (
    PLAN_METHODS,
    make_plan,
)
from specgpu.planning.narrowband import (
    plan_narrowband,
    plan_reciprocal_narrowband,
)
from specgpu.planning.basis_plans import (
    plan_biased_basis,
    plan_symmetric_basis,
)
from specgpu.planning.response import (
    camera_sensitivities,
    plan_camera_simulator,
    plan_steady_state,
    plan_tristimulus,
)
from specgpu.planning.design import (
    OBJECTIVES,
    design_optimal,
    objective_weights,
    plan_hadamard,
    plan_optimal,
    s_matrix,
    wiener_objective,
)
from specgpu.planning.noise import (
    NoiseModel,
)
from specgpu.planning.priors import (
    HELD_OUT_CHART,
    Prior,
    default_prior,
    held_out_basis,
    held_out_spectra,
    prior_from_spectra,
    read_training,
    smooth_prior,
    subspace_bound,
    training_database,
    training_spectra,
)
from specgpu.planning.estimators import (
    ESTIMATORS,
    expected_error,
    forward,
    output_weights,
    smooth_decoder,
    wiener_decoder,
    with_estimator,
)
from specgpu.planning.uncertainty import (
    ambient_variance,
    constant_covariance,
    constant_variance,
    delta_E_sigma,
    frame_covariance,
    frame_variance,
    output_covariance,
    sigma_map,
    variance_rows,
)
from specgpu.planning.correction import (
    DEFAULT_WHITE_REFLECTANCE,
    WhiteReference,
    ambient_index,
    ambient_needed,
    corrected_decoder,
    gain_noise,
    parse_roi,
    probe_indices,
    white_gains,
    white_reflectance_curve,
    with_ambient_frame,
    with_drift_probes,
)

__all__ = [
    "BasisTable",
    "COLORCHECKER_24_SETS",
    "DEFAULT_WAVELENGTHS",
    "DEFAULT_WHITE_REFLECTANCE",
    "ESTIMATORS",
    "HELD_OUT_CHART",
    "NoiseModel",
    "OBJECTIVES",
    "PLAN_FORMAT",
    "PLAN_METHODS",
    "Plan",
    "Prior",
    "REFLECTANCE_SETS",
    "ReflectanceDatabase",
    "WhiteReference",
    "ambient_index",
    "ambient_needed",
    "ambient_variance",
    "camera_sensitivities",
    "constant_covariance",
    "constant_variance",
    "corrected_decoder",
    "default_prior",
    "delta_E_sigma",
    "design_optimal",
    "evaluation_exclusions",
    "expected_error",
    "forward",
    "frame_covariance",
    "frame_variance",
    "gain_noise",
    "held_out_basis",
    "held_out_spectra",
    "load_basis",
    "load_plan",
    "load_reflectances",
    "make_plan",
    "objective_weights",
    "output_covariance",
    "output_weights",
    "parse_roi",
    "pca_basis",
    "plan_biased_basis",
    "plan_camera_simulator",
    "plan_hadamard",
    "plan_narrowband",
    "plan_optimal",
    "plan_reciprocal_narrowband",
    "plan_steady_state",
    "plan_symmetric_basis",
    "plan_tristimulus",
    "prior_from_spectra",
    "probe_indices",
    "read_reflectance_csv",
    "read_training",
    "s_matrix",
    "save_basis",
    "save_plan",
    "sigma_map",
    "smooth_decoder",
    "smooth_prior",
    "subspace_bound",
    "training_database",
    "training_spectra",
    "variance_rows",
    "white_gains",
    "white_reflectance_curve",
    "wiener_decoder",
    "wiener_objective",
    "with_ambient_frame",
    "with_drift_probes",
    "with_estimator",
]

from specgpu.planning.requests import estimated_plan  # noqa: E402

__all__ += ["estimated_plan"]

from specgpu.planning.timing import budget_params, check_budget, exposure_within, extra_count  # noqa: E402
from specgpu.planning.budget import budget_plan  # noqa: E402
from specgpu.planning.bound import Bound, design_bound  # noqa: E402
from specgpu.planning.equal_time import EQUAL_TIME, equal_time_bounds, equal_time_plans  # noqa: E402

__all__ += ["exposure_within", "budget_params", "check_budget", "extra_count", "budget_plan", "Bound", "design_bound",
            "EQUAL_TIME", "equal_time_bounds", "equal_time_plans"]

from specgpu.planning.reference_frames import (  # noqa: E402
    check_reference_every, pattern_indices, reference_count, reference_indices, reference_positions,
    with_reference_frames)

__all__ += ["check_reference_every", "pattern_indices", "reference_count", "reference_indices",
            "reference_positions", "with_reference_frames"]

from specgpu.planning.bound import primaries_limit  # noqa: E402
from specgpu.planning.registry import NARROWBAND_METHODS, check_light_can  # noqa: E402

__all__ += ["primaries_limit", "NARROWBAND_METHODS", "check_light_can"]
