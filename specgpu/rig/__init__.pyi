"""Public names of :mod:`specgpu.rig`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .camera import Camera, CameraParameters
from .config import FaultRates, RigDescription, dump_rig, load_rig, rig_from_dict
from .led import LED_PRESETS, LEDParameters
from .light import LightParameters, ProgrammableLight
from .lights import LIGHT_KINDS
from .motion import MotionParameters, MovingScene
from .ol490 import OL490Parameters
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
from .twin import FaultSchedule, SNRReport, TwinRig, measure_snr

__all__ = [
    "BUILTIN_SCENES",
    "Camera",
    "CameraParameters",
    "colorchecker_scene",
    "dump_rig",
    "FaultRates",
    "FaultSchedule",
    "LED_PRESETS",
    "LEDParameters",
    "LIGHT_KINDS",
    "LightParameters",
    "load_rig",
    "load_scene",
    "measure_snr",
    "MotionParameters",
    "MovingScene",
    "natural_scene",
    "OL490Parameters",
    "ProgrammableLight",
    "read_scene",
    "rig_from_dict",
    "RigDescription",
    "SNRReport",
    "SpectralScene",
    "Spectroradiometer",
    "SpectroradiometerParameters",
    "TwinRig",
    "white_plate_scene",
    "write_scene",
]
