"""Public names of :mod:`specgpu.calibration`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .bundle import (
    CALIBRATION_FORMAT,
    CALIBRATION_VERSION,
    DEFAULT_MAX_EXPOSURE_S,
    CalibrationBundle,
    calibration_error,
    load_calibration,
    measure_line_shapes,
    oracle_calibration,
    rig_fingerprint,
    save_calibration,
)
from .loops import LoopResult, camera_loop, spectral_loop
from .on_rig import calibrate_on_rig
from .procedure import MIRRORS_OFF_TOLERANCE, calibrate
from .rigs import CalibrationRig, TwinCalibrationRig, as_calibration_rig, capture_mean, distribute_counts

__all__ = [
    "as_calibration_rig",
    "calibrate",
    "calibrate_on_rig",
    "calibration_error",
    "CALIBRATION_FORMAT",
    "CALIBRATION_VERSION",
    "CalibrationBundle",
    "CalibrationRig",
    "camera_loop",
    "capture_mean",
    "DEFAULT_MAX_EXPOSURE_S",
    "distribute_counts",
    "load_calibration",
    "LoopResult",
    "measure_line_shapes",
    "MIRRORS_OFF_TOLERANCE",
    "oracle_calibration",
    "rig_fingerprint",
    "save_calibration",
    "spectral_loop",
    "TwinCalibrationRig",
]
