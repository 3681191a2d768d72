"""The sigma outputs with ``--denoise``, in every path: the device's variance of the guided filter against a
float64 NumPy reference, that model against the spread of filtered noise draws (a flat guide, a textured guide with
noise of its own, a warp's half-pixel samples), the stream equal to ``recover`` for the combinations of
``--motion``, ``--white-roi`` and the sigma outputs, and the denoised sigma of a natural scene, still and moving,
calibrated against fresh noise draws."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from guided_variance_helpers import reference_filtered_variance
from moving_helpers import CAM, draw_pair_scores, moving_setup

from specgpu.core.mask import Mask
from specgpu.engine.guided import guided_filter
from specgpu.engine.guided_variance import MAX_RADIUS, box_box_squares, filtered_variance
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.outputs import delta_E_sigma_map, sigma_with_rms
from specgpu.pipeline.recovery import recover, to_XYZ, uncertainty
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.estimators import with_estimator
from specgpu.planning.noise import NoiseModel
from specgpu.rig import RigDescription
from specgpu.rig.motion import MotionParameters

DENOISE = (2, 1e-4)
SIGMAS = ("cube", "XYZ", "sigma", "sigma_rms", "dE_sigma")
MOVING = MotionParameters(velocity_px_per_frame=(2.0, 1.0))


def assert_close_nan(a, b, **tol):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), **tol)


# ------------------------------------------------------------------------------ the device's variance of the filter


def flat(v, radius=2):
    """The variance the filter of a flat guide (the mean of box means) leaves of independent noise ``v`` (H, W)."""
    h, w = v.shape
    z = np.zeros((h, w, 1))
    return filtered_variance(v[..., None], v[..., None], np.ones((h, w)), radius=radius, eps=1e-4, slopes=z,
                             guide_var=z[..., 0], terms=[[]])[..., 0]


@pytest.mark.parametrize("radius", [1, 2, 3])
@pytest.mark.parametrize("sqrt", [False, True])
def test_the_device_variance_equals_the_float64_reference(radius, sqrt):
    rng = np.random.default_rng(radius)
    h, w = 23, 31
    guide = rng.uniform(0.5, 1.0, (h, w))
    guide[:, 15:] += 0.5  # an edge the weights follow
    own = rng.uniform(0.0, 2.0, (h, w, 3))
    total = own + rng.uniform(0.0, 1.0, own.shape)
    own[3, 4, 1] = np.nan  # a pixel with no own variance: adds nothing to its neighbours
    total[10, 12, 2] = np.nan  # a NaN total stays NaN, and its own part is not spread
    mask = np.zeros((h, w), np.uint8)
    mask[15, 7] = Mask.SATURATED
    mask[5, 25] = Mask.OUTSIDE  # not among the bits asked: its own part is spread
    slopes = rng.standard_normal((h, w, 2)) + guide[..., None]
    guide_var = rng.uniform(0.0, 1e-3, (h, w))
    terms = [[(0, 0, 1.0)], [(1, 1, 1.0)], [(0, 1, 0.5), (1, 1, 0.5)]]
    offsets = np.array([0.1, 0.0, 0.3]) if sqrt else None
    kw = dict(radius=radius, eps=1e-3, slopes=slopes, guide_var=guide_var, terms=terms, offsets=offsets, sqrt=sqrt)
    got = filtered_variance(own, total, guide, mask=mask, mask_bits=int(Mask.SATURATED), **kw)
    want = reference_filtered_variance(own, total, guide, radius, 1e-3, slopes, guide_var, terms, offsets, sqrt,
                                       mask, int(Mask.SATURATED))
    assert got.dtype == np.float32 and got.shape == own.shape
    assert_close_nan(got, want, rtol=2e-5, atol=1e-7)
    # the masked pixel's own part is left out: with it the neighbours' values change
    assert np.nanmax(np.abs(filtered_variance(own, total, guide, **kw) - got)) > 1e-3
    with pytest.raises(ValueError, match="offsets must be 3 finite numbers"):
        filtered_variance(own, total, guide, **{**kw, "offsets": [1.0, 2.0]})
    with pytest.raises(ValueError, match="radius"):
        filtered_variance(own, total, guide, **{**kw, "radius": MAX_RADIUS + 1})


def filtered_draws(images, guides, radius=2, eps=1e-4):
    """Each draw (H, W, N) through the guided filter of its guide (one guide, or (H, W, N) of them)."""
    if guides.ndim == 2:
        return np.concatenate([guided_filter(images[..., i:i + 50].astype(np.float32), guides.astype(np.float32),
                                             radius=radius, eps=eps) for i in range(0, images.shape[-1], 50)], -1)
    return np.stack([guided_filter(images[..., i:i + 1].astype(np.float32), guides[..., i].astype(np.float32),
                                   radius=radius, eps=eps)[..., 0] for i in range(images.shape[-1])], -1)


def test_where_the_guide_is_flat_the_filter_leaves_the_box_box_variance():
    """400 noise draws of a smoothly varying variance through the filter of a flat guide (the mean of box means):
    the spread of the filtered draws is the variance the device computes, 54 times below the input's at radius 2
    (away from the border, where the clipped windows average fewer pixels)."""
    rng = np.random.default_rng(5)
    h, w, draws, r = 40, 48, 400, 2
    yy, xx = np.mgrid[0:h, 0:w]
    v = 1.0 + 0.5 * np.sin(xx / 7.0) * np.cos(yy / 9.0)
    q = filtered_draws(rng.standard_normal((h, w, draws)) * np.sqrt(v)[..., None], np.ones((h, w)))
    inner = (slice(2 * r, h - 2 * r), slice(2 * r, w - 2 * r))
    model = flat(v)[inner]
    assert np.mean(q.astype(np.float64).var(axis=-1)[inner] / model) == pytest.approx(1.0, abs=0.03)
    assert 1.0 / np.sum(box_box_squares(r)) ** 2 == pytest.approx(np.mean(v[inner] / model), rel=0.02)


def test_a_textured_noisy_guide_leaves_its_weights_variance_and_passes_its_own_noise():
    """An image that follows a textured guide, both with noise of their own, 300 draws each filtered by its own
    noisy guide: the spread is the filter's weights' sum_j W_ij^2 v_j plus the guide's noise passed by the slope,
    abar^2 var g; either term alone, or the flat guide's variance, falls well short."""
    rng = np.random.default_rng(6)
    h, w, draws, r, eps = 32, 40, 300, 2, 1e-4
    yy, xx = np.mgrid[0:h, 0:w]
    g0 = 0.6 + 0.2 * np.sin(xx / 2.3) * np.cos(yy / 3.1)
    p0 = 0.8 * g0 + 0.1
    v, gv = np.full((h, w), 4e-4), np.full((h, w), 2e-5)
    guides = g0[..., None] + rng.standard_normal((h, w, draws)) * np.sqrt(gv)[..., None]
    q = filtered_draws(p0[..., None] + rng.standard_normal((h, w, draws)) * np.sqrt(v)[..., None], guides)
    inner = (slice(2 * r, h - 2 * r), slice(2 * r, w - 2 * r))
    spread = q.astype(np.float64).var(axis=-1)[inner]

    def model(guide_var):
        return filtered_variance(v[..., None], v[..., None], g0, radius=r, eps=eps, slopes=p0[..., None],
                                 guide_var=guide_var, terms=[[(0, 0, 1.0)]])[..., 0][inner]

    both, weights = model(gv), model(np.zeros((h, w)))
    assert np.mean(spread / both) == pytest.approx(1.0, abs=0.05)
    assert np.mean(spread / weights) > 1.5 and np.mean(spread / (both - weights)) > 1.5
    assert np.mean(spread / flat(v)[inner]) > 3.0


