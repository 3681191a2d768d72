"""The camera driver a rig description names: the digital twin when it has no ``[hardware]`` table, else the real
devices (a GenICam camera lit by a DLPC900, an LED array or an OL490), each with a plan's illuminant sequence
uploaded. The one place that chooses between the two, for the stream and the capture alike."""

from __future__ import annotations

from typing import TYPE_CHECKING

import specgpu.hardware.rig as hardware_rig
from specgpu.capture.twin_driver import TwinDriver
from specgpu.rig.twin import TwinRig

if TYPE_CHECKING:
    from specgpu.rig.config import RigDescription
    from specgpu.rig.scene import SpectralScene

__all__ = ["hardware_config", "open_rig_driver"]


def hardware_config(description: RigDescription):
    """The rig description's ``[hardware]`` table checked, as a :class:`~specgpu.hardware.rig.HardwareConfig`;
    None for the twin (no table)."""
    if not description.hardware:
        return None
    return hardware_rig.HardwareConfig.from_dict(description.hardware, source=description.source,
                                                 base_dir=description.base_dir or None,
                                                 kind=getattr(description.light, "kind", None))


def open_rig_driver(description: RigDescription, plan, *, hardware=None, scene: SpectralScene | None = None,
                    calibration=None, seed: int | None = None, pacing: str = "paced",
                n_frames: int | None = None):
    """Open the camera driver of ``description`` with ``plan``'s patterns.

    Parameters
    ----------
    description : specgpu.rig.config.RigDescription
    plan : specgpu.planning.plans.Plan
        Its patterns are uploaded; the twin captures with ``plan.rig_description(description)``, real devices at
        ``plan.exposure_s`` (its dark frame and decoder are for that exposure).
    hardware : HardwareConfig, optional
        :func:`hardware_config` of ``description``; None: the twin.
    scene : SpectralScene
        What the twin looks at.
    calibration : CalibrationBundle, optional
        The light's column map and forward model (real devices).
    seed : int, optional
        Seed of the twin's temporal noise.
    pacing : {"paced", "free"}
        The twin's pacing (real devices are always paced).
    n_frames : int, optional
        Exposures after which real devices end the stream.
    """
    if hardware is None:
        rig = TwinRig(plan.rig_description(description), scene=scene)
        if seed is not None:
            rig.seed = seed
        return TwinDriver(rig, patterns=plan.patterns, pacing=pacing)
    extra = {"n_frames": n_frames} if n_frames is not None else {}
    return hardware_rig.open_hardware(description, hardware=hardware, patterns=plan.patterns,
                                      calibration=calibration, exposure_s=plan.exposure_s, **extra)
