"""Public names of :mod:`specgpu.rig`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .camera import Camera, CameraParameters, sensitivity_curve
from .config import FaultRates, RigDescription, dump_rig, load_rig, rig_from_dict
from .light import LightParameters, PatternFit, ProgrammableLight, lamp_spd
from .motion import MotionParameters, MovingScene, Trajectory, motion_from_table, warp_image
from .scene import (
    BUILTIN_SCENES,
    SpectralScene,
    colorchecker_scene,
    load_scene,
    natural_scene,
    read_scene,
    white_plate_scene,
    write_scene,
)
from .spectroradiometer import Spectroradiometer, SpectroradiometerParameters
from .twin import FaultSchedule, SNRReport, TwinRig, band_patterns, measure_snr

__all__ = [
    "band_patterns",
    "BUILTIN_SCENES",
    "Camera",
    "CameraParameters",
    "colorchecker_scene",
    "dump_rig",
    "FaultRates",
    "FaultSchedule",
    "lamp_spd",
    "LightParameters",
    "load_rig",
    "load_scene",
    "measure_snr",
    "motion_from_table",
    "MotionParameters",
    "MovingScene",
    "natural_scene",
    "PatternFit",
    "ProgrammableLight",
    "read_scene",
    "rig_from_dict",
    "RigDescription",
    "sensitivity_curve",
    "SNRReport",
    "SpectralScene",
    "Spectroradiometer",
    "SpectroradiometerParameters",
    "Trajectory",
    "TwinRig",
    "warp_image",
    "white_plate_scene",
    "write_scene",
]