def test_half_pixel_warped_samples_are_averaged_by_the_filter_as_their_sensor_pixels():
    """Samples halfway between sensor rows are correlated (neighbours share a pixel): the filter averages the
    sensor pixels beneath them, so its variance is the pixels' variance interpolated with the weights themselves
    times rho(0.5) = 0.97 (radius 2), not the samples' sum w^2 var (half of it), which would understate it
    twofold."""
    from specgpu.pipeline.moving_decode import warped_sample_variance

    rng = np.random.default_rng(8)
    h, w, draws, r = 40, 48, 400, 2
    _, bundle, plan, _ = moving_setup()
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel(gain_e_per_dn=2.0, read_var_dn2=1.0))
    frames = np.full((1, h, w), 200.0)  # a flat frame: per-pixel variance (200 / 2 + 1) = 101 DN^2
    shifts = np.array([[0.0, 0.5]])  # half a pixel down
    samples = warped_sample_variance(frames, plan, 0.0, None, shifts, read=[0])[0]
    as_filtered = warped_sample_variance(frames, plan, 0.0, None, shifts, read=[0], filtered=r)[0]
    inner = (slice(2 * r, h - 2 * r - 1), slice(2 * r, w - 2 * r))
    np.testing.assert_allclose(samples[inner], 0.5 * 101.0, rtol=1e-9)
    rho = 1 - 2 * 0.25 * (1 - 80 / 85)  # the box-box weights' autocorrelation at one pixel over at zero
    np.testing.assert_allclose(as_filtered[inner], rho * 101.0, rtol=1e-9)
    c = rng.standard_normal((h + 1, w, draws)) * np.sqrt(101.0)
    q = filtered_draws(0.5 * (c[:-1] + c[1:]), np.ones((h, w)))
    spread = q.astype(np.float64).var(axis=-1)[inner]
    assert np.mean(spread / flat(as_filtered)[inner]) == pytest.approx(1.0, abs=0.03)
    assert np.mean(spread / flat(samples)[inner]) > 1.8


