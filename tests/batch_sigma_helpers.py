"""A twin recording of a 160 x 120 window for the batch's sigma tests: the twin renders at 320 x 240 (its smallest
sensor window) and the window is cut from each frame, with the calibration cut to the same window, so every stream
and batch runs on 160 x 120 frames; the natural scene (a chart's flat patches give the motion estimate too little
texture in so small a window) with a 0.99 white painted on it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.io.recording import ZarrRecorder
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import natural_scene

SEQUENCES = 2
WINDOW = (slice(60, 180), slice(80, 240))  # the 160 x 120 window kept, about the scene's centre
WHITE = (slice(80, 100), slice(130, 170))  # a 0.99 white painted on the scene: rows 20-40, columns 50-90 of WINDOW
SIGMAS = ("sigma", "sigma_rms", "dE_sigma")
OUTPUTS = ("cube", "XYZ", *SIGMAS)
DENOISE = (2, 1e-4)


def window_twin():
    """The 7-band narrowband plan with its noise model and the oracle calibration, both of the 160 x 120 window,
    and the twin's description and the natural scene (with a 0.99 white painted on it) to render the frames at
    320 x 240."""
    desc = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=200.0,
                                                  exposure_s=0.0049))
    full = oracle_calibration(desc)
    plan = make_plan("narrowband", full, step_nm=50.0, max_exposure_s=0.0049)
    plan = with_estimator(plan, full, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
    assert full.flat_fields is None  # the window of the calibration is its dark and flat field
    bundle = replace(full, dark=full.dark[WINDOW], flat_field=full.flat_field[WINDOW])
    scene = natural_scene(240, 320)
    reflectance = np.array(scene.reflectance)
    reflectance[WHITE] = 0.99
    return desc, replace(plan, calibration=bundle.hash), bundle, replace(scene, reflectance=reflectance)


def rendered(twin, *, moving: bool):
    """:data:`SEQUENCES` sequences of the twin's scene, still or drifting (2, 1) px per frame, cut to the window:
    (frames, frame infos, the light's record) as a replay driver takes them."""
    from specgpu.capture.replay import record
    from specgpu.capture.twin_driver import TwinDriver
    from specgpu.rig.twin import TwinRig

    desc, plan, _, scene = twin
    motion = {"motion": MotionParameters(velocity_px_per_frame=(2.0, 1.0))} if moving else {}
    rig = TwinRig(plan.rig_description(replace(desc, **motion)), scene=scene)
    rig.seed = 3
    frames, infos, light = record(TwinDriver(rig, patterns=plan.patterns, pacing="free"), plan.K * SEQUENCES)
    frames = np.ascontiguousarray(frames[:, WINDOW[0], WINDOW[1]])
    frames.setflags(write=False)
    return frames, infos, light


def white_roi(plan, bundle, frames) -> str:
    """The painted white where the sequence ``frames`` has it at its reference time (decoded motion-compensated),
    inset by 2 px: ``--white-roi`` of a white moving with the scene."""
    cube = SequenceDecoder(plan, bundle, ("cube",), motion="global").maps(frames)["cube"]
    white = np.all(np.abs(cube - 0.99) < 0.08, axis=-1)
    ys, xs = np.nonzero(white)
    assert xs.size > 100, xs.size
    return f"{xs.min() + 2},{ys.min() + 2},{xs.max() - xs.min() - 3},{max(1, ys.max() - ys.min() - 3)}"


def streamed(path, plan, bundle, frames, infos, light, *, motion, denoise, white) -> Path:
    """``specgpu stream --frames`` of the replayed ``frames`` with the options: the recording at ``path``."""
    from specgpu.capture.replay import ReplayDriver
    from specgpu.pipeline.stream import Stream

    recorder = ZarrRecorder(path, plan, frames=True)
    roi = {} if white is None else {"white_roi": white[0], "white_moves": white[2]}
    report = Stream(ReplayDriver(frames, infos, light), plan, bundle, outputs=OUTPUTS, cube_dtype=np.float32,
                    policy="block", motion=motion, denoise=denoise, sinks=[recorder], **roi).run()
    assert report.sequences_out == SEQUENCES
    return path
