"""The OpenCL engine: runtime (device order, program cache, the one kernel loader), launchers, transfers, the
linear map, colorimetry, selftest.

The NumPy-facing API (``apply_linear``, ``XYZ_to_Lab``, ``delta_E``, ``reflectance_to_XYZ``,
``frames_to_delta_E``) validates its inputs and accepts host or device arrays; the ``launch_*`` and ``prepare_*``
launchers of :mod:`specgpu.engine.kernels` take device arrays already validated.
"""

from __future__ import annotations

from specgpu.engine.runtime import (
    DTYPE_TO_CTYPE,
    DeviceInfo,
    SpecgpuDeviceError,
    VARIANTS,
    build_options,
    get_allocator,
    get_kernel,
    get_queue,
    is_discrete,
    kernel_dir,
    kernel_source,
    kernel_variant,
    list_devices,
    select_device,
)
from specgpu.engine.kernels import (
    DE_CODES,
    FusedOutputs,
    Prepared,
    VW,
    gain_map,
    launch_XYZ_to_Lab,
    launch_delta_E,
    launch_frames_to_delta_E,
    launch_linear,
    linear_matrix,
    matrix_on_device,
    pixel_map,
    prepare_delta_E_sigma,
    prepare_frames_to_delta_E,
    prepare_linear,
    to_device,
)
from specgpu.engine.transfer import (
    MODES,
    linear_pipelined,
    pinned_empty,
    transfer_mode,
)
from specgpu.engine.linear_map import (
    LAYOUTS,
    LinearResult,
    apply_linear,
)
from specgpu.engine.warp_map import (
    MASK_OUTSIDE,
    PreparedWarp,
    apply_linear_warped,
    check_shifts,
    prepare_linear_warped,
)
from specgpu.engine.colorimetry import (
    DELTA_E_METHODS,
    FusedResult,
    XYZ_to_Lab,
    delta_E,
    frames_to_delta_E,
    reflectance_to_XYZ,
)
from specgpu.engine.selftest import (
    CASES,
    CaseResult,
    SelftestReport,
    golden_path,
    load_golden,
    run_selftest,
)

__all__ = [
    "CASES",
    "CaseResult",
    "DELTA_E_METHODS",
    "DE_CODES",
    "DTYPE_TO_CTYPE",
    "DeviceInfo",
    "FusedOutputs",
    "FusedResult",
    "LAYOUTS",
    "LinearResult",
    "MODES",
    "Prepared",
    "PreparedWarp",
    "SelftestReport",
    "SpecgpuDeviceError",
    "VARIANTS",
    "VW",
    "XYZ_to_Lab",
    "MASK_OUTSIDE",
    "apply_linear",
    "apply_linear_warped",
    "check_shifts",
    "build_options",
    "delta_E",
        "frames_to_delta_E",
        "get_allocator",
    "get_kernel",
    "get_queue",
    "golden_path",
    "is_discrete",
    "kernel_dir",
    "kernel_source",
    "kernel_variant",
    "gain_map",
    "launch_XYZ_to_Lab",
    "launch_delta_E",
    "launch_frames_to_delta_E",
    "launch_linear",
    "linear_matrix",
    "linear_pipelined",
    "list_devices",
    "load_golden",
    "matrix_on_device",
    "pinned_empty",
    "pixel_map",
    "prepare_delta_E_sigma",
    "prepare_frames_to_delta_E",
    "prepare_linear",
    "prepare_linear_warped",
    "reflectance_to_XYZ",
    "run_selftest",
    "select_device",
    "to_device",
    "transfer_mode",
]

from specgpu.engine.guided import box_box_variance, flat_variance_reduction, guided_filter  # noqa: E402

__all__ += ["box_box_variance", "flat_variance_reduction", "guided_filter"]
from specgpu.engine.consistency import (consistency_from_frames, consistency_maps,  # noqa: E402
                                        consistency_maps_numpy, exact_median)
from specgpu.engine.gradients import gradient_images  # noqa: E402

__all__ += ["consistency_from_frames", "consistency_maps", "consistency_maps_numpy", "exact_median", "gradient_images"]
