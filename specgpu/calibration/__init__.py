"""The calibration bundle and its file, and the two feedback loops that measure it on a rig."""

from __future__ import annotations

from specgpu.calibration.bundle import (
    CalibrationBundle,
    CalibrationRig,
    LoopResult,
    MIRRORS_OFF_TOLERANCE,
    TwinCalibrationRig,
    as_calibration_rig,
    calibrate,
    calibration_error,
    camera_loop,
    capture_mean,
    distribute_counts,
    load_calibration,
    oracle_calibration,
    rig_fingerprint,
    save_calibration,
    spectral_loop,
)

__all__ = [
    "CalibrationBundle",
    "CalibrationRig",
    "LoopResult",
    "MIRRORS_OFF_TOLERANCE",
    "TwinCalibrationRig",
    "as_calibration_rig",
    "calibrate",
    "calibration_error",
    "camera_loop",
    "capture_mean",
    "distribute_counts",
    "load_calibration",
    "oracle_calibration",
    "rig_fingerprint",
    "save_calibration",
    "spectral_loop",
]

from specgpu.calibration.session import calibrate_on_rig  # noqa: E402

__all__ += ["calibrate_on_rig"]
