"""The motion methods by name: one entry point, the registry's choices, a one-line refusal of an unknown name."""

from __future__ import annotations

import numpy as np
import pytest
from moving_helpers import frames_of, moving_setup

from specgpu.core.validate import BadArgument
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.motion.methods import MOTION_METHODS, check_motion_mode, estimate_motion
from specgpu.rig.motion import MotionParameters


@pytest.fixture(scope="module")
def drifting():
    desc, bundle, plan, scene = moving_setup()
    frames, truth = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=(2.0, -1.0)))
    return frames, bundle.dark_at(plan.exposure_s), bundle.flat_field, truth


def test_the_registry_names_each_method_once():
    assert list(MOTION_METHODS) == ["none", "global", "affine", "flow"]
    assert all(callable(f) and f.__doc__ for f in MOTION_METHODS.values())
    assert check_motion_mode("Affine") == "affine"


def test_an_unknown_method_is_refused_in_one_line_naming_the_choices():
    frames = np.ones((3, 8, 8), np.float32)
    with pytest.raises(BadArgument) as caught:
        estimate_motion(frames, method="optical")
    message = str(caught.value)
    assert "\n" not in message and "optical" in message
    assert all(repr(name) in message for name in MOTION_METHODS)
    with pytest.raises(BadArgument, match="motion='warp'"):
        check_motion_mode("warp")


def test_none_is_a_still_scene():
    est = estimate_motion(np.ones((5, 8, 8), np.float32), method="none")
    assert est.shifts.shape == (5, 2) and not est.shifts.any() and est.registered.all() and est.reference_frame == 2


def test_each_method_estimates_the_drift(drifting):
    """The registry's global method is the global estimate itself (within the device's rounding of the gradient
    images), the flow starts from it, the affine method is the estimate's affine model."""
    frames, dark, gain, truth = drifting
    direct = estimate_global_motion(frames, dark, gain)
    by_name = estimate_motion(frames, dark, gain, method="GLOBAL")
    np.testing.assert_allclose(by_name.shifts, direct.shifts, atol=1e-4)  # its gradient images made on the device
    np.testing.assert_allclose(by_name.shifts, truth["displacement"], atol=0.1)
    np.testing.assert_allclose(estimate_motion(frames, dark, gain, method="flow").shifts, direct.shifts, atol=1e-4)
    affine = estimate_motion(frames, dark, gain, method="affine")
    assert affine.model == "affine" and affine.shifts.shape == (len(frames), 2, 3)
    np.testing.assert_allclose(affine.shifts, estimate_global_motion(frames, dark, gain, model="affine").shifts,
                               atol=1e-3)


def test_the_flow_refuses_reference_frames_and_short_sequences():
    with pytest.raises(ValueError, match="a flow is estimated from every frame"):
        estimate_motion(np.ones((9, 8, 8), np.float32), method="flow", reference_frames=[0, 8])
    with pytest.raises(ValueError, match="at least 4 frames"):
        estimate_motion(np.ones((3, 8, 8), np.float32), method="flow")
