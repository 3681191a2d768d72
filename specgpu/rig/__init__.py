"""The physical system, modelled: light source, camera, scene and the synchronous twin.

Everything is NumPy on the host; the defaults reproduce the paper's rig (Tominaga and Horiuchi 2012, Section 2)
and every parameter can be overridden from a rig TOML (:func:`load_rig`).
"""

from specgpu.rig.camera import Camera, CameraParameters, sensitivity_curve
from specgpu.rig.config import FaultRates, RigDescription, dump_rig, load_rig, rig_from_dict
from specgpu.rig.led import LED_PRESETS, LEDLight, LEDParameters
from specgpu.rig.light import LightParameters, PatternFit, ProgrammableLight, lamp_spd
from specgpu.rig.lights import LIGHT_KINDS, light_kind, make_light
from specgpu.rig.motion import MotionParameters, MovingScene, Trajectory, motion_from_table, warp_image
from specgpu.rig.ol490 import OL490Light, OL490Parameters
from specgpu.rig.scene import (
                               BUILTIN_SCENES,
                               SpectralScene,
                               colorchecker_scene,
                               load_scene,
                               natural_scene,
                               read_scene,
                               white_plate_scene,
                               write_scene,
)
from specgpu.rig.spectroradiometer import Spectroradiometer, SpectroradiometerParameters
from specgpu.rig.twin import FaultSchedule, SNRReport, TwinRig, band_patterns, measure_snr

__all__ = [
    "Camera", "CameraParameters", "sensitivity_curve",
    "FaultRates", "RigDescription", "dump_rig", "load_rig", "rig_from_dict",
    "LightParameters", "PatternFit", "ProgrammableLight", "lamp_spd",
    "LED_PRESETS", "LEDLight", "LEDParameters",
    "LIGHT_KINDS", "light_kind", "make_light",
    "OL490Light", "OL490Parameters",
    "MotionParameters", "MovingScene", "Trajectory", "motion_from_table", "warp_image",
    "BUILTIN_SCENES", "SpectralScene", "colorchecker_scene", "load_scene", "natural_scene", "read_scene",
    "white_plate_scene", "write_scene",
    "Spectroradiometer", "SpectroradiometerParameters",
    "FaultSchedule", "SNRReport", "TwinRig", "band_patterns", "measure_snr",
]
