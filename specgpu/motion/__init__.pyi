"""Public names of :mod:`specgpu.motion`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .ambient import place_frame
from .candidates import choose_candidates
from .consistency import (
    CHECK_THRESHOLD,
    NOISE_FLOOR,
    consistency,
    inconsistent_pixels,
    noise_floors,
    noise_floors_on_device,
)
from .device_estimate import estimate_on_device
from .estimate import MotionEstimate, at_reference_time
from .flow import flow_field, tile_motion
from .global_motion import estimate_global_motion
from .images import frame_gradients, gradient_image
from .methods import MOTION_METHODS, check_motion_mode, estimate_motion
from .object_motion import estimate_layer_motion
from .reference import estimate_reference_motion
from .residual import ResidualCheck, residual_check, residual_chi2

__all__ = [
    "at_reference_time",
    "CHECK_THRESHOLD",
    "check_motion_mode",
    "choose_candidates",
    "consistency",
    "estimate_global_motion",
    "estimate_layer_motion",
    "estimate_motion",
    "estimate_on_device",
    "estimate_reference_motion",
    "flow_field",
    "frame_gradients",
    "gradient_image",
    "inconsistent_pixels",
    "MOTION_METHODS",
    "MotionEstimate",
    "NOISE_FLOOR",
    "noise_floors",
    "noise_floors_on_device",
    "place_frame",
    "residual_check",
    "residual_chi2",
    "ResidualCheck",
    "tile_motion",
]
