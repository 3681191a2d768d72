"""A capture folder of the chart on the small twin, for the report and viewer tests."""

from __future__ import annotations

from dataclasses import replace

from specgpu.calibration import oracle_calibration, save_calibration
from specgpu.pipeline import capture_plan, write_capture
from specgpu.planning import make_plan, save_plan
from specgpu.planning.noise import NoiseModel
from specgpu.rig import CameraParameters, RigDescription, colorchecker_scene


def write_chart_capture(root, folder: str, *, sequences: int = 1, noise_seed: int, noise_model: bool = False):
    """The chart captured with a narrowband plan (20 nm steps) on the 320 x 240 twin, written as ``specgpu capture``
    writes it into ``root / folder`` with ``plan.npz`` and ``calibration.npz`` beside it (``noise_model``: the plan
    records the camera's noise, so sigma maps can be made); returns the capture folder."""
    rig = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    bundle = oracle_calibration(rig)
    plan = make_plan("narrowband", bundle, step_nm=20.0)
    if noise_model:
        plan = replace(plan, params={**plan.params, "noise": NoiseModel.from_rig(rig, plan.exposure_s).as_params()})
    scene = colorchecker_scene(240, 320)
    result = capture_plan(rig, plan, scene, sequences=sequences, noise_seed=noise_seed, calibration=bundle)
    save_plan(root / "plan.npz", plan)
    save_calibration(root / "calibration.npz", bundle)
    return write_capture(root / folder, result.sequences, result.assembly, root / "plan.npz",
                         root / "calibration.npz", metadata={"scene": scene.name})


def write_moving_capture(root, folder: str, *, sequences: int = 2, noise_seed: int = 4):
    """The natural scene drifting 2 px per frame in x and 1 in y on the 320 x 240 twin at 200 fps, captured with a
    narrowband plan (40 nm steps) into ``root / folder`` with each sequence's motion truth beside it, as
    ``specgpu capture`` on a rig with a [motion] table writes it; returns the capture folder."""
    from specgpu.capture.motion_truth import truth_recorder
    from specgpu.rig import natural_scene
    from specgpu.rig.motion import MotionParameters

    rig = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=200.0,
                                                 exposure_s=0.0049),
                         motion=MotionParameters(velocity_px_per_frame=(2.0, 1.0)))
    bundle = oracle_calibration(rig)
    plan = make_plan("narrowband", bundle, step_nm=40.0)
    scene = natural_scene(240, 320)
    result = capture_plan(rig, plan, scene, sequences=sequences, noise_seed=noise_seed, calibration=bundle)
    save_plan(root / "plan.npz", plan)
    save_calibration(root / "calibration.npz", bundle)
    out = write_capture(root / folder, result.sequences, result.assembly, root / "plan.npz",
                        root / "calibration.npz", metadata={"scene": scene.name})
    record = truth_recorder(out, rig, plan, scene)
    for s, sequence in enumerate(result.sequences):
        record(s, sequence)
    return out