# --------------------------------------------------------------------------- the stream and the batch equal recover

@pytest.fixture(scope="module")
def chart():
    """The 7-band plan with its noise model, the oracle calibration, and a chart with a 0.99 white tile."""
    from specgpu.rig.scene import colorchecker_scene

    desc, bundle, plan, _ = moving_setup()
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
    return plan, bundle, colorchecker_scene(240, 320, white_tile=0.99)


def streamed(plan, bundle, scene, outputs, *, motion="none", white_roi=None, seed=7):
    """One sequence streamed from the twin (moving (2, 1) px per frame with ``motion``): its maps and frames."""
    from specgpu.capture.twin_driver import TwinDriver
    from specgpu.pipeline.stream import Stream
    from specgpu.rig.twin import TwinRig

    moving = {} if motion == "none" else {"motion": MOVING}
    rig = TwinRig(plan.rig_description(RigDescription(camera=CAM, **moving)), scene=scene)
    rig.seed = seed
    kept = []
    Stream(TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K, pacing="free"), plan, bundle, outputs=outputs,
           cube_dtype=np.float32, policy="block", motion=motion, white_roi=white_roi, denoise=DENOISE,
           sinks=[lambda r: kept.append(({k: np.array(v) for k, v in r.arrays.items()}, np.array(r.frames)))]).run()
    (maps, frames), = kept
    return maps, frames


def recovered(plan, bundle, frames, *, motion="none", white_roi=None):
    """``recover --denoise --sigma --delta-e-sigma`` of one sequence: the cube, the sigma map (with its RMS) and
    dE_sigma, as recover writes them."""
    folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
    kw = {"sequence": 0, "motion": motion, "white_roi": white_roi}
    cube = recover(folder, denoise=DENOISE, **kw)
    sigma, cov = uncertainty(folder, illuminant="D65", denoise=DENOISE, **kw)
    dE_sigma = delta_E_sigma_map(to_XYZ(cube, plan), cov, plan.white_XYZ("D65"))
    return cube, sigma_with_rms(sigma, plan.output_labels)[0], dE_sigma


def white_tile_roi(plan, bundle, scene, motion):
    """The white tile where a sequence of the twin (moving as :func:`streamed` makes it) has it at its reference
    time, inset by 2 px."""
    from specgpu.pipeline.twin_capture import capture_plan

    moving = {} if motion == "none" else {"motion": MOVING}
    frames = capture_plan(RigDescription(camera=CAM, **moving), plan, scene, noise_seed=1,
                          calibration=bundle).sequences[0].frames
    cube = SequenceDecoder(plan, bundle, ("cube",), motion="global" if motion != "none" else "none").maps(frames)
    white = np.all(np.abs(cube["cube"] - 0.99) < 0.08, axis=-1) & (np.arange(240) < 40)[:, None]
    ys, xs = np.nonzero(white)
    return f"{xs.min() + 2},{ys.min() + 2},{xs.max() - xs.min() - 3},{max(1, ys.max() - ys.min() - 3)}"


@pytest.mark.parametrize(("motion", "white"), [("none", False), ("none", True), ("global", False),
                                               pytest.param("global", True, marks=pytest.mark.slow),
                                               pytest.param("flow", False, marks=pytest.mark.slow)])
