"""Quality options composed with motion compensation, through the one decoder: ``--denoise`` guided by the warped
frames' sum, against a float64 NumPy reference of the same composition, and the stream and the batch equal to
``recover`` with the combination."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from moving_helpers import CAM, MOTION, draw_pair_scores, moving_capture
from reference import guided_filter_numpy, linear_warp_ref

from specgpu.core.mask import Mask
from specgpu.core.numerics import live_gain
from specgpu.engine.colorimetry import delta_E
from specgpu.pipeline.batch import run_batch
from specgpu.pipeline.capture_folder import SequenceFolder, read_capture
from specgpu.pipeline.denoise import warped_guide_row
from specgpu.pipeline.recovery import recover, to_Lab, to_XYZ
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.rig import RigDescription, natural_scene

LAB_REF = [50.0, 0.0, 0.0]
DENOISE = (2, 1e-4)


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """2 sequences of a 7-band plan on a twin whose scene drifts (2, 1) px per frame, as a sequence folder."""
    return moving_capture(tmp_path_factory.mktemp("composed"))


def assert_close_nan(a, b, **tol):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), **tol)


def denoised_reference(frames, plan, bundle, shifts, mask, radius, eps):
    """float64: the frames warped in NumPy with ``shifts`` through the plan's A and the guide's row, then the
    still path's guided filter with the flagged pixels (``mask``) left out as the decoder leaves them out."""
    A = np.vstack([plan.A, warped_guide_row(plan)])
    y, _ = linear_warp_ref(frames, A, shifts, bundle.dark_at(plan.exposure_s), live_gain(bundle.flat_field))
    cube, guide = y[..., :-1], y[..., -1]
    bad = ((mask & ~np.uint8(Mask.LAYER)) != 0) | ~np.isfinite(guide) | ~np.isfinite(cube).all(axis=-1)
    guide = guide / np.percentile(guide[~bad], 99)
    filtered = guided_filter_numpy(np.where(bad[..., None], 0.0, cube), np.where(bad, 0.0, guide), radius, eps)
    h, w = bad.shape
    near = np.zeros_like(bad)
    for y0, x0 in zip(*np.nonzero(bad)):
        near[max(0, y0 - 2 * radius):y0 + 2 * radius + 1, max(0, x0 - 2 * radius):x0 + 2 * radius + 1] = True
    out = np.where(near[..., None], cube, filtered)
    out[bad] = np.nan
    return out, near & ~bad


def test_denoise_with_motion_equals_the_numpy_reference_of_the_warp_then_the_filter(moving):
    root, plan, bundle, _, _ = moving
    folder = read_capture(root / "seq")
    got = recover(folder, sequence=0, motion="global", denoise=DENOISE)
    plain = recover(folder, sequence=0, motion="global")
    maps = SequenceDecoder(plan, bundle, ("cube",), motion="global").maps(folder.frames[0])
    want, near = denoised_reference(folder.frames[0], plan, bundle, maps["estimate"].shifts, maps["mask"], *DENOISE)
    assert 0 < np.isnan(want[..., 0]).mean() < 0.2  # the drift leaves a border seen outside the field
    assert_close_nan(got, want, rtol=1e-3, atol=2e-4)
    # the pixels whose windows reach a flagged one keep their decoded value; the others are filtered
    assert near.sum() > 1000
    np.testing.assert_array_equal(got[near], plain[near])
    far = np.isfinite(got[..., 0]) & ~near
    assert np.abs(got[far] - plain[far]).mean() > 1e-3


def test_the_guide_of_a_moving_scene_is_the_warped_sum_not_the_frames_sum(moving):
    """The same composition with the still guide (the frames' sum, not warped) is measurably different: the
    reference can tell them apart."""
    root, plan, bundle, _, _ = moving
    folder = read_capture(root / "seq")
    got = recover(folder, sequence=0, motion="global", denoise=DENOISE)
    maps = SequenceDecoder(plan, bundle, ("cube",), motion="global").maps(folder.frames[0])
    zero = np.zeros_like(maps["estimate"].shifts)
    A = np.vstack([plan.A, warped_guide_row(plan)])
    still_guide = linear_warp_ref(folder.frames[0], A, zero, bundle.dark_at(plan.exposure_s),
                                  live_gain(bundle.flat_field))[0][..., -1]
    warped, _ = denoised_reference(folder.frames[0], plan, bundle, maps["estimate"].shifts, maps["mask"], *DENOISE)
    ok = np.isfinite(got[..., 0])
    assert np.abs(got[ok] - warped[ok]).max() < 1e-3
    plain = recover(folder, sequence=0, motion="global")
    unwarped = guided_filter_numpy(np.nan_to_num(plain), still_guide / np.percentile(still_guide, 99), *DENOISE)
    assert np.abs(got[ok] - unwarped[ok]).mean() > 3 * np.abs(got[ok] - warped[ok]).mean()


