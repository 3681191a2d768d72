"""Motion compensation with a plan that has an ambient frame: the ambient frame placed on the other frames' steady
motion, sampled where it saw each pixel and subtracted in the warped pass; a motion too unsteady to place it flagged,
not decoded wrong; recover and the stream alike; the twin's moving chart under room light recovered as the still one
is; the sigma outputs calibrated against noise draws."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from moving_helpers import draw_pair_scores, moving_setup
from scipy import ndimage

from specgpu.calibration.bundle import oracle_calibration
from specgpu.core.mask import Mask
from specgpu.motion.ambient import STEADY_PX, place_frame
from specgpu.motion.estimate import MotionEstimate
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.recovery import recover, to_XYZ, uncertainty
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.correction import subtracting_ambient, with_ambient_frame
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.planning.registry import make_plan
from specgpu.rig.motion import MotionParameters
from specgpu.rig.realism import Realism
from specgpu.rig.scene import colorchecker_scene, interpolation_matrix
from specgpu.rig.twin import TwinRig

H, W, K = 120, 160, 8
AMBIENT = K - 1
DARK = 20.0
#: each pattern's light on the scene (DN for a white), and the decoder (3, K) reading the pattern frames
POWER = np.array([300.0, 420.0, 520.0, 600.0, 560.0, 450.0, 350.0])
A_PLAN = np.hstack([np.random.default_rng(0).normal(size=(3, K - 1)) / 1000.0, np.zeros((3, 1))])


def patches(seed, margin=40):
    """A piecewise-constant reflectance (random rectangles, no period a correlation could take for the motion)
    on a canvas ``margin`` px wider than the field on each side, and a room light of its own structure."""
    rng = np.random.default_rng(seed)
    h, w = H + 2 * margin, W + 2 * margin
    R = np.full((h, w), 0.5)
    for _ in range(90):
        y, x = rng.integers(0, h - 8), rng.integers(0, w - 8)
        R[y:y + rng.integers(8, 40), x:x + rng.integers(8, 50)] = rng.uniform(0.1, 0.9)
    # brighter to one side, and with shadows of its own (bands its edges the reflectance does not have)
    room = 60.0 * (1.0 + 0.5 * (np.arange(w) / w))[None, :] * np.ones((h, 1))
    room *= np.where((np.arange(w) // 37) % 2 == 0, 1.0, 0.4)[None, :]
    return R, room


def sequence(positions, seed=1, margin=40, room_light=True):
    """The frames (K, H, W) of a scene whose content moved by ``positions`` (K, 2) integer px (x, y) in each frame
    (frame k shows the canvas at p - positions[k]), the room light (``room_light``) moving with it (it lights the
    scene, whose reflectance it takes), frame ``AMBIENT`` lit by the room light alone; with the canvas's
    reflectance and room light."""
    R, room = patches(seed, margin)
    room = room if room_light else 0.0 * room
    frames = np.random.default_rng(seed + 100).normal(0.0, 1.0, (K, H, W))  # a camera's noise, 1 DN
    for k, (dx, dy) in enumerate(np.asarray(positions, int)):
        view = (slice(margin - dy, margin - dy + H), slice(margin - dx, margin - dx + W))
        lit = R[view] * room[view]
        frames[k] += DARK + lit + (POWER[k] * R[view] if k != AMBIENT else 0.0)
    return frames.astype(np.float32), R, room


def bilinear(image, sx, sy):
    """``image`` sampled bilinearly at (sx, sy), float64, NaN beyond half a pixel outside (as the warp reads)."""
    h, w = image.shape
    out = ndimage.map_coordinates(image, [np.clip(sy, 0, h - 1), np.clip(sx, 0, w - 1)], order=1)
    outside = (sx < -0.5 - 1e-3) | (sy < -0.5 - 1e-3) | (sx > w - 0.5 + 1e-3) | (sy > h - 0.5 + 1e-3)
    return np.where(outside, np.nan, out)


def reference_decode(frames, shifts, A, ambient):
    """float64: each frame (less the dark) sampled where ``shifts`` (K, 2) say it saw each pixel, the ambient
    frame's sample (``ambient``; None: none) subtracted from the others', then the decoder ``A`` (B, K) whose
    ambient column is zero."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    s = np.stack([bilinear(frames[k].astype(np.float64) - DARK, xx + d[0], yy + d[1]) for k, d in enumerate(shifts)])
    above = s if ambient is None else s - s[ambient][None]
    return np.einsum("bk,khw->hwb", np.asarray(A, np.float64), above)


