"""Calibration of the rig a description names: both feedback loops on the digital twin when it has no
``[hardware]`` table, else on the real devices (the camera looking at the reference white, the spectrometer at the
light's output), released when the loops end."""

from __future__ import annotations

from typing import TYPE_CHECKING

import specgpu.hardware.rig as hardware_rig
from specgpu.calibration import procedure

if TYPE_CHECKING:
    from specgpu.rig.config import RigDescription

__all__ = ["calibrate_on_rig"]


def calibrate_on_rig(description: RigDescription, *, hardware=None, seed: int = 0, line_shape: str = "gaussian"):
    """Run both feedback loops on the rig of ``description`` and return the calibration bundle.

    Parameters
    ----------
    description : specgpu.rig.config.RigDescription
    hardware : specgpu.hardware.rig.HardwareConfig, optional
        Its checked ``[hardware]`` table (:func:`specgpu.hardware.drivers.hardware_config`); None: the twin.
    seed : int
        Seed of the twin's noise; on hardware, of the loops' perturbed start only.
    line_shape : {"gaussian", "measured"}
        The light's line shape in the bundle.
    """
    if hardware is None:
        return procedure.calibrate(description, seed=seed, line_shape=line_shape)
    with hardware_rig.open_calibration_rig(description, hardware=hardware) as rig:
        return procedure.calibrate(description, seed=seed, rig=rig, line_shape=line_shape)
