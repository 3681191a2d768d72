"""The small moving twin the motion tests share: 320 x 240 at 200 fps, a 7-band narrowband plan (50 nm steps) with
its oracle calibration, the natural scene; one sequence of it rendered frame by frame with its truth, and a
sequence folder of it captured while the scene drifts (:func:`moving_capture`)."""

from __future__ import annotations

import copy
import functools
from dataclasses import replace

import numpy as np

from specgpu.calibration.bundle import oracle_calibration
from specgpu.capture.assemble import AssemblyStats
from specgpu.pipeline.capture_folder import save_plan_and_calibration, write_capture
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.registry import make_plan
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters
from specgpu.rig.twin import TwinRig

CAM = CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=200.0, exposure_s=0.0049)


@functools.cache
def _made_once():
    desc = RigDescription(camera=CAM)
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=50.0, max_exposure_s=0.0049)
    return desc, bundle, plan, natural_scene(240, 320)


def moving_setup():
    """(rig description, oracle calibration, 7-band narrowband plan (400-700 nm), natural scene): made once per
    session (a second and a half, asked for by a score of test modules), each caller given its own deep copy (a
    fiftieth of a second), so what one test changes no other test sees."""
    return copy.deepcopy(_made_once())


def frames_of(desc, plan, scene, motion, seed=5):
    """One sequence of ``plan`` on the moving twin, rendered frame by frame, with its truth."""
    rig = TwinRig(plan.rig_description(replace(desc, motion=motion)), scene=scene, seed=seed)
    rig.load_sequence(plan.patterns)
    ts = np.arange(plan.K) * rig.frame_period_s
    frames = np.stack([rig.render(k, k, ts[k])[0] for k in range(plan.K)])
    return frames, rig.motion_truth(ts)


MOTION = MotionParameters(velocity_px_per_frame=(2.0, 1.0))


def moving_capture(root):
    """A sequence folder ``root / "seq"`` of 2 sequences of a 7-band narrowband plan on a twin whose scene drifts
    2 px per frame in x and 1 in y, with its plan and calibration files: (root, plan, bundle, plan path,
    calibration path)."""
    desc, bundle, plan, scene = moving_setup()
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))  # sigma_rms
    shot = capture_plan(replace(desc, motion=MOTION), plan, scene, sequences=2, noise_seed=3,
                        calibration=bundle)
    plan_path, calib_path = save_plan_and_calibration(root, plan, bundle)
    write_capture(root / "seq", shot.sequences, shot.assembly or AssemblyStats(), plan_path, calib_path)
    return root, plan, bundle, plan_path, calib_path


def draw_pair_scores(a, b, B):
    """Two noise draws' maps ``a``, ``b`` of one sequence (cube, Lab, sigma, dE_sigma): the pixels both decoded,
    the RMS z-score per band of their difference over sqrt(2) against ``a``'s sigma (its first ``B`` channels),
    and the RMS of dE2000 between them over sqrt(2) against dE_sigma."""
    from specgpu.engine.colorimetry import delta_E

    ok = np.isfinite(a["cube"][..., 0]) & np.isfinite(b["cube"][..., 0])
    z = ((a["cube"] - b["cube"]) / np.sqrt(2) / a["sigma"][..., :B])[ok]
    rms = np.sqrt(np.mean(z.astype(np.float64) ** 2, axis=0))
    dE = delta_E(a["Lab"], b["Lab"])[ok] / np.sqrt(2)
    ratio = np.sqrt(np.mean(dE.astype(np.float64) ** 2) / np.mean(a["dE_sigma"][ok].astype(np.float64) ** 2))
    return ok, rms, ratio
