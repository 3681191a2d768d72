"""The motion mode's sigmas carried through the filter read the unfiltered cube's slopes on the guide. Where the cube
is not an output, the warped pass decodes the frames' K samples instead of the cube's B rows, and the slopes are the
decoder times them: the same sigmas (the pass's identity rows go through the ambient frame's subtraction and a
reference white's gains as every row does), from a pass of K + outputs rows instead of B + outputs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from moving_helpers import moving_setup

from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.recovery import default_basis
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.basis_plans import plan_symmetric_basis
from specgpu.planning.correction import with_ambient_frame
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.rig.motion import MotionParameters
from specgpu.rig.realism import Realism
from specgpu.rig.scene import colorchecker_scene
from specgpu.rig.twin import TwinRig

DENOISE = (2, 1e-4)
MOVING = MotionParameters(velocity_px_per_frame=(2.0, 1.0))
SIGMAS = ("XYZ", "sigma", "sigma_rms", "dE_sigma")


def basis_plan(bundle, exposure_s):
    """The symmetric basis method (m = 5, K = 9) with 31 output bands: more bands than frames."""
    return plan_symmetric_basis(bundle, default_basis(), m=5, max_exposure_s=exposure_s,
                                output_wavelengths=np.arange(400.0, 700.0 + 1e-9, 10.0))


@pytest.fixture(scope="module")
def setups():
    desc, bundle, plan, _ = moving_setup()
    plain = basis_plan(bundle, plan.exposure_s)
    plain = with_estimator(plain, bundle, "projection", noise=NoiseModel.from_rig(desc, plain.exposure_s))
    room = replace(desc, realism=Realism(ambient_lux=300.0), light=replace(desc.light, fluctuation_rms=0.0))
    room_bundle = oracle_calibration(room)
    amb = basis_plan(room_bundle, plan.exposure_s)
    amb = with_ambient_frame(with_estimator(amb, room_bundle, "projection",
                                            noise=NoiseModel.from_rig(room, amb.exposure_s)))
    return {"plain": (desc, bundle, plain), "ambient": (room, room_bundle, amb)}


def frames_of(desc, plan, scene, seed=5):
    rig = TwinRig(plan.rig_description(replace(desc, motion=MOVING)), scene=scene, seed=seed)
    rig.load_sequence(plan.patterns)
    ts = np.arange(plan.K) * rig.frame_period_s
    return np.stack([rig.render(k, k, ts[k])[0] for k in range(plan.K)])


@pytest.mark.parametrize(("case", "white"), [("plain", False), ("plain", True), ("ambient", False)])
def test_the_samples_slopes_give_the_cube_rows_sigmas(setups, case, white):
    desc, bundle, plan = setups[case]
    scene = colorchecker_scene(120, 160, white_tile=0.99)
    frames = frames_of(desc, plan, scene)
    kw = dict(motion="global", denoise=DENOISE, white_roi="20,4,60,10" if white else None,
              illuminant="D65")
    samples = SequenceDecoder(plan, bundle, SIGMAS, **kw)
    with_cube = SequenceDecoder(plan, bundle, ("cube", *SIGMAS), **kw)
    assert "samples" in samples.slices and "cube" not in samples.slices
    assert len(samples.rows) == samples.slices["samples"].stop + 1 < len(with_cube.rows)  # K rows, not B
    got, want = samples.maps(frames), with_cube.maps(frames)
    assert np.isfinite(want["sigma_rms"]).mean() > 0.6
    # XYZ filtered as itself or from the filtered cube: the same filter, float32 box sums apart (2e-5 of white),
    # and dE_sigma taken at that XYZ
    for name, rtol, atol in (("XYZ", 2e-4, 5e-5), ("sigma", 2e-4, 1e-7), ("sigma_rms", 2e-4, 1e-7),
                             ("dE_sigma", 3e-3, 1e-4)):
        a, b = np.asarray(got[name], np.float64), np.asarray(want[name], np.float64)
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
        np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), rtol=rtol, atol=atol, err_msg=name)


def test_a_samples_pass_without_its_decoder_is_refused(setups):
    desc, bundle, plan = setups["plain"]
    dec = SequenceDecoder(plan, bundle, ("sigma_rms",), motion="global", denoise=DENOISE)
    frames = frames_of(desc, plan, colorchecker_scene(60, 80))
    rec, y, _, _ = dec.warped_outputs(dec.corrections.moving(frames))
    with pytest.raises(ValueError, match="give the decoder"):
        dec.smoothed(y, rec.mask)


def test_a_variance_prepared_for_another_noise_is_refused(setups):
    from specgpu.engine.warped_variance import PreparedWarpedVariance
    from specgpu.pipeline.moving_decode import warped_uncertainty

    desc, bundle, plan = setups["plain"]
    dec = SequenceDecoder(plan, bundle, ("sigma_rms",), motion="global")
    frames = frames_of(desc, plan, colorchecker_scene(60, 80))
    sensor = dec.corrections.moving(frames)
    rec, _, _, A = dec.warped_outputs(sensor)
    other = PreparedWarpedVariance(dec.queue, sensor.shape[1:], dec.corrections.dark, dec.gain, gain_e_per_dn=1.0,
                                   read_var_dn2=1.0, light_rms=0.0)
    with pytest.raises(ValueError, match="the plan's noise") as info:
        warped_uncertainty(sensor, plan, dec.corrections.dark, dec.gain, rec, A, rms=True, variance=other)
    assert "\n" not in str(info.value)
    sigma, _ = warped_uncertainty(sensor, plan, dec.corrections.dark, dec.gain, rec, A, rms=True,
                                  variance=dec.variance_launch())
    assert np.isfinite(sigma).mean() > 0.5
