"""The moving-scene comparison of the demo and the motion study: the edge band against a drawn step, and a
translating scene whose uncompensated recovery is far off while the compensated one gives the still error back."""

import numpy as np
import pytest

from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.moving_scores import RECOVERIES, compare_motion, edge_band
from specgpu.planning import make_plan
from specgpu.rig import CameraParameters, RigDescription, natural_scene
from specgpu.rig.motion import MotionParameters


def test_the_edge_band_is_the_pixels_within_its_width_of_a_step():
    r = np.zeros((20, 30, 4))
    r[:, 15:] = 0.5  # a vertical step between columns 14 and 15
    band = edge_band(r, 0.1, width=3)
    cols = np.flatnonzero(band[10])
    assert cols.min() == 14 - 3 and cols.max() == 15 + 3 and band.all(axis=0)[cols].all()
    assert not edge_band(r, 0.6).any()  # a step below the threshold is no edge


def test_a_translating_scene_is_far_off_uncompensated_and_given_back_compensated():
    desc = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240, frame_rate_hz=200.0,
                                                  exposure_s=0.0049))
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=40.0, max_exposure_s=0.0049)
    scene = natural_scene(240, 320)
    run = compare_motion(desc, bundle, plan, scene, MotionParameters(velocity_px_per_frame=(2.4, 1.8)), 3)
    still, moving, comp = (run[k] for k in RECOVERIES)
    assert moving["rmse_field"] > 1.5 * still["rmse_field"] and moving["rmse_edge"] > moving["rmse_field"]
    assert comp["rmse_field"] < 1.3 * still["rmse_field"]
    assert run["shift_error_px"] < 0.1 and 0.0 < run["flagged"] < 0.25
    for kind in RECOVERIES:  # NaN exactly where a pixel is not scored, the same pixels for all three
        assert run["maps"][kind].shape == (240, 320)
        assert np.nanmean(run["maps"][kind]) == pytest.approx(run[kind]["rmse_field"], rel=1e-5)
    assert len({tuple(np.flatnonzero(np.isnan(m))) for m in run["maps"].values()}) == 1