def twin_driver(plan, sequences, seed=7):
    from specgpu.capture.twin_driver import TwinDriver
    from specgpu.rig.twin import TwinRig

    rig = TwinRig(plan.rig_description(RigDescription(camera=CAM, motion=MOTION)), scene=natural_scene(240, 320))
    rig.seed = seed
    return TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K * sequences, pacing="free")


def test_stream_and_batch_with_denoise_and_motion_equal_recover(moving, tmp_path, dask_scheduler):
    import zarr

    from specgpu.pipeline.stream import Stream

    root, plan, bundle, _, _ = moving
    kept = []

    def keep(result):
        kept.append(({k: np.array(v) for k, v in result.arrays.items()}, np.array(result.frames)))

    Stream(twin_driver(plan, 1), plan, bundle, outputs=("cube", "XYZ", "dE"), reference=LAB_REF,
           cube_dtype=np.float32, policy="block", sinks=[keep], motion="global", denoise=DENOISE).run()
    (maps, frames), = kept
    want = recover(SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {}), sequence=0, motion="global",
                   denoise=DENOISE)
    assert_close_nan(maps["cube"], want, rtol=1e-5, atol=1e-5)
    XYZ = to_XYZ(want, plan)
    assert_close_nan(maps["XYZ"], XYZ, rtol=1e-4, atol=1e-5)
    assert_close_nan(maps["dE"], delta_E(np.array(LAB_REF, np.float32), to_Lab(XYZ, plan)), atol=1e-2)
    run_batch(root / "seq", plan, bundle, tmp_path / "out.zarr", outputs=("cube",), workers=1, progress=False,
              motion="global", denoise=DENOISE)
    out = zarr.open_group(str(tmp_path / "out.zarr"), mode="r")
    assert_close_nan(out["cube"][1], recover(read_capture(root / "seq"), sequence=1, motion="global",
                                             denoise=DENOISE), rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------- a reference white that moves

@pytest.fixture(scope="module")
def white_chart(tmp_path_factory):
    """One sequence of the 7-band plan of a chart with a 0.99 white tile drifting (2, 1) px per frame (also as a
    sequence folder ``seq`` beside its plan and calibration files), the plan, the calibration, the decoder's maps
    of it (its estimate and mask), and the tile at the sequence's reference time (x, y, w, h)."""
    from dataclasses import replace

    from moving_helpers import moving_setup

    from specgpu.capture.assemble import AssemblyStats
    from specgpu.pipeline.capture_folder import save_plan_and_calibration, write_capture
    from specgpu.pipeline.twin_capture import capture_plan
    from specgpu.rig.scene import colorchecker_scene

    desc, bundle, plan, _ = moving_setup()
    scene = colorchecker_scene(240, 320, white_tile=0.99)
    shot = capture_plan(replace(desc, motion=MOTION), plan, scene, noise_seed=4, calibration=bundle)
    frames = shot.sequences[0].frames
    root = tmp_path_factory.mktemp("white-chart")
    write_capture(root / "seq", shot.sequences, shot.assembly or AssemblyStats(),
                  *save_plan_and_calibration(root, plan, bundle))
    maps = SequenceDecoder(plan, bundle, ("cube",), motion="global").maps(frames)
    white = np.all(np.abs(maps["cube"] - 0.99) < 0.08, axis=-1) & (np.arange(240) < 40)[:, None]
    ys, xs = np.nonzero(white)
    tile = (int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1))
    return frames, plan, bundle, maps, tile, root


