"""Set-ups shared by the white-reference and correction tests of a room and of its commands."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from stream_helpers import shared_stream_setup

from specgpu.calibration.bundle import oracle_calibration
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.priors import smooth_prior
from specgpu.planning.registry import make_plan
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import colorchecker_scene, white_tile_roi

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


def white_chart_setup():
    """(oracle bundle, 20 nm narrowband plan, the chart with a 0.99 white tile, the tile's ROI) at 320 x 240."""
    bundle = oracle_calibration(DESC)
    plan = make_plan("narrowband", bundle, step_nm=20.0)
    scene = colorchecker_scene(240, 320, white_tile=0.99)
    return bundle, plan, scene, white_tile_roi(240, 320)


def white_stream_setup(width: int, height: int, sequences: int):
    """The twin recording of the chart with a white tile, its plan given a noise model (and the expected error on a
    smooth prior)."""
    s = shared_stream_setup(width, height, sequences=sequences, output_step_nm=10.0, white_tile=0.99)
    noise = NoiseModel.from_rig(s.description, s.plan.exposure_s)
    plan = with_estimator(s.plan, s.bundle, "projection", prior=smooth_prior(np.arange(400.0, 700.0 + 1e-9, 5.0)),
                          noise=noise)
    return replace(s, plan=plan)
