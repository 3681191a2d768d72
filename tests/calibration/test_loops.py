"""The two feedback loops on the noisy twin: loop (a) drives camera outputs to targets, loop (b) the light's
spectrum to a target spectrum (CIE D65)."""

import colour
import numpy as np
import pytest

from specgpu.calibration.loops import camera_loop, spectral_loop
from specgpu.rig.scene import white_plate_scene
from specgpu.rig.twin import TwinRig


def test_camera_loop_alone(small_rig):
    rig = TwinRig(small_rig, scene=white_plate_scene(240, 320))
    cw = rig.light.column_wavelengths
    masks = np.stack([(cw >= a) & (cw < a + 50) for a in (450, 500, 550, 600)])
    targets = np.array([40.0, 60.0, 80.0, 60.0])
    dark = np.full(rig.camera.shape, float(rig.expected_frame(0).mean()))  # loaded sequence is all dark
    res = camera_loop(rig, masks, targets, dark=dark, initial_levels=[0.02, 0.5, 0.05, 0.9], repeats=3,
                      tolerance=0.02, max_iterations=6)
    assert res.converged and res.iterations <= 4
    np.testing.assert_allclose(res.outputs, targets, rtol=0.05)
    with pytest.raises(ValueError, match="targets must be"):
        camera_loop(rig, masks, targets[:2])


def test_spectral_loop_reaches_d65(small_rig):
    rig = TwinRig(small_rig, scene="white")
    d65 = colour.SDS_ILLUMINANTS["D65"]
    grid = rig.light.wavelengths
    target = np.interp(grid, d65.wavelengths, d65.values)
    sel = (grid >= 400) & (grid <= 700)
    target = np.where(sel, target, 0.0)
    target *= 0.5 * float(np.min(rig.light.max_spectrum[sel] / target[sel]))
    start = np.full(rig.light.params.columns, 300)
    res = spectral_loop(rig, target, initial=start, tolerance=0.01, max_iterations=20)
    assert res.history[0] > 0.1 and res.converged and res.iterations <= 20
    # The light really emits the target (truth, not the instrument's reading).
    emitted = rig.light.pattern_to_spectrum(res.patterns[0])
    inner = (grid >= 412) & (grid <= 688)
    assert np.sqrt(np.mean((emitted - target)[inner] ** 2)) / target[inner].max() < 0.02
    with pytest.raises(ValueError, match="target must be finite"):
        spectral_loop(rig, -target)