def decode(frames, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = recover_moving(frames, subtracting_ambient(A_PLAN, AMBIENT), dark=np.full((H, W), DARK, np.float32),
                             gain=np.ones((H, W), np.float32), ambient=AMBIENT, **kw)
    return rec, [w for w in caught if "ambient frame" in str(w.message)]


STEADY = np.stack([2 * np.arange(K), np.arange(K)], axis=1)  # 2 px per frame in x, 1 in y


def test_the_ambient_column_subtracts_the_ambient_frame_from_every_other():
    R = subtracting_ambient(A_PLAN, AMBIENT)
    np.testing.assert_allclose(R[:, :AMBIENT], A_PLAN[:, :AMBIENT])
    np.testing.assert_allclose(R[:, AMBIENT], -A_PLAN.sum(axis=1))
    s = np.random.default_rng(2).uniform(size=K)
    np.testing.assert_allclose(R @ s, A_PLAN[:, :AMBIENT] @ (s[:AMBIENT] - s[AMBIENT]))
    np.testing.assert_array_equal(subtracting_ambient(A_PLAN, None), A_PLAN)


def test_the_warped_decode_equals_a_float64_reference_with_the_ambient_frame_placed_and_subtracted():
    frames, _, _ = sequence(STEADY)
    rec, warned = decode(frames)
    assert not warned
    est = rec.estimates[0]
    # the ambient frame was not registered; its place, extrapolated from the steady motion, is where it was
    assert not est.registered[AMBIENT] and est.registered[:AMBIENT].all()
    truth = (STEADY - STEADY[:K].mean(axis=0)).astype(np.float64)  # from the sequence's reference time
    np.testing.assert_allclose(est.shifts, truth, atol=0.05)
    assert rec.ambient_misfit < 0.05
    want = reference_decode(frames, est.shifts, A_PLAN, AMBIENT)
    clean = rec.mask == 0
    assert clean.mean() > 0.75
    np.testing.assert_allclose(rec.y[clean], want[clean].astype(np.float32), rtol=1e-4, atol=2e-5)
    # and that is the scene's projector light alone: the room light, which moved with the scene, is gone
    dark_room, _, _ = sequence(STEADY, room_light=False)
    without = recover_moving(dark_room, subtracting_ambient(A_PLAN, AMBIENT), dark=np.full((H, W), DARK, np.float32),
                             shifts=est.shifts, check=False).y
    scale = np.abs(without[clean]).max()
    np.testing.assert_allclose(rec.y[clean], without[clean], atol=2e-3 * scale)  # the estimate is 0.0x px off
    # subtracted on fixed pixels instead (what a still decoding does), the room light's moved edges stay
    fixed = reference_decode(frames - frames[AMBIENT][None] + DARK, est.shifts, A_PLAN, None)
    assert np.nanmax(np.abs(fixed[clean] - without[clean])) > 0.05 * scale
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    # the pixels only the ambient frame saw outside the field: NaN with the outside bit, as for any frame
    last = np.isnan(bilinear(np.ones((H, W)), xx + est.shifts[AMBIENT, 0], yy + est.shifts[AMBIENT, 1]))
    only_ambient = last & ~np.isnan(bilinear(np.ones((H, W)), xx + est.shifts[AMBIENT - 1, 0],
                                             yy + est.shifts[AMBIENT - 1, 1]))
    assert only_ambient.sum() > 100
    assert np.all(rec.mask[only_ambient] & Mask.OUTSIDE)
    assert np.isnan(rec.y[only_ambient]).all()


def test_the_consistency_check_reads_the_pattern_frames_only():
    """The ambient frame, lit by the room light alone, is unlike every pattern frame; were it compared, its pixels
    would be flagged wherever it has structure."""
    frames, _, _ = sequence(STEADY)
    rec, _ = decode(frames)
    assert (rec.mask & Mask.INCONSISTENT).astype(bool).mean() < 0.01  # 0.3 %; 4 % with it compared


def test_a_motion_too_unsteady_to_place_the_ambient_frame_is_flagged_not_decoded_wrong():
    """The scene speeds up from 2 to 3 px per frame half-way: the registered frames depart from a steady motion by
    over a third of a pixel and the ambient frame, extrapolated, lies more than half a pixel from where it was. The
    pixels where its room light changes within that reach are flagged (and a warning says so); every pixel left
    decoded is right, and the flagged ones would not have been."""
    positions = np.stack([[0, 2, 4, 6, 9, 12, 15, 18], np.zeros(K, int)], axis=1)
    frames, _, _ = sequence(positions, seed=3)
    rec, warned = decode(frames, layers=False)
    assert len(warned) == 1 and "\n" not in str(warned[0].message)
    assert rec.ambient_misfit > STEADY_PX
    est = rec.estimates[0]
    truth = positions - positions.mean(axis=0)
    assert np.abs(est.shifts[AMBIENT, 0] - truth[AMBIENT, 0]) > 0.4  # it was placed off
    # the right decoding: the ambient frame sampled where it truly saw each pixel; the one it was placed for
    exact = reference_decode(frames, np.where(np.arange(K)[:, None] == AMBIENT, truth, est.shifts), A_PLAN, AMBIENT)
    placed = reference_decode(frames, est.shifts, A_PLAN, AMBIENT)
    decoded = np.all(np.isfinite(rec.y), axis=-1)
    flagged = (rec.mask & Mask.INCONSISTENT).astype(bool) & np.all(np.isfinite(placed), axis=-1)
    assert decoded.mean() > 0.3 and flagged.sum() > 500
    scale = np.abs(exact[decoded]).max()
    err = np.abs(rec.y[decoded] - exact[decoded]).max(axis=-1)
    assert np.quantile(err, 0.999) < 0.01 * scale  # left decoded: right, within a percent of the range
    wrong = np.abs(placed - exact).max(axis=-1) > 0.02 * scale  # where the misplaced ambient sample would be wrong
    assert wrong.sum() > 100
    assert np.mean(flagged[wrong] | ~decoded[wrong]) > 0.98


def test_place_frame_fits_a_steady_motion_and_measures_its_misfit():
    shifts = np.array([[-3.0, 0.0], [-1.0, 0.0], [1.0, 0.3], [3.0, 0.0]])  # frame 2 off the line by about 0.2-0.3
    est = MotionEstimate(shifts, np.ones(4, bool), np.zeros(4), 1)
    full, misfit = place_frame(est, [0, 1, 2, 3], 5, 4, (H, W))
    assert full.shifts.shape == (5, 2) and not full.registered[4] and full.reference_frame == 1
    assert 0.15 < misfit < 0.3
    # the placed frame on the fitted line (x: 2 px per frame), everything from the 5 frames' reference time
    np.testing.assert_allclose(full.shifts[:, 0], 2.0 * (np.arange(5) - 2), atol=1e-9)
    affine = np.tile(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), (4, 1, 1))
    affine[:, 0, 2] = shifts[:, 0]
    full, misfit = place_frame(replace(est, shifts=affine, model="affine"), [0, 1, 2, 3], 5, 4, (H, W))
    assert full.shifts.shape == (5, 2, 3) and misfit < 1e-9
    np.testing.assert_allclose(full.shifts[:, 0, 2], 2.0 * (np.arange(5) - 2), atol=1e-9)
    with pytest.raises(ValueError, match="every frame of the 5 but frame 4"):
        place_frame(est, [0, 1, 2], 5, 4, (H, W))


