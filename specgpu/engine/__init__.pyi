"""Public names of :mod:`specgpu.engine`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .colorimetry import DELTA_E_METHODS, FusedResult, XYZ_to_Lab, delta_E, frames_to_delta_E, reflectance_to_XYZ
from .guided import guided_filter, guided_filter_device
from .guided_variance import filtered_variance, filtered_variance_device
from .kernels import (
    launch_delta_E,
    launch_frames_to_delta_E,
    launch_linear,
    launch_XYZ_to_Lab,
    linear_matrix,
    prepare_delta_E_sigma,
    prepare_frames_to_delta_E,
    prepare_linear,
    prepare_XYZ_to_delta_E,
    to_device,
)
from .linear_map import LAYOUTS, LinearResult, apply_linear
from .noise_floor import FloorPlanes, PreparedNoiseFloors
from .registration import DeviceRegistration, register_gradients
from .residual import PreparedResidual, residual_chi2_device
from .runtime import DeviceInfo, SpecgpuDeviceError, get_queue, list_devices, select_device
from .selftest import SelftestReport, run_selftest
from .warp_map import apply_linear_warped
from .warped_variance import PreparedWarpedVariance

__all__ = [
    "apply_linear",
    "apply_linear_warped",
    "delta_E",
    "filtered_variance",
    "filtered_variance_device",
    "FloorPlanes",
    "DELTA_E_METHODS",
    "DeviceInfo",
    "DeviceRegistration",
    "frames_to_delta_E",
    "FusedResult",
    "get_queue",
    "guided_filter",
    "guided_filter_device",
    "launch_delta_E",
    "launch_frames_to_delta_E",
    "launch_linear",
    "launch_XYZ_to_Lab",
    "LAYOUTS",
    "linear_matrix",
    "LinearResult",
    "list_devices",
    "prepare_XYZ_to_delta_E",
    "prepare_delta_E_sigma",
    "prepare_frames_to_delta_E",
    "prepare_linear",
    "PreparedNoiseFloors",
    "PreparedResidual",
    "PreparedWarpedVariance",
    "reflectance_to_XYZ",
    "register_gradients",
    "residual_chi2_device",
    "run_selftest",
    "select_device",
    "SelftestReport",
    "SpecgpuDeviceError",
    "to_device",
    "XYZ_to_Lab",
]
