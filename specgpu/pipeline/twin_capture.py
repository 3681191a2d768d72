"""Capture through the digital twin: a plan's sequences of a scene exposed on the twin rig and assembled like
hardware frames (:func:`capture_plan`), after checking that the scene's bands cover what the plan lights."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from specgpu.capture.session import CaptureResult, capture_sequences
from specgpu.capture.twin_driver import TwinDriver
from specgpu.planning.plans import Plan
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import read_scene
from specgpu.rig.twin import FaultSchedule, TwinRig

__all__ = ["capture_plan", "check_scene_covers"]


def capture_plan(description: RigDescription, plan: Plan, scene, *, sequences: int = 1, noise_seed: int | None = None,
                 faults: FaultSchedule | None = None, on_sequence=None, calibration=None) -> CaptureResult:
    """Capture ``sequences`` repetitions of ``plan``'s illuminant sequence of ``scene`` on the twin.

    The camera runs at the plan's exposure, at the fastest frame rate the camera and the light's switch time allow
    (never faster than the rig description's rate); frames go through the driver, ring buffer and assembler like
    hardware frames.

    Parameters
    ----------
    description : RigDescription
    plan : Plan
    scene : specgpu.rig.scene.SpectralScene
        At the camera's resolution.
    sequences : int
        Number of whole sequences to expose (>= 1).
    noise_seed : int, optional
        Seed of the frames' temporal noise (the camera's fixed pattern comes from the description's seed).
    faults : FaultSchedule, optional
        Injected faults (none by default).
    on_sequence : callable, optional
        Given each complete sequence as it arrives (then sequences are not kept in the result).
    calibration : CalibrationBundle, optional
        The bundle the plan was made from: the rig's clock starts where that calibration ended plus the rig's
        ``capture_delay`` (so the lamp has drifted on as on a bench); without it, at ``capture_delay``.

    Returns
    -------
    CaptureResult
        The complete sequences (each with its (K, H, W) ``frames``) and the assembler's counters (``assembly``).

    Examples
    --------
    >>> from specgpu.calibration import oracle_calibration
    >>> from specgpu.planning import make_plan
    >>> from specgpu.rig import CameraParameters, RigDescription, colorchecker_scene
    >>> rig = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    >>> bundle = oracle_calibration(rig)
    >>> plan = make_plan("narrowband", bundle, step_nm=20.0)
    >>> from specgpu.pipeline import capture_plan
    >>> result = capture_plan(rig, plan, colorchecker_scene(240, 320), noise_seed=1, calibration=bundle)
    >>> result.sequences[0].frames.shape == (plan.K, 240, 320)
    True
    """
    if sequences < 1:
        raise ValueError(f"sequences must be >= 1, got {sequences}")
    check_scene_covers(scene, plan, description.light.line_fwhm_nm, rig=description)
    clock = description.capture_delay
    if calibration is not None:
        clock += float(calibration.reports.get("rig_clock_end_s", 0.0))
    rig = TwinRig(plan.rig_description(description), scene=scene, clock_start_s=clock)
    if noise_seed is not None:
        rig.seed = noise_seed
    driver = TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K * sequences,
                        faults=faults or FaultSchedule(), pacing="free")
    return capture_sequences(driver, plan.K, on_sequence=on_sequence)


def check_scene_covers(scene, plan: Plan, slack_nm: float = 5.0, *, rig: RigDescription | None = None) -> None:
    """Refuse a scene whose bands do not cover the wavelengths the plan's illuminants light (above 1 % of their
    peak, less ``slack_nm``): its reflectance there would be made up, never measured. Given ``rig``, its
    ``[motion] object`` cube is held to the same test, named by the key and the rig file."""
    targets = np.asarray(plan.target_spectra, np.float64)
    lit = plan.light_wavelengths[targets.max(axis=0) > 0.01 * targets.max()]
    if lit.size == 0:
        return
    cubes = [(f"scene {scene.name!r}", scene.wavelengths)]
    obj = "" if rig is None else rig.motion.object
    if Path(obj).suffix.lower() in (".exr", ".npz", ".hdr"):  # a file (built-ins span the visible)
        cubes.append((f"{rig.source}: [motion] object {obj}", read_scene(obj).wavelengths))
    for what, wavelengths in cubes:
        lo, hi = float(wavelengths[0]), float(wavelengths[-1])
        if lo > lit[0] + slack_nm or hi < lit[-1] - slack_nm:
            raise ValueError(f"{what} covers {lo:g}-{hi:g} nm but the {plan.method} plan lights "
                             f"{lit[0]:g}-{lit[-1]:g} nm; give a cube whose bands cover its illuminants")