# ------------------------------------------------------------------------------- the twin's moving chart, room light

LUX = 300.0  # a lit room: the ambient frame a few DN above the dark on the chart, the surround near none
SPEED = MotionParameters(velocity_px_per_frame=(3.0, 0.0))


@pytest.fixture(scope="module")
def chart():
    """(rig description with room light and no light fluctuation, oracle calibration, a 7-band narrowband plan
    with its noise model and an ambient frame, the ColorChecker at 320 x 240)."""
    desc, bundle, plan, _ = moving_setup()
    desc = replace(desc, realism=Realism(ambient_lux=LUX), light=replace(desc.light, fluctuation_rms=0.0))
    bundle = oracle_calibration(desc)
    plan = make_plan("narrowband", bundle, step_nm=50.0, max_exposure_s=0.0049)
    plan = with_ambient_frame(with_estimator(plan, bundle, "projection",
                                             noise=NoiseModel.from_rig(desc, plan.exposure_s)))
    return desc, bundle, plan, colorchecker_scene(240, 320)


def shot(chart, motion, seed=5):
    """One sequence of the chart (its frames) and its truth: the reflectance at the reference time on the plan's
    output wavelengths."""
    desc, bundle, plan, scene = chart
    rig = TwinRig(plan.rig_description(replace(desc, motion=motion)), scene=scene, seed=seed)
    rig.load_sequence(plan.patterns)
    ts = np.arange(plan.K) * rig.frame_period_s
    frames = np.stack([rig.render(k, k, ts[k])[0] for k in range(plan.K)])
    truth = rig.motion_truth(ts)["reflectance"] @ interpolation_matrix(plan.output_wavelengths, scene.wavelengths).T
    return frames, truth.astype(np.float32)


