"""A second motion layer: an object moving on its own over the scene, registered and decoded with its own motion."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from moving_helpers import frames_of, moving_setup

from specgpu.core.mask import Mask
from specgpu.engine.runtime import get_queue
from specgpu.motion.object_motion import occluded_by
from specgpu.motion.residual import residual_check
from specgpu.pipeline.evaluate import evaluate_pixels
from specgpu.pipeline.moving_decode import warped_sample_variance
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.uncertainty import constant_covariance
from specgpu.rig.motion import MotionParameters
from specgpu.rig.scene import SpectralScene

OBJECT = MotionParameters(object="colorchecker", object_velocity_px_per_frame=(3.0, 0.0), object_size_px=(100, 140))


@pytest.fixture(scope="module")
def setup():
    return moving_setup()


@pytest.fixture(scope="module")
def chart_over_scene(setup):
    desc, bundle, plan, scene = setup
    frames, truth = frames_of(desc, plan, scene, OBJECT)
    kw = dict(dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field, saturation=float(bundle.max_code),
              residual=residual_check(plan, bundle))  # as recover and the stream decoder check it
    return frames, truth, recover_moving(frames, plan.A, **kw), recover_moving(frames, plan.A, layers=False, **kw)


def test_the_objects_own_motion_is_registered(setup, chart_over_scene):
    _, _, plan, _ = setup
    _, _, res, _ = chart_over_scene
    assert len(res.layers) == 1, [(layer.shifts, layer.box, layer.pixels) for layer in res.layers]
    t = np.arange(plan.K) - plan.K // 2  # frame periods from the reference time (the middle frame)
    np.testing.assert_allclose(res.layers[0].shifts, np.c_[3.0 * t, np.zeros(plan.K)], atol=0.2)
    # the background stands still (an object of a fifth of the field pulls its estimate by up to 0.2 px)
    np.testing.assert_allclose(res.estimates[0].shifts, 0.0, atol=0.2)


def test_the_object_is_decoded_not_flagged_and_its_spectra_are_right(setup, chart_over_scene):
    _, _, plan, scene = setup
    _, truth, res, single = chart_over_scene
    obj = truth["object_mask"] > 0.5
    flagged_before = ((single.mask & Mask.INCONSISTENT) > 0)[obj].mean()
    flagged_after = ((res.mask & Mask.INCONSISTENT) > 0)[obj].mean()
    assert flagged_before > 0.1 and flagged_after < 0.7 * flagged_before
    layer = (res.mask & Mask.LAYER) > 0
    # most of the object, flat patches included, is decoded with its motion (less the ring the flags grow by about
    # the pixels it cannot decode)
    assert layer[obj].mean() > 0.65
    assert (layer & ~obj).sum() < 0.1 * layer.sum()
    at_reference = SpectralScene(scene.wavelengths, truth["reflectance"], name="truth at the reference time")
    rep = evaluate_pixels(res.y, at_reference, wavelengths=plan.output_wavelengths)
    single_rep = evaluate_pixels(single.y, at_reference, wavelengths=plan.output_wavelengths)
    both = obj & np.isfinite(rep.rmse) & np.isfinite(single_rep.rmse)
    # on the object's pixels both decode, the object's motion gives the right spectra and the background's does not
    # (the few the global decoding leaves unflagged there, whose samples fit one spectrum: 0.61 of the error with the
    # background's motion within 0.04 px, 0.54 when the object's peaks pulled it 0.15 px off)
    assert np.mean(rep.rmse[both]) < 0.65 * np.mean(single_rep.rmse[both])
    assert np.nanmean(rep.rmse[layer & obj]) < 0.06, np.nanmean(rep.rmse[layer & obj])


def test_background_the_object_covered_during_the_sequence_is_flagged(setup, chart_over_scene):
    _, _, plan, _ = setup
    _, truth, res, single = chart_over_scene
    obj = truth["object_mask"] > 0.5
    t = np.arange(plan.K) - plan.K // 2
    covered = occluded_by(obj, np.c_[3.0 * t, np.zeros(plan.K)])
    assert covered.sum() > 2 * 100 * 8  # two strips about 9 px wide along the object's 100 px height
    nan = ~np.all(np.isfinite(res.y), axis=2)
    nan_single = ~np.all(np.isfinite(single.y), axis=2)
    # the layer flags the strips as a whole (the global check alone only where some frame has structure there)
    assert nan[covered].mean() > nan_single[covered].mean(), (nan[covered].mean(), nan_single[covered].mean())
    assert np.all(nan == ((res.mask & (1 | 4 | Mask.INCONSISTENT)) > 0))  # every NaN is flagged, every flag NaN


def test_a_repeating_object_too_slow_to_separate_is_not_given_a_motion_one_period_off(setup):
    """A chart moving 0.5 px/frame: its peak never leaves the background's, and its patch pitch offers peaks one
    period off in every frame that a steady motion would also explain; none is taken, so the chart stays as the
    global check left it (flagged where its frames disagree), never decoded a period off."""
    desc, bundle, plan, scene = setup
    slow = replace(OBJECT, object_velocity_px_per_frame=(0.5, 0.0))
    frames, truth = frames_of(desc, plan, scene, slow)
    res = recover_moving(frames, plan.A, dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field,
                         saturation=float(bundle.max_code))
    t = np.arange(plan.K) - plan.K // 2
    for layer in res.layers:
        np.testing.assert_allclose(layer.shifts, np.c_[0.5 * t, np.zeros(plan.K)], atol=0.3)


def test_a_scene_without_an_object_of_its_own_gets_no_layer(setup):
    desc, bundle, plan, scene = setup
    frames, _ = frames_of(desc, plan, scene, MotionParameters(velocity_px_per_frame=(3.0, 1.0)))
    kw = dict(dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field, saturation=float(bundle.max_code))
    res, single = recover_moving(frames, plan.A, **kw), recover_moving(frames, plan.A, layers=False, **kw)
    assert res.layers == [] and not ((res.mask & Mask.LAYER) > 0).any()
    np.testing.assert_array_equal(res.y, single.y)


def test_the_stream_decoder_decodes_the_object_layer_as_recover_does(setup, chart_over_scene):
    _, bundle, plan, _ = setup
    frames = chart_over_scene[0]
    # the decoder registers the motion on its device (the default one), as recover and the stream do
    res = recover_moving(frames, plan.A, dark=bundle.dark_at(plan.exposure_s), gain=bundle.flat_field,
                         saturation=float(bundle.max_code), residual=residual_check(plan, bundle), device=get_queue())
    maps = SequenceDecoder(plan, bundle, ("cube",), motion="global").maps(frames)
    assert len(maps["layers"]) == 1
    np.testing.assert_array_equal(maps["mask"], res.mask)
    np.testing.assert_allclose(np.nan_to_num(maps["cube"]), np.nan_to_num(res.y), rtol=1e-5, atol=1e-6)


def test_sigma_rms_reads_an_object_layers_pixels_with_its_own_motion(setup, chart_over_scene):
    """The motion decoder's sigma_rms: on the pixels an object layer decoded, the noise model at that layer's
    samples; elsewhere at the background's; NaN exactly where the cube is."""
    desc, bundle, plan, _ = setup
    frames = chart_over_scene[0]
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
    dec = SequenceDecoder(plan, bundle, ("cube", "sigma_rms"), motion="global")
    maps = dec.maps(frames)
    sigma = maps["sigma_rms"]
    np.testing.assert_array_equal(np.isnan(sigma), np.isnan(maps["cube"][..., 0]))
    (layer,) = maps["layers"]
    own = (maps["mask"] & Mask.LAYER) != 0
    assert own.sum() > 1000 and not (own & ~layer.decoded).any()

    A = np.asarray(plan.A, np.float64)
    read = np.flatnonzero(np.any(A != 0, axis=0))
    sensor = dec.corrections.sensor(frames)

    def at(shifts):  # each read frame's bilinear sample variance through A^2, plus the plan's constant
        V = warped_sample_variance(sensor, plan, dec.corrections.dark, bundle.flat_field, shifts, read=read)
        var = np.tensordot(V, (A[:, read] ** 2).T, axes=([0], [0])) + np.diag(constant_covariance(plan))
        return np.sqrt(np.mean(var, axis=-1))

    # the device sums the variances in float32 (about 1e-5 of sigma); the two motions' samples differ by far more
    np.testing.assert_allclose(sigma[own], at(layer.shifts)[own], rtol=4e-5)
    rest = np.isfinite(sigma) & ~own
    np.testing.assert_allclose(sigma[rest], at(maps["estimate"].shifts)[rest], rtol=4e-5)
    # the two motions' samples differ on the object: the comparison can fail
    assert np.nanmax(np.abs(at(layer.shifts)[own] - at(maps["estimate"].shifts)[own])) > 1e-3
