"""recover --denoise: the guided filter of the frames' sum lowers the noise, its sigma map stays calibrated
(the standard deviation of the standardised noise within [0.8, 1.25], over fresh noise draws), raw and denoised
agree where the scene is flat; the command writes the denoised cube and sigma and refuses what it cannot carry."""

from pathlib import Path

import numpy as np
import pytest
from stream_helpers import shared_stream_setup

import specgpu.planning as E
from specgpu.calibration.bundle import oracle_calibration
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.denoise import denoise_recovery, sequence_guide, stream_denoise
from specgpu.pipeline.recovery import recover, to_XYZ, uncertainty
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.priors import held_out_basis
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import colorchecker_scene, natural_scene

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)


def _plan(bundle, prior=None):
    plan = E.plan_hadamard(bundle, bands=7)
    return E.with_estimator(plan, bundle, "projection", prior=prior, noise=E.NoiseModel.from_rig(DESC,
                                                                                                 plan.exposure_s))


def _folder(bundle, plan, scene, seed):
    res = capture_plan(DESC, plan, scene, noise_seed=seed, calibration=bundle)
    return SequenceFolder(Path("<memory>"), np.stack([s.frames for s in res.sequences]), plan, bundle, [], {})


@pytest.mark.parametrize("scene", ["natural", "chart"])
def test_sigma_stays_calibrated_after_denoising(bundle, scene):
    """z = (output - its mean over the draws) / sigma, raw and denoised: the noise the sigma map states."""
    plan = _plan(bundle)
    sc = natural_scene(240, 320) if scene == "natural" else colorchecker_scene(240, 320)
    raw, den, sig_raw, sig_den = [], [], [], []
    for d in range(10):
        folder = _folder(bundle, plan, sc, 500 + d)
        y = recover(folder)
        s = uncertainty(folder)[0]
        raw.append(y)
        sig_raw.append(s)
        den.append(denoise_recovery(folder, y))
        sig_den.append(uncertainty(folder, denoise=(2, 1e-4))[0])
    n = len(raw)
    for ys, ss, name in ((raw, sig_raw, "raw"), (den, sig_den, "denoised")):
        ys, ss = np.stack(ys), np.stack(ss)
        z = (ys - ys.mean(axis=0)) / ss * np.sqrt(n / (n - 1))
        assert 0.8 <= np.nanstd(z) <= 1.25, (name, np.nanstd(z))
    # the filter lowered the noise (the light's fluctuation, common to every pixel of a frame, stays: Hadamard's
    # bright frames make it most of this plan's noise), and its sigma says by how much
    spread = [np.nanstd(np.stack(v) - np.stack(v).mean(0)) for v in (raw, den)]
    rms = [np.sqrt(np.nanmean(np.stack(v) ** 2)) for v in (sig_raw, sig_den)]
    assert spread[1] < 0.95 * spread[0]
    assert spread[1] / spread[0] == pytest.approx(rms[1] / rms[0], rel=0.1)


def test_flat_patches_keep_their_level_and_the_guide_is_normalised(bundle):
    plan = _plan(bundle)
    sc = colorchecker_scene(240, 320)
    folder = _folder(bundle, plan, sc, 7)
    g = sequence_guide(folder)
    assert g.shape == (240, 320) and np.nanpercentile(g, 99) == pytest.approx(1.0, rel=1e-5)
    y = recover(folder)
    q = denoise_recovery(folder, y)
    for mask in list(sc.masks.values())[:6]:  # a patch's mean is unchanged (the window lies inside it)
        np.testing.assert_allclose(q[mask].mean(axis=0), y[mask].mean(axis=0), atol=2e-3)


