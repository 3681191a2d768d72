"""The rig as calibration sees it: any CalibrationRig calibrates the same way, and a band's power is set one
mirror at a time."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.calibration.loops import camera_loop
from specgpu.calibration.procedure import calibrate
from specgpu.calibration.rigs import (
    CalibrationRig,
    TwinCalibrationRig,
    distribute_counts,
)
from specgpu.rig.scene import white_plate_scene


def test_calibrate_runs_on_any_calibration_rig(small_rig):
    """The procedure is written once against CalibrationRig: the twin's, passed explicitly, gives the same bundle
    as the default, bit for bit (the hardware rig's run is in test_hw_calibration.py)."""
    kw = {"repeats": 1, "band_step_nm": 25.0, "spectral_check": False, "seed": 2}
    white = white_plate_scene(240, 320, reflectance=0.99)
    rig = TwinCalibrationRig(small_rig, scene=white)
    assert isinstance(rig, CalibrationRig) and rig.frame_shape == (240, 320) and rig.max_code == 1023
    assert calibrate(small_rig, rig=rig, **kw).hash == calibrate(small_rig, **kw).hash
    with pytest.raises(TypeError, match="TwinRig or a CalibrationRig"):
        camera_loop(object(), np.ones((1, 4), bool), [1.0])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 1), st.integers(1, 40)), min_size=1, max_size=6), st.integers(1, 768))
def test_distribute_counts_property(spec, rows):
    columns = 64
    masks = np.zeros((len(spec), columns), bool)
    rng = np.random.default_rng(len(spec))
    for k, (_, n) in enumerate(spec):
        masks[k, rng.choice(columns, size=n, replace=False)] = True
    levels = np.array([lv for lv, _ in spec])
    out = distribute_counts(levels, masks, rows)
    assert out.min() >= 0 and out.max() <= rows
    for k in range(len(spec)):
        assert np.all(out[k, ~masks[k]] == 0)
        inside = out[k, masks[k]]
        assert inside.max() - inside.min() <= 1  # spread evenly: one mirror of dither at most
        assert inside.sum() == int(round(levels[k] * rows * masks[k].sum()))