def white_reference_decoding(frames, plan, bundle, shifts, mask, roi):
    """float64: every frame warped in NumPy with ``shifts``, the white's gains measured on those samples at the
    reference time, and the corrected decoder applied to them (the still path's white reference on the warped
    frames); NaN where ``mask`` flags a pixel."""
    from specgpu.planning.correction import WhiteReference

    dark, gain = bundle.dark_at(plan.exposure_s), live_gain(bundle.flat_field)
    s, _ = linear_warp_ref(frames, np.eye(plan.K), shifts, dark, gain)
    s[(mask & ~np.uint8(Mask.LAYER)) != 0] = np.nan
    white = WhiteReference(plan, bundle, roi, None, frame_shape=frames.shape[1:])
    gains = white.gains(np.moveaxis(s, -1, 0) / gain + dark, dark=dark)
    return s @ white.decoder(gains).T, gains


def inset(roi, by):
    x, y, w, h = roi
    return f"{x + by},{y + by},{w - 2 * by},{h - 2 * by}"


def test_a_white_that_moves_with_the_scene_equals_the_numpy_reference(white_chart):
    frames, plan, bundle, maps, tile, _ = white_chart
    roi = inset(tile, 1)
    folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
    got = recover(folder, sequence=0, motion="global", white_roi=roi)
    want, gains = white_reference_decoding(frames, plan, bundle, maps["estimate"].shifts, maps["mask"], roi)
    assert_close_nan(got, want, rtol=1e-4, atol=1e-5)
    # the oracle calibration's light has not drifted: the white's gains are one within the noise
    np.testing.assert_allclose(gains, 1.0, atol=0.05)
    dec = SequenceDecoder(plan, bundle, ("cube", "XYZ"), motion="global", white_roi=roi)
    out = dec.maps(frames)
    np.testing.assert_allclose(out["white_gains"], gains, rtol=1e-5)
    assert_close_nan(out["cube"], got, rtol=1e-5, atol=1e-6)
    assert_close_nan(out["XYZ"], to_XYZ(got, plan), rtol=1e-4, atol=1e-6)


def test_scene_or_camera_says_where_the_white_is_measured(white_chart):
    """The tile's ROI at the reference time: measured with the scene it is the white in every frame; measured on
    the fixed pixels the frames before and after see it slide away (the chart's dark surround comes in), and
    the gains are wrong. A ROI well inside the tile's path gives the same gains either way."""
    frames, plan, bundle, _, tile, _ = white_chart
    scene = SequenceDecoder(plan, bundle, ("cube",), motion="global", white_roi=inset(tile, 0)).maps(frames)
    np.testing.assert_allclose(scene["white_gains"], 1.0, atol=0.05)
    camera = SequenceDecoder(plan, bundle, ("cube",), motion="global", white_roi=inset(tile, 0),
                             white_moves="camera")
    try:
        gains = camera.maps(frames)["white_gains"]
    except ValueError as error:  # a frame that saw no white in the ROI at all
        assert "gives no signal" in str(error)
    else:
        assert np.abs(gains - 1.0).max() > 0.05
    x, y, w, h = tile
    inner = f"{x + 10},{y + 4},{w - 20},{max(1, h - 8)}"
    fixed = SequenceDecoder(plan, bundle, ("cube",), motion="global", white_roi=inner, white_moves="Camera")
    # frame 1's gain is 0.970 here whichever the estimate (the tile found 28 or 80 px wide): 0.035, not 0.03
    np.testing.assert_allclose(fixed.maps(frames)["white_gains"], 1.0, atol=0.035)