def test_filtering_the_output_subspace_equals_filtering_every_band(bundle):
    from specgpu.engine.guided import guided_filter
    from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS, output_subspace

    plan = E.plan_narrowband(bundle, step_nm=10.0)  # 31 outputs from 31 frames: full rank, filtered as they are
    assert output_subspace(plan).shape == (31, 31)
    plan = _plan(bundle)  # 7 outputs of 7 frames
    folder = _folder(bundle, plan, natural_scene(240, 320), 3)
    y = recover(folder)
    every = guided_filter(y, sequence_guide(folder), radius=DENOISE_RADIUS, eps=DENOISE_EPS)
    np.testing.assert_allclose(denoise_recovery(folder, y), every, atol=2e-5)
    sym = E.with_estimator(E.plan_symmetric_basis(bundle, held_out_basis(), m=5,
                                                  output_wavelengths=np.arange(400.0, 701.0, 10.0)),
                           bundle, "projection", noise=E.NoiseModel.from_rig(DESC, 0.005))
    U = output_subspace(sym)
    assert U.shape == (31, 5)  # 9 frames, 5 basis functions: the outputs span 5 dimensions
    folder = _folder(bundle, sym, natural_scene(240, 320), 4)
    y = recover(folder)
    every = guided_filter(y, sequence_guide(folder), radius=DENOISE_RADIUS, eps=DENOISE_EPS)
    np.testing.assert_allclose(denoise_recovery(folder, y), every, atol=2e-5)


def test_stream_denoise_equals_recover_denoise():
    """The stream's denoised coefficients, cube and XYZ equal recover --denoise on the same frames, its Lab and dE
    those of the filtered XYZ (colour-science's); a float16 cube is refused in one line."""
    import colour

    from specgpu.pipeline.stream import Stream

    setup = shared_stream_setup(320, 240, sequences=2, output_step_nm=10.0)
    got = []
    stream = Stream(setup.driver(loops=1), setup.plan, setup.bundle,
                    outputs=("coefficients", "cube", "XYZ", "Lab", "dE"), reference=setup.reference,
                    cube_dtype=np.float32, policy="block", denoise=(2, 1e-4),
                    sinks=[lambda r: got.append((r.frame_ids.copy(), {k: v.copy() for k, v in r.arrays.items()}))])
    stream.run()
    assert len(got) == 2
    K = setup.plan.K
    for ids, maps in got:
        i = setup.recorded_sequence(ids)
        folder = SequenceFolder(Path("."), setup.frames[i * K:(i + 1) * K][None], setup.plan, setup.bundle, [], {})
        raw = recover(folder)
        want = denoise_recovery(folder, raw, radius=2, eps=1e-4)
        scale = np.max(np.abs(want))
        np.testing.assert_allclose(maps["cube"], want, atol=1e-4 * scale)
        np.testing.assert_allclose(maps["coefficients"] @ stream.decoder.basis.T, want, atol=1e-4 * scale)
        np.testing.assert_allclose(maps["XYZ"], to_XYZ(want, setup.plan), atol=1e-4)
        # the white of the plan's grid, as the stream's Lab takes it
        lab = colour.XYZ_to_Lab(maps["XYZ"].astype(np.float64), colour.XYZ_to_xy(setup.plan.white_XYZ("D65")))
        np.testing.assert_allclose(maps["Lab"], lab, atol=2e-3)
        ref = np.broadcast_to(np.asarray(setup.reference, np.float64), lab.shape)
        np.testing.assert_allclose(maps["dE"], colour.delta_E(ref, lab, method="CIE 2000"), atol=2e-3)
        assert np.abs(maps["cube"] - raw).max() > 10 * 1e-4 * scale  # it did filter
    # the sigmas are carried through the filter (tests/pipeline/test_denoised_sigma_paths.py), dE_sigma from the
    # filtered XYZ
    carried = stream_denoise(setup.plan, ("cube", "sigma_rms", "dE_sigma"), np.float32, (2, 1e-4))
    assert carried["sigmas"] == ["sigma_rms", "dE_sigma"] and set(carried["channels"]) == {"cube", "XYZ"}
    for outputs, why in ((("cube",), "float32 cube"),):
        with pytest.raises(ValueError, match=why) as info:
            Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=outputs, reference=setup.reference,
                   cube_dtype=np.float16, denoise=(2, 1e-4))
        assert "\n" not in str(info.value)
