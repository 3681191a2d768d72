"""The calibration bundle and its file, and the two feedback loops that measure it on a rig.

Modules: :mod:`~specgpu.calibration.bundle` (the bundle, its file and fingerprint, the twin's oracle bundle),
:mod:`~specgpu.calibration.rigs` (what calibration needs from a rig, the twin's, the capture helpers),
:mod:`~specgpu.calibration.loops` (loop (a), camera plus white; loop (b), spectroradiometer) and
:mod:`~specgpu.calibration.procedure` (:func:`calibrate`, the whole procedure).
"""

from __future__ import annotations

from specgpu.calibration.bundle import (
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
from specgpu.calibration.loops import LoopResult, camera_loop, spectral_loop
from specgpu.calibration.procedure import MIRRORS_OFF_TOLERANCE, calibrate
from specgpu.calibration.rigs import (
    CalibrationRig,
    TwinCalibrationRig,
    as_calibration_rig,
    capture_mean,
    distribute_counts,
)

__all__ = [
    "CALIBRATION_FORMAT",
    "CALIBRATION_VERSION",
    "DEFAULT_MAX_EXPOSURE_S",
    "MIRRORS_OFF_TOLERANCE",
    "CalibrationBundle",
    "CalibrationRig",
    "LoopResult",
    "TwinCalibrationRig",
    "as_calibration_rig",
    "calibrate",
    "calibration_error",
    "camera_loop",
    "capture_mean",
    "distribute_counts",
    "load_calibration",
    "measure_line_shapes",
    "oracle_calibration",
    "rig_fingerprint",
    "save_calibration",
    "spectral_loop",
]