def interiors(truth, surround=0.03):
    """(H, W) bool: the patches' pixels 4 px or more inside their edges (the truth flat over 9 x 9 about them)."""
    level = truth.sum(axis=-1)
    flat = ndimage.maximum_filter(level, 9) - ndimage.minimum_filter(level, 9) < 1e-6
    return flat & (np.abs(truth - surround).max(axis=-1) > 1e-3)


@pytest.fixture(scope="module")
def shots(chart):
    """:func:`shot` of the chart under a motion, rendered once per motion for the module (four tests decode the
    same moving sequence, each its own way, and rendering it costs seconds); the frames and truth are read-only."""
    made = {}

    def take(motion):
        if motion not in made:
            frames, truth = shot(chart, motion)
            frames.setflags(write=False)
            truth.setflags(write=False)
            made[motion] = frames, truth
        return made[motion]

    return take


def patch_rmse(chart, shots, motion, mode) -> float:
    """The RMSE over the patches' interiors of recover --motion ``mode`` of one sequence of the chart moving so
    (taken from ``shots``); nearly every interior pixel decoded."""
    _, bundle, plan, _ = chart
    frames, truth = shots(motion)
    cube = recover(SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {}), sequence=0, motion=mode)
    inside = interiors(truth)
    decoded = inside & np.isfinite(cube[..., 0])
    assert decoded.sum() > 0.95 * inside.sum() > 10000
    return float(np.sqrt(np.mean((cube[decoded] - truth[decoded]) ** 2)))


@pytest.fixture(scope="module")
def still_rmse(chart, shots):
    return patch_rmse(chart, shots, MotionParameters(), "none")


@pytest.mark.parametrize("mode", ["global", "affine", "flow"])
def test_the_twins_moving_chart_under_room_light_is_recovered_as_the_still_one(chart, shots, still_rmse, mode):
    """The chart moving 3 px per frame under 300 lux of room light, recover --motion with the ambient frame warped:
    over the patches' interiors within 1.2 times the still chart's RMSE (the same plan; 0.022 both on the twin)."""
    assert patch_rmse(chart, shots, SPEED, mode) < 1.2 * still_rmse


def test_the_moving_chart_decoded_still_is_far_off(chart, shots, still_rmse):
    """What a user could do before, the plan refused with --motion: decode the moving frames still, the ambient
    frame subtracted where it is."""
    assert patch_rmse(chart, shots, SPEED, "none") > 2.5 * still_rmse