def test_the_streams_denoised_sigmas_equal_recover(chart, motion, white):
    """``stream --denoise`` with every sigma output (on the device without motion, at the warped samples with
    it) equals ``recover --denoise --sigma --delta-e-sigma`` on the same frames (a moving white and the flow in
    the slow set: each runs the motion estimate three times)."""
    plan, bundle, scene = chart
    roi = white_tile_roi(plan, bundle, scene, motion) if white else None
    maps, frames = streamed(plan, bundle, scene, SIGMAS, motion=motion, white_roi=roi)
    cube, sigma, dE_sigma = recovered(plan, bundle, frames, motion=motion, white_roi=roi)
    assert_close_nan(maps["cube"], cube, rtol=1e-4, atol=1e-5)
    assert np.isfinite(sigma[..., 0]).mean() > 0.6
    assert_close_nan(maps["sigma"], sigma, rtol=1e-4, atol=1e-7)
    assert_close_nan(maps["sigma_rms"], sigma[..., -1], rtol=1e-4, atol=1e-7)
    ok = np.isfinite(maps["dE_sigma"])
    np.testing.assert_array_equal(ok, np.isfinite(dE_sigma))
    np.testing.assert_allclose(maps["dE_sigma"][ok], dE_sigma[ok], rtol=1e-3, atol=1e-5)


# ----------------------------------------------------------------------------- calibrated on a moving natural scene

@pytest.mark.parametrize("motion", ["none", "global"])
def test_the_denoised_sigma_of_a_natural_scene_is_calibrated(motion):
    """Two noise draws of one sequence of the natural scene, still or moving (3, 0.5) px per frame (the light's
    fluctuation off: two draws hold one sample of it per band), decoded with the filter (and compensation):
    their difference over sqrt(2) against the denoised sigma has an RMS z-score within [0.8, 1.25] per band, and
    so has dE2000 between the draws against dE_sigma. The mean of box means alone gave 1.5 to 3.5."""
    from specgpu.pipeline.twin_capture import capture_plan

    desc, bundle, plan, scene = moving_setup()
    desc = replace(desc, light=replace(desc.light, fluctuation_rms=0.0))
    plan = with_estimator(plan, bundle, "projection", noise=NoiseModel.from_rig(desc, plan.exposure_s))
    moving = desc if motion == "none" else replace(desc, motion=MotionParameters(velocity_px_per_frame=(3.0, 0.5)))
    dec = SequenceDecoder(plan, bundle, ("cube", "Lab", "sigma", "dE_sigma"), motion=motion, denoise=DENOISE)
    a, b = (dec.maps(capture_plan(moving, plan, scene, noise_seed=s, calibration=bundle).sequences[0].frames)
            for s in (21, 22))
    ok, rms, ratio = draw_pair_scores(a, b, plan.A.shape[0])
    assert ok.mean() > 0.8
    assert np.all((rms > 0.8) & (rms < 1.25)), rms
    assert 0.8 < ratio < 1.25, ratio


# ------------------------------------------------------------------------------------------------- what stays refused

def test_the_refusals_that_remain_are_one_line(chart):
    """A radius beyond the kernel's with a sigma output (each work-item holds its (4r + 1)^2 weights), in the
    stream's set-up and in recover's uncertainty. A plan with an ambient frame is taken under motion."""
    from specgpu.pipeline.denoise import stream_denoise
    from specgpu.pipeline.moving_decode import check_motion_options
    from specgpu.planning.correction import with_ambient_frame

    plan, bundle, _ = chart
    for outputs in (("cube", "sigma"), ("dE_sigma",)):
        with pytest.raises(ValueError, match=f"--denoise-radius {MAX_RADIUS + 1}: the sigma maps") as info:
            stream_denoise(plan, outputs, np.float32, (MAX_RADIUS + 1, 1e-4))
        assert "\n" not in str(info.value)
    assert stream_denoise(plan, ("cube",), np.float32, (MAX_RADIUS + 1, 1e-4))["sigmas"] == []
    folder = SequenceFolder(Path("mem"), np.zeros((1, plan.K, 240, 320), np.uint16), plan, bundle, [], {})
    with pytest.raises(ValueError, match="--denoise-radius 6"):
        uncertainty(folder, denoise=(6, 1e-4))
    assert check_motion_options("global", with_ambient_frame(plan), outputs=("cube", "sigma")) == "global"
