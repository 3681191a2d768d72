"""The small moving twin the motion tests share: 320 x 240 at 200 fps, a 7-band narrowband plan (50 nm steps) with
its oracle calibration, the natural scene; and one sequence of it rendered frame by frame with its truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.twin import TwinRig

CAM = CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=200.0, exposure_s=0.0049)


def moving_setup():
    """(rig description, oracle calibration, 7-band narrowband plan (400-700 nm), natural scene)."""
    desc = RigDescription(camera=CAM)
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=50.0, max_exposure_s=0.0049)
    return desc, bundle, plan, natural_scene(240, 320)


def frames_of(desc, plan, scene, motion, seed=5):
    """One sequence of ``plan`` on the moving twin, rendered frame by frame, with its truth."""
    rig = TwinRig(plan.rig_description(replace(desc, motion=motion)), scene=scene, seed=seed)
    rig.load_sequence(plan.patterns)
    ts = np.arange(plan.K) * rig.frame_period_s
    frames = np.stack([rig.render(k, k, ts[k])[0] for k in range(plan.K)])
    return frames, rig.motion_truth(ts)