def test_a_batch_decodes_a_moving_ambient_plan_as_recover_does(chart, tmp_path, dask_scheduler):
    import zarr

    from specgpu.capture.assemble import AssemblyStats
    from specgpu.pipeline.batch import run_batch
    from specgpu.pipeline.capture_folder import read_capture, save_plan_and_calibration, write_capture

    desc, bundle, plan, scene = chart
    captured = capture_plan(replace(desc, motion=SPEED), plan, scene, noise_seed=4, calibration=bundle)
    plan_path, calib_path = save_plan_and_calibration(tmp_path, plan, bundle)
    write_capture(tmp_path / "seq", captured.sequences, captured.assembly or AssemblyStats(), plan_path, calib_path)
    report = run_batch(tmp_path / "seq", plan, bundle, tmp_path / "out.zarr", outputs=("cube",), progress=False,
                       motion="global")
    assert report.computed == 1
    want = recover(read_capture(tmp_path / "seq"), sequence=0, motion="global")
    assert 0.8 < np.isfinite(want[..., 0]).mean() < 0.99
    assert_close_nan(zarr.open_group(str(tmp_path / "out.zarr"), mode="r")["cube"][0], want, rtol=1e-6, atol=1e-6)


def test_recover_and_the_stream_decode_a_moving_ambient_plan_alike(chart):
    from specgpu.capture.twin_driver import TwinDriver
    from specgpu.pipeline.stream import Stream

    desc, bundle, plan, scene = chart
    rig = TwinRig(plan.rig_description(replace(desc, motion=SPEED)), scene=scene)
    rig.seed = 7
    kept = []
    report = Stream(TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K, pacing="free"), plan, bundle,
                    outputs=("cube", "XYZ", "sigma"), cube_dtype=np.float32, policy="block", motion="global",
                    sinks=[lambda r: kept.append(({k: np.array(v) for k, v in r.arrays.items()},
                                                  np.array(r.frames)))]).run()
    assert report.sequences_out == 1 == len(kept)
    maps, frames = kept[0]
    folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
    cube = recover(folder, sequence=0, motion="global")
    assert 0.8 < np.isfinite(cube[..., 0]).mean() < 0.99  # the motion leaves a border seen outside the field
    assert_close_nan(maps["cube"], cube, rtol=1e-6, atol=1e-6)
    assert_close_nan(maps["XYZ"], to_XYZ(cube, plan), rtol=1e-5, atol=1e-6)
    sigma, _ = uncertainty(folder, sequence=0, motion="global")
    assert_close_nan(maps["sigma"][..., :-1], sigma, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("denoise", [None, pytest.param((2, 1e-4), marks=pytest.mark.slow)])
def test_the_sigmas_of_a_moving_ambient_plan_are_calibrated(chart, denoise):
    """Two noise draws of one moving sequence: their difference over sqrt(2) against sigma has an RMS z-score in
    [0.8, 1.25] per band, and dE2000 between them against dE_sigma: the ambient frame's own noise, shared by every
    output through its column, is in the sigma (0.99-1.01 and 1.00 on the twin; denoised, carried through the
    filter, 1.02-1.04 and 1.01, in the slow set: the filter's variance takes half a minute)."""
    desc, bundle, plan, scene = chart
    dec = SequenceDecoder(plan, bundle, ("cube", "Lab", "sigma", "dE_sigma"), motion="global", denoise=denoise)
    a, b = (dec.maps(capture_plan(replace(desc, motion=SPEED), plan, scene, noise_seed=s,
                                  calibration=bundle).sequences[0].frames) for s in (21, 22))
    ok, rms, ratio = draw_pair_scores(a, b, plan.A.shape[0])
    assert ok.mean() > 0.8
    assert np.all((rms > 0.8) & (rms < 1.25)), rms
    assert 0.8 < ratio < 1.25, ratio


def assert_close_nan(a, b, **tol):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), **tol)