def test_a_stream_with_a_moving_white_equals_recover(white_chart):
    from specgpu.capture.twin_driver import TwinDriver
    from specgpu.pipeline.stream import Stream
    from specgpu.rig.scene import colorchecker_scene
    from specgpu.rig.twin import TwinRig

    _, plan, bundle, _, tile, _ = white_chart
    roi = inset(tile, 2)
    rig = TwinRig(plan.rig_description(RigDescription(camera=CAM, motion=MOTION)),
                  scene=colorchecker_scene(240, 320, white_tile=0.99))
    rig.seed = 9
    kept = []
    Stream(TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K, pacing="free"), plan, bundle,
           outputs=("cube",), cube_dtype=np.float32, policy="block", motion="global", white_roi=roi,
           sinks=[lambda r: kept.append((np.array(r.arrays["cube"]), np.array(r.frames), r.white_gains))]).run()
    (cube, frames, gains), = kept
    assert gains is not None and np.all(np.abs(gains - 1.0) < 0.05)
    want = recover(SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {}), sequence=0, motion="global",
                   white_roi=roi)
    assert_close_nan(cube, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("motion", ["global", "none"])
def test_a_batch_with_a_white_equals_recover(white_chart, tmp_path, motion, dask_scheduler):
    """batch --white-roi, with --motion (the white moving with the scene) and without (the device-resident
    launches given each sequence's corrected decoder), equals recover with the same white."""
    import zarr

    _, plan, bundle, _, tile, root = white_chart
    x, y, w, h = tile
    roi = inset(tile, 2) if motion != "none" else f"{x + 10},{y + 4},{w - 20},{max(1, h - 8)}"
    run_batch(root / "seq", plan, bundle, tmp_path / "out.zarr", outputs=("cube",), workers=1, progress=False,
              motion=motion, white=(roi, None, "scene"))
    out = zarr.open_group(str(tmp_path / "out.zarr"), mode="r")
    assert out.attrs["white_roi"] == roi and out.attrs["white_roi_moves"] == (None if motion == "none" else "scene")
    want = recover(read_capture(root / "seq"), sequence=0, motion=motion, white_roi=roi)
    plain = recover(read_capture(root / "seq"), sequence=0, motion=motion)
    assert_close_nan(out["cube"][0], want, rtol=1e-5, atol=1e-6)
    assert np.nanmax(np.abs(want - plain)) > 1e-4  # the white's correction changed the decoding


# ------------------------------------------------------------------------------------------ sigma through the warp

@pytest.fixture(scope="module")
def sigma_chart():
    """Two noise draws of one sequence of the 7-band plan (with its noise model) of the natural scene moving 3 px
    per frame in x and half a pixel in y (so every other frame is sampled between pixels), and the plan and
    calibration. The light's frame-to-frame fluctuation is off: it is one number per frame, common to every
    pixel, so two draws hold one sample of it per band and no pixel statistic could check it; what the
    interpolation changes is the pixels' own noise."""
    from dataclasses import replace

    from moving_helpers import moving_setup

    from specgpu.pipeline.twin_capture import capture_plan
    from specgpu.planning.estimators import with_estimator
    from specgpu.planning.noise import NoiseModel
    from specgpu.rig.motion import MotionParameters

    desc, bundle, plan, scene = moving_setup()
    desc = replace(desc, light=replace(desc.light, fluctuation_rms=0.0))
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
    moving = replace(desc, motion=MotionParameters(velocity_px_per_frame=(3.0, 0.5)))
    draws = [capture_plan(moving, plan, scene, noise_seed=seed, calibration=bundle).sequences[0].frames
             for seed in (21, 22)]
    return draws, plan, bundle


def test_sigma_through_the_warp_is_calibrated_on_a_moving_scene(sigma_chart):
    """The difference of two noise draws of the same moving sequence, decoded with compensation, over sqrt(2):
    its z-scores against the decoder's sigma (each band) and dE_sigma (dE2000 between the draws) have an RMS
    within [0.8, 1.25]."""
    (one, two), plan, bundle = sigma_chart
    dec = SequenceDecoder(plan, bundle, ("cube", "XYZ", "Lab", "sigma", "dE_sigma"), motion="global")
    a, b = dec.maps(one), dec.maps(two)
    B = plan.A.shape[0]
    ok, rms, ratio = draw_pair_scores(a, b, B)
    assert ok.mean() > 0.8
    assert np.all((rms > 0.8) & (rms < 1.25)), rms
    np.testing.assert_array_equal(np.isnan(a["sigma"][..., 0]), np.isnan(a["cube"][..., 0]))
    np.testing.assert_allclose(a["sigma"][..., B], np.sqrt(np.mean(a["sigma"][..., :B].astype(np.float64) ** 2,
                                                                    axis=-1)), rtol=1e-5)
    assert 0.8 < ratio < 1.25, ratio


def squared_weight_reference(frames, plan, bundle, shifts, A):
    """float64 variance of each output of ``A`` at translated samples, written independently of the decoder: the
    squared bilinear weights of a fraction f along an axis, (1 - f)^2 and f^2, are (1 - f)^2 + f^2 times the
    bilinear weights of the fraction f^2 / ((1 - f)^2 + f^2), so each frame's per-pixel variance is warped by
    the NumPy reference at that shift and scaled; the light's fluctuation is that of the warped signal."""
    from specgpu.planning.noise import NoiseModel
    from specgpu.planning.uncertainty import constant_variance

    noise = NoiseModel.from_params(plan.params["noise"])
    dark, gain = bundle.dark_at(plan.exposure_s), live_gain(bundle.flat_field).astype(np.float64)
    x = np.asarray(frames, np.float64) - dark
    own = gain ** 2 * (x / noise.gain_e_per_dn + noise.read_var_dn2)
    d = np.asarray(shifts, np.float64)
    base, f = np.floor(d), d - np.floor(d)
    n = (1 - f) ** 2 + f ** 2
    moved = base + f ** 2 / n
    V = np.stack([linear_warp_ref(own[k:k + 1], [[1.0]], moved[k:k + 1])[0][..., 0] * n[k].prod()
                  for k in range(plan.K)])
    signal = linear_warp_ref(x * gain, np.eye(plan.K), d)[0]
    V += (noise.light_rms * np.moveaxis(signal, -1, 0)) ** 2
    var = np.tensordot(V, np.asarray(A, np.float64).T ** 2, axes=([0], [0])) + constant_variance(plan)
    return np.sqrt(var)


def test_sigma_through_the_warp_equals_the_squared_weight_reference(sigma_chart):
    from dataclasses import replace

    from specgpu.planning.estimators import with_estimator
    from specgpu.planning.noise import NoiseModel

    (one, _), plan, bundle = sigma_chart
    noise = replace(NoiseModel.from_params(plan.params["noise"]), light_rms=0.0138)  # the light's term too
    plan = with_estimator(plan, bundle, "projection", noise=noise)
    maps = SequenceDecoder(plan, bundle, ("sigma",), motion="global").maps(one)
    want = squared_weight_reference(one, plan, bundle, maps["estimate"].shifts, plan.A)
    B = plan.A.shape[0]
    from scipy.ndimage import minimum_filter

    # beside the field's edge a sample point's taps are clamped to it, at the shift the reference moves too
    ok = minimum_filter(np.isfinite(maps["sigma"][..., 0]) & np.isfinite(want[..., 0]), size=3, mode="constant")
    assert ok.mean() > 0.8
    np.testing.assert_allclose(maps["sigma"][..., :B][ok], want[ok], rtol=1e-4)
    # the bound it replaces (each frame's variance interpolated with the weights themselves) is measurably higher
    from specgpu.planning.uncertainty import frame_variance

    bound = frame_variance(one, plan, bundle.dark_at(plan.exposure_s), bundle.flat_field,
                           shifts=maps["estimate"].shifts)
    assert np.median(bound[ok] / (want[ok] ** 2)) > 1.05


def test_stream_sigmas_with_motion_equal_recover(moving):
    from specgpu.pipeline.outputs import delta_E_sigma_map, sigma_with_rms
    from specgpu.pipeline.recovery import uncertainty
    from specgpu.pipeline.stream import Stream

    _, plan, bundle, _, _ = moving
    kept = []
    Stream(twin_driver(plan, 1), plan, bundle, outputs=("cube", "XYZ", "sigma", "dE_sigma"), cube_dtype=np.float32,
           policy="block", motion="global",
           sinks=[lambda r: kept.append(({k: np.array(v) for k, v in r.arrays.items()}, np.array(r.frames)))]).run()
    (maps, frames), = kept
    folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
    sigma, cov = uncertainty(folder, sequence=0, illuminant="D65", motion="global")
    assert_close_nan(maps["sigma"], sigma_with_rms(sigma, plan.output_labels)[0], rtol=1e-5, atol=1e-7)
    want = delta_E_sigma_map(to_XYZ(recover(folder, sequence=0, motion="global"), plan), cov, plan.white_XYZ("D65"))
    ok = np.isfinite(maps["dE_sigma"])
    assert ok.mean() > 0.8
    np.testing.assert_allclose(maps["dE_sigma"][ok], want[ok], rtol=1e-3, atol=1e-5)
