"""Public names of :mod:`specgpu.calibration`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .bundle import (
    CALIBRATION_FORMAT,
    CALIBRATION_VERSION,
    CalibrationBundle,
    calibration_error,
    load_calibration,
    oracle_calibration,
    rig_fingerprint,
    save_calibration,
)
from .cache import cached_calibration, calibration_file, find_calibration
from .loops import LoopResult, camera_loop, spectral_loop
from .on_rig import calibrate_on_rig
from .procedure import calibrate
from .rigs import CalibrationRig, TwinCalibrationRig

__all__ = [
    "calibrate",
    "calibrate_on_rig",
    "cached_calibration",
    "calibration_file",
    "calibration_error",
    "CALIBRATION_FORMAT",
    "CALIBRATION_VERSION",
    "CalibrationBundle",
    "CalibrationRig",
    "find_calibration",
    "camera_loop",
    "load_calibration",
    "LoopResult",
    "oracle_calibration",
    "rig_fingerprint",
    "save_calibration",
    "spectral_loop",
    "TwinCalibrationRig",
]
