"""A replayable twin workload: a calibrated twin with a recorded stream of the colorchecker to replay
(:func:`stream_setup`) and the offline maps a stream of it must equal (:func:`offline_maps`). The stream's tests
and ``specgpu bench --stream`` (:mod:`specgpu.apps.bench.stream`) run on it, so both measure the same work."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from specgpu.calibration.bundle import save_calibration
from specgpu.calibration.procedure import calibrate
from specgpu.capture.assemble import AssemblyStats, Sequence
from specgpu.capture.replay import ReplayDriver, record
from specgpu.capture.twin_driver import TwinDriver
from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E, reflectance_to_XYZ
from specgpu.pipeline.capture_folder import read_capture, write_capture
from specgpu.pipeline.recovery import default_basis, recover, to_Lab, to_XYZ
from specgpu.planning.basis_plans import plan_symmetric_basis
from specgpu.planning.plans import save_plan
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import colorchecker_scene
from specgpu.rig.sensors import camera_for_size
from specgpu.rig.twin import TwinRig

__all__ = ["StreamSetup", "offline_maps", "scene_Lab", "stream_setup"]


@dataclass
class StreamSetup:
    """What the stream benchmark streams: a calibrated twin, a symmetric plan (K = 9, 61 output bands) whose
    exposure fits the paced frame rate, a recording of ``sequences`` whole sequences of the colorchecker replayed
    by :class:`~specgpu.capture.replay.ReplayDriver`, and the scene's per-pixel Lab as the dE reference."""

    description: object
    bundle: object
    plan: object
    frames: np.ndarray
    infos: list
    light: object
    reference: np.ndarray

    def driver(self, *, loops=None, pacing="free"):
        return ReplayDriver(self.frames, self.infos, self.light, loops=loops, pacing=pacing)

    def recorded_sequence(self, frame_ids) -> int:
        """Index of the recorded sequence a result's frame ids replay (replay ids run on across loops)."""
        return int(frame_ids[0]) // self.plan.K % (self.frames.shape[0] // self.plan.K)


def stream_setup(width: int = 640, height: int = 480, *, frame_rate_hz: float = 200.0, sequences: int = 8,
                 output_step_nm: float = 5.0, seed: int = 0, white_tile: float | None = None,
                 progress=None) -> StreamSetup:
    """Calibrate the twin at ``width`` x ``height`` and ``frame_rate_hz``, plan the symmetric basis method with
    an exposure that fits the frame period, and record ``sequences`` sequences of the colorchecker (10-bit);
    ``white_tile``: with a reference white tile of that reflectance above the chart
    (:func:`specgpu.rig.scene.white_tile_roi` gives its ROI). ``progress``, if given, is called with a line
    naming each step as it starts (each takes seconds to tens of seconds)."""
    say = progress or (lambda _line: None)
    base = RigDescription()
    switch = base.light.switch_time_s
    # the paper's camera up to 640 x 480, else the smallest machine-vision sensor preset that holds the size
    sensor = camera_for_size(width, height, base.camera)
    frame_rate_hz = min(float(frame_rate_hz), replace(sensor, frame_rate_hz=1.0, exposure_s=0.5).max_frame_rate_hz)
    exposure = 1.0 / frame_rate_hz - switch - 5e-6  # the longest exposure the light can follow at this rate
    cam = replace(sensor, bit_depth=10, exposure_s=exposure, frame_rate_hz=frame_rate_hz)
    description = replace(base, camera=cam)
    say(f"calibrating the twin at {width} x {height}, {frame_rate_hz:g} frames/s (both feedback loops)")
    bundle = calibrate(description, seed=seed)
    say("planning the symmetric basis method (m = 5) on the default basis")
    plan = plan_symmetric_basis(bundle, default_basis(), m=5, max_exposure_s=exposure,
                                output_wavelengths=np.arange(400.0, 700.0 + 1e-9, output_step_nm))
    scene = colorchecker_scene(int(height), int(width), white_tile=white_tile)
    rig = TwinRig(plan.rig_description(description), scene=scene)
    rig.seed = seed + 1
    say(f"recording {sequences} sequences of {plan.K} frames of the chart on the twin")
    frames, infos, light = record(TwinDriver(rig, patterns=plan.patterns, pacing="free"), plan.K * sequences)
    return StreamSetup(description, bundle, plan, frames, infos, light, scene_Lab(scene))


def scene_Lab(scene, illuminant="D65"):
    """The scene's per-pixel Lab under ``illuminant``, its white from the scene's own grid: a stream's dE reference."""
    XYZ = reflectance_to_XYZ(scene.reflectance, scene.wavelengths, illuminant)
    return XYZ_to_Lab(XYZ, illuminant, wavelengths=scene.wavelengths)


def offline_maps(setup: StreamSetup, index: int, *, method: str = "CIE 2000", illuminant: str = "D65") -> dict:
    """The offline path's maps (``pipeline.recover`` on a sequence folder written from the recording, then
    ``to_XYZ``, ``to_Lab`` and ``delta_E``) for recorded sequence ``index``: what the stream must equal."""
    K = setup.plan.K
    sl = slice(index * K, (index + 1) * K)
    seq = Sequence(setup.frames[sl], np.array([i.frame_id for i in setup.infos[sl]]),
                   np.array([i.timestamp_s for i in setup.infos[sl]]), setup.plan.exposure_s, index)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_plan(tmp / "plan.npz", setup.plan)
        save_calibration(tmp / "calib.npz", setup.bundle)
        write_capture(tmp / "seq", [seq], AssemblyStats(), tmp / "plan.npz", tmp / "calib.npz")
        folder = read_capture(tmp / "seq")
        cube = recover(folder, sequence=0)
    XYZ = to_XYZ(cube, setup.plan, illuminant)
    Lab = to_Lab(XYZ, setup.plan, illuminant)
    return {"cube": cube, "XYZ": XYZ, "Lab": Lab, "dE": delta_E(setup.reference, Lab, method)}
