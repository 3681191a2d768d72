"""Estimators (Wiener, smooth, projection) against float64 NumPy references, their expected error against exact
averages, per-pixel sigma maps against NumPy and against the twin's real noise."""

import numpy as np
import pytest
from estimator_helpers import DESC, WL, H, W
from hypothesis import given, settings
from hypothesis import strategies as st

import specgpu.planning as E
from specgpu.engine.linear_map import apply_linear
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning import load_plan, make_plan, save_plan
from specgpu.planning.estimator_plans import chart_error
from specgpu.planning.estimators import forward, interp_rows, output_weights, smooth_decoder
from specgpu.planning.priors import HELD_OUT_CHART, held_out_spectra, read_training, subspace_bound
from specgpu.planning.uncertainty import constant_covariance, constant_variance, frame_variance, variance_rows
from specgpu.rig.scene import patch_scene


def _random_problem(seed, K=6, P=31):
    rng = np.random.default_rng(seed)
    F = rng.uniform(0, 50, (K, WL.size))
    Wout = interp_rows(np.linspace(400, 700, P), WL)
    noise = E.NoiseModel(rng.uniform(5, 50), rng.uniform(0.1, 5), rng.uniform(0, 0.02))
    return F, Wout, noise


def test_prior_is_the_second_moment(spectra):
    p = E.prior_from_spectra(spectra, WL)
    ref = np.zeros((WL.size, WL.size))
    for r in spectra:
        ref += np.outer(r, r)
    np.testing.assert_allclose(p.moment, ref / len(spectra), rtol=1e-12)
    np.testing.assert_allclose(p.mean, spectra.mean(axis=0), rtol=1e-12)
    assert p.n == len(spectra) > 200


def test_default_prior_leaves_the_held_out_chart_out(spectra):
    _, _, test = held_out_spectra(HELD_OUT_CHART, WL)
    d = np.sqrt(((spectra[:, None, :] - test[None]) ** 2).mean(axis=-1))
    assert d.min() >= 0.01
    assert "ColorChecker" not in HELD_OUT_CHART


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wiener_against_the_information_form(prior, seed):
    F, Wout, noise = _random_problem(seed)
    A = E.wiener_decoder(F, Wout, prior, noise)
    # independent float64 reference: W (S^-1 + F^T N^-1 F)^-1 F^T N^-1 with S regularised to be invertible
    S = prior.moment
    o = F @ prior.mean
    N = o / noise.gain_e_per_dn + noise.read_var_dn2 + noise.light_rms ** 2 * np.diag(F @ S @ F.T)
    Ninv = np.diag(1.0 / N)
    ref = Wout @ np.linalg.pinv(F.T @ Ninv @ F + np.linalg.pinv(S, rcond=1e-14, hermitian=True)) @ F.T @ Ninv
    # the forms agree on the prior's span; compare through the data they act on
    np.testing.assert_allclose(A @ F @ S, ref @ F @ S, rtol=2e-4, atol=1e-6 * np.abs(A @ F @ S).max())


def test_wiener_minimises_the_expected_error(prior):
    F, Wout, noise = _random_problem(3)
    A = E.wiener_decoder(F, Wout, prior, noise)
    best = E.expected_error(A, F, Wout, prior, noise)["mse"].sum()
    rng = np.random.default_rng(4)
    for _ in range(5):
        other = A + rng.normal(scale=1e-3 * np.abs(A).max(), size=A.shape)
        assert E.expected_error(other, F, Wout, prior, noise)["mse"].sum() > best


def test_expected_error_is_the_exact_average(spectra, prior):
    F, Wout, noise = _random_problem(5)
    A = E.wiener_decoder(F, Wout, prior, noise)
    e = E.expected_error(A, F, Wout, prior, noise)
    # mismatch: the exact mean over the training spectra
    err = spectra @ (Wout - A @ F).T
    np.testing.assert_allclose(e["mismatch"], (err ** 2).mean(axis=0), rtol=1e-9)
    # noise: A N A^T on the diagonal
    N = np.diag(noise.covariance(F, prior))
    np.testing.assert_allclose(e["noise"], (A ** 2) @ N, rtol=1e-9)
    np.testing.assert_allclose(e["rmse"], np.sqrt((e["mismatch"] + e["noise"]).mean()), rtol=1e-12)


def test_smooth_against_a_stacked_least_squares():
    """The smooth decoder is the regularised least squares argmin |N^-1/2 (F r - o)|^2 + r^T C^-1 r."""
    F, Wout, noise = _random_problem(6, K=9)
    A = smooth_decoder(F, Wout, noise, WL, correlation_nm=40.0)
    sp = E.smooth_prior(WL, correlation_nm=40.0)
    N = np.diag(noise.covariance(F, sp))
    # whitened coordinates r = U lam^1/2 z, |z|^2 = r^T C^-1 r: a ridge least squares, stacked
    lam, U = np.linalg.eigh(sp.moment)
    T = U * np.sqrt(np.clip(lam, 0, None))
    G = (F @ T) / np.sqrt(N)[:, None]
    stack = np.vstack([G, np.eye(WL.size)])
    rhs = np.vstack([np.diag(1 / np.sqrt(N)), np.zeros((WL.size, F.shape[0]))])
    ref = Wout @ T @ np.linalg.lstsq(stack, rhs, rcond=None)[0]
    np.testing.assert_allclose(A, ref, rtol=1e-4, atol=1e-6 * np.abs(ref).max())
    with pytest.raises(ValueError, match="correlation_nm"):
        E.smooth_prior(WL, correlation_nm=0)


def test_smooth_estimator_without_training(bundle):
    plan = make_plan("narrowband", bundle)
    s = E.with_estimator(plan, bundle, "smooth", noise=E.NoiseModel.from_rig(DESC, plan.exposure_s))
    assert s.params["estimator"] == "smooth" and "smooth prior" in s.params["expected"]["prior"]
    wl = np.arange(400.0, 700.0 + 1e-9, 5.0)
    test = held_out_spectra(wavelengths=wl)[2]
    assert chart_error(s, bundle, test, wl) < 0.01


def test_empty_training_set_is_one_line(tmp_path):
    with pytest.raises(ValueError, match="training set is empty") as info:
        E.default_prior(builtin=False)
    assert "\n" not in str(info.value)
    p = tmp_path / "none.npz"
    np.savez(p, wavelengths=WL, reflectance=np.zeros((0, WL.size)))
    with pytest.raises(ValueError, match="none.npz"):
        E.default_prior(builtin=False, training_files=[p])


def test_training_files_csv_and_npz(tmp_path, spectra):
    csv = tmp_path / "mine.csv"
    rows = ["wavelength,a,b"] + [f"{w},{0.2 + 0.001 * i},{0.5}" for i, w in enumerate(range(380, 781, 10))]
    csv.write_text("\n".join(rows))
    npz = tmp_path / "more.npz"
    np.savez(npz, wavelengths=WL, reflectance=spectra[:3])
    p = E.default_prior(builtin=False, training_files=[csv, npz])
    assert p.n == 5 and "mine.csv" in p.source
    full = E.default_prior(training_files=[csv])
    assert full.n == len(spectra) + 2
    bad = tmp_path / "bad.npz"
    np.savez(bad, wl=WL)
    with pytest.raises(ValueError, match="bad.npz"):
        read_training(bad, WL)


@settings(max_examples=40, deadline=None)
@given(st.floats(-1e3, 1e6) | st.just(float("nan")), st.floats(-10, 1e4) | st.just(float("inf")), st.floats(-1, 2))
def test_noise_model_validator(g, r, rms):
    ok = np.isfinite(g) and g > 0 and np.isfinite(r) and r >= 0 and 0 <= rms < 1
    if ok:
        n = E.NoiseModel(g, r, rms)
        assert E.NoiseModel.from_params(n.as_params()) == n
    else:
        with pytest.raises(ValueError, match="noise"):
            E.NoiseModel(g, r, rms)


def test_noise_model_from_the_camera():
    n = E.NoiseModel.from_rig(DESC, 0.02)
    cam = DESC.camera
    assert n.gain_e_per_dn == pytest.approx(cam.full_well_e / cam.max_code)
    assert n.read_var_dn2 == pytest.approx((cam.read_noise_e ** 2 + cam.dark_current_e_per_s * 0.02)
                                           / n.gain_e_per_dn ** 2 + 1 / 12)


def test_with_estimator_records_and_round_trips(tmp_path, bundle, prior):
    plan = make_plan("narrowband", bundle)
    noise = E.NoiseModel.from_rig(DESC, plan.exposure_s)
    w = E.with_estimator(plan, bundle, "wiener", prior=prior, noise=noise)
    assert w.params["estimator"] == "wiener" and w.params["expected"]["rmse"] > 0
    p = E.with_estimator(plan, bundle, "projection", prior=prior, noise=noise)
    np.testing.assert_array_equal(p.A, plan.A)
    assert w.params["expected"]["rmse"] <= p.params["expected"]["rmse"]
    save_plan(tmp_path / "w.npz", w)
    back = load_plan(tmp_path / "w.npz")
    np.testing.assert_array_equal(back.A, w.A)
    assert back.params["noise"] == noise.as_params()
    with pytest.raises(ValueError, match="estimator"):
        E.with_estimator(plan, bundle, "bayes", prior=prior, noise=noise)
    with pytest.raises(ValueError, match="prior"):
        E.with_estimator(plan, bundle, "wiener", noise=noise)
    steady = make_plan("steady", bundle, "D65")
    with pytest.raises(ValueError, match="no estimator"):
        E.with_estimator(steady, bundle, "wiener", prior=prior, noise=noise)


def test_wiener_tristimulus_outputs_xyz(bundle, prior):
    plan = make_plan("tristimulus", bundle, illuminant="D65")
    w = E.with_estimator(plan, bundle, "wiener", prior=prior, noise=E.NoiseModel.from_rig(DESC, plan.exposure_s))
    assert w.A.shape == (3, 3) and w.output == "XYZ"
    assert w.params["expected"]["rmse"] < 0.01  # XYZ units, Y = 1 for the white


def test_sigma_map_against_numpy(bundle, prior):
    plan = make_plan("narrowband", bundle, step_nm=20.0)
    plan = E.with_estimator(plan, bundle, "wiener", prior=prior, noise=E.NoiseModel.from_rig(DESC, plan.exposure_s))
    rng = np.random.default_rng(0)
    frames = rng.integers(20, 900, (plan.K, 24, 32)).astype(np.uint16)
    dark = np.full((24, 32), 16.0, np.float32)
    gain = rng.uniform(0.9, 1.1, (24, 32)).astype(np.float32)
    sig = E.sigma_map(frames, plan, dark, gain, sequences=2)
    n = E.NoiseModel.from_params(plan.params["noise"])
    assert n.light_rms > 0
    o = frames.astype(np.float64) - dark
    # shot, read and dark noise, and the light's fluctuation at each frame's own signal (it scales the frame)
    var_o = o / n.gain_e_per_dn + n.read_var_dn2 + (n.light_rms * o) ** 2
    ref = np.einsum("bk,khw->hwb", plan.A ** 2, var_o) * gain[..., None].astype(np.float64) ** 2 / 2
    ref += constant_variance(plan)
    np.testing.assert_allclose(sig, np.sqrt(ref), rtol=2e-4)
    # the constant is the prior's mismatch alone (the light is no longer in it at the prior's mean signal)
    np.testing.assert_allclose(constant_variance(plan), plan.params["expected"]["mismatch_var"], rtol=1e-9)
    # without the light (a white reference divides it out) only the linear part stays
    ref_nl = np.einsum("bk,khw->hwb", plan.A ** 2, o / n.gain_e_per_dn + n.read_var_dn2)
    ref_nl = ref_nl * gain[..., None].astype(np.float64) ** 2 / 2 + constant_variance(plan)
    np.testing.assert_allclose(E.sigma_map(frames, plan, dark, gain, sequences=2, light=False), np.sqrt(ref_nl),
                               rtol=2e-4)


def test_frame_variance_at_warped_samples_against_numpy(bundle, prior):
    """With a motion-compensated recovery's shifts each frame's sample variance is read where that frame saw the
    pixel, bilinearly: equal to sampling NumPy's per-sensor-pixel variance there."""
    from scipy import ndimage

    plan = make_plan("narrowband", bundle, step_nm=50.0)
    plan = E.with_estimator(plan, bundle, "projection", noise=E.NoiseModel.from_rig(DESC, plan.exposure_s))
    rng = np.random.default_rng(4)
    frames = rng.integers(20, 900, (plan.K, 24, 32)).astype(np.uint16)
    dark = np.full((24, 32), 16.0, np.float32)
    gain = rng.uniform(0.9, 1.1, (24, 32)).astype(np.float32)
    n = E.NoiseModel.from_params(plan.params["noise"])
    o = frames.astype(np.float64) - dark
    sensor = (o / n.gain_e_per_dn + n.read_var_dn2 + (n.light_rms * o) ** 2) * gain.astype(np.float64) ** 2
    np.testing.assert_allclose(frame_variance(frames, plan, dark, gain, shifts=np.zeros((plan.K, 2))),
                               frame_variance(frames, plan, dark, gain), rtol=1e-5)
    shifts = rng.uniform(-2.5, 2.5, (plan.K, 2))
    got = frame_variance(frames, plan, dark, gain, shifts=shifts)
    yy, xx = np.mgrid[:24, :32].astype(np.float64)
    # sampled as the warped pass samples: bilinear, clamped to the pixel centres; outside the sensor's footprint
    # (more than half a pixel beyond an edge pixel's centre) no sample at all
    at = np.stack([ndimage.map_coordinates(sensor[k], [yy + shifts[k, 1], xx + shifts[k, 0]], order=1,
                                           mode="nearest") for k in range(plan.K)])
    outside = np.any([(xx + dx < -0.5) | (xx + dx > 31.5) | (yy + dy < -0.5) | (yy + dy > 23.5)
                      for dx, dy in shifts], axis=0)
    ref = np.einsum("bk,khw->hwb", plan.A ** 2, at)
    np.testing.assert_array_equal(np.isnan(got[..., 0]), outside)
    assert 0.1 < outside.mean() < 0.6  # both kinds of pixel are compared
    np.testing.assert_allclose(got[~outside], ref[~outside], rtol=2e-4)


def test_sigma_map_needs_a_noise_model(bundle):
    plan = make_plan("narrowband", bundle, step_nm=20.0)
    with pytest.raises(ValueError, match="noise model"):
        E.sigma_map(np.zeros((plan.K, 4, 4), np.uint16), plan, np.zeros((4, 4)), None)


def test_sigma_z_scores_on_the_twin(bundle, prior):
    """Standardised errors of a Wiener symmetric-9 recovery of the held-out chart on the noisy twin."""
    from specgpu.pipeline.evaluate import truth_cube

    names, wl, spec = held_out_spectra()
    scene = patch_scene(names, wl, spec, H, W)
    plan = E.with_estimator(make_plan("narrowband", bundle, step_nm=20.0), bundle, "wiener", prior=prior,
                            noise=E.NoiseModel.from_rig(DESC, make_plan("narrowband", bundle, step_nm=20.0).exposure_s))
    frames = capture_plan(DESC, plan, scene, noise_seed=3).sequences[0].frames
    dark = bundle.dark_at(plan.exposure_s)
    y = apply_linear(frames, plan.A, dark, bundle.flat_field)
    sig = E.sigma_map(frames, plan, dark, bundle.flat_field)
    mask = np.any(list(scene.masks.values()), axis=0)
    err = (y - truth_cube(scene, plan.output_wavelengths))[mask]
    z = err / sig[mask]
    assert 0.8 <= z.std() <= 1.25
    # the exact prediction on the chart's spectra is the measured RMS error within 25 %
    wl = prior.wavelengths
    predicted = chart_error(plan, bundle, held_out_spectra(wavelengths=wl)[2], wl)
    assert 0.8 <= np.sqrt((err ** 2).mean()) / predicted <= 1.25


def test_delta_e_sigma_against_monte_carlo():
    import colour

    from specgpu.engine.colorimetry import XYZ_to_Lab

    rng = np.random.default_rng(1)
    xyz = np.array([[0.3, 0.25, 0.2], [0.1, 0.12, 0.4], [0.6, 0.55, 0.3]])
    C = np.array([[4, 1, 0], [1, 3, 0.5], [0, 0.5, 5]]) * 1e-6
    sig = E.delta_E_sigma(xyz, np.broadcast_to(C, (3, 3, 3)))
    L = np.linalg.cholesky(C)
    for i in range(3):
        draws = xyz[i] + rng.standard_normal((4000, 3)) @ L.T
        lab0 = np.asarray(XYZ_to_Lab(xyz[i][None], "D65"), np.float64)
        lab = np.asarray(XYZ_to_Lab(draws, "D65"), np.float64)
        de = colour.delta_E(lab0, lab, method="CIE 2000")
        assert sig[i] == pytest.approx(np.sqrt(np.mean(de ** 2)), rel=0.1)


def test_subspace_bound_against_numpy_svd():
    rng = np.random.default_rng(3)
    train = rng.uniform(0, 1, (40, 12)) @ np.diag(np.linspace(1, 0.1, 12))
    test = rng.uniform(0, 1, (7, 12))
    for K in (1, 4, 12):
        U = np.linalg.svd(train, full_matrices=False)[2][:K].T
        ref = np.sqrt(np.mean((test - test @ U @ U.T) ** 2))
        assert subspace_bound(train, test, K) == pytest.approx(ref, rel=1e-9, abs=1e-12)
        mu = train.mean(axis=0)
        Uc = np.linalg.svd(train - mu, full_matrices=False)[2][:K].T
        refc = np.sqrt(np.mean(((test - mu) - (test - mu) @ Uc @ Uc.T) ** 2))
        assert subspace_bound(train, test, K, centred=True) == pytest.approx(refc, rel=1e-9, abs=1e-12)
    assert subspace_bound(train, test, 12) < 1e-12
    for bad in (0, 13, 2.5):
        with pytest.raises(ValueError, match="K must be") as err:
            subspace_bound(train, test, bad)
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="one grid"):
        subspace_bound(train, test[:, :5], 3)


def _spread_over_sigma(plan, bundle, scene, draws, seed):
    """Per brightness quintile (darkest first): sqrt(mean spread^2 / mean predicted variance) of the recoveries of
    ``draws`` noise draws, recovered and given their sigma as ``recover --sigma`` does; and the same with the
    light's fluctuation left out of the prediction."""
    from specgpu.pipeline.capture_folder import SequenceFolder
    from specgpu.pipeline.recovery import recover, uncertainty
    from specgpu.planning.correction import ambient_index

    ys, var, var_nl = [], [], []
    dark = bundle.dark_at(plan.exposure_s)
    for i in range(draws):
        frames = capture_plan(DESC, plan, scene, noise_seed=seed + i, calibration=bundle).sequences[0].frames
        folder = SequenceFolder(None, frames[None], plan, bundle, [], {})
        ys.append(np.asarray(recover(folder, sequence=0), np.float64))
        var.append(np.asarray(uncertainty(folder, sequence=0)[0], np.float64) ** 2)
        if ambient_index(plan) is None:
            var_nl.append(np.asarray(E.sigma_map(frames, plan, dark, bundle.flat_field, light=False), np.float64) ** 2)
    y = np.array(ys)
    spread2 = y.var(axis=0, ddof=1)
    level = y.mean(axis=(0, -1))
    edges = np.quantile(level, np.linspace(0, 1, 6))
    out = []
    for v in (np.mean(var, axis=0), np.mean(var_nl, axis=0) if var_nl else np.mean(var, axis=0)):
        out.append([float(np.sqrt(spread2[(level >= a) & (level <= b)].mean() / v[(level >= a) & (level <= b)].mean()))
                    for a, b in zip(edges[:-1], edges[1:])])
    return out


def test_sigma_holds_for_a_multiplexed_plan_in_bright_pixels(bundle):
    """A Hadamard plan (half the light in every frame) on the colorchecker: the spread of the recoveries over noise
    draws is the predicted sigma in the darkest and the brightest fifth of the pixels alike. The light's
    frame-to-frame fluctuation scales each frame, so its variance grows with the pixel's signal squared; left out
    (or taken at the prior's mean signal) the bright pixels' spread is twice the sigma. The fluctuation is common
    to every pixel of a frame, so the bright quintile sees only draws x K independent draws of it: its bounds are
    wide (about +-12 % at 1 sigma for 20 draws), the failure they catch is 2x."""
    from specgpu.planning import plan_hadamard
    from specgpu.rig.scene import colorchecker_scene

    plan = plan_hadamard(bundle, bands=7)
    plan = E.with_estimator(plan, bundle, "projection", noise=E.NoiseModel.from_rig(DESC, plan.exposure_s))
    assert plan.params["noise"]["light_rms"] > 0
    ratio, without_light = _spread_over_sigma(plan, bundle, colorchecker_scene(H, W), draws=20, seed=500)
    assert 0.85 <= ratio[0] <= 1.15, ratio
    assert 0.7 <= ratio[-1] <= 1.35, ratio
    assert without_light[-1] > 1.4, without_light  # the light's fluctuation is what the bright pixels need


def test_constant_covariance_is_the_mismatch_and_reads_an_older_plans_constant(bundle, prior):
    from dataclasses import replace

    plan = make_plan("narrowband", bundle, step_nm=20.0)
    plan = E.with_estimator(plan, bundle, "wiener", prior=prior, noise=E.NoiseModel.from_rig(DESC, plan.exposure_s))
    P = plan.A.shape[0]
    exp = plan.params["expected"]
    assert "constant_cov" not in exp
    C = constant_covariance(plan)
    np.testing.assert_allclose(np.diag(C), exp["mismatch_var"], rtol=1e-9)
    np.testing.assert_allclose(C, C.T, atol=1e-15)
    # a plan saved before the light was taken per pixel: its recorded constant (mismatch + light) is used as it is
    old = {k: v for k, v in exp.items() if k != "mismatch_cov"}
    old["constant_cov"] = (C + 1e-4 * np.eye(P)).ravel().tolist()
    older = replace(plan, params={**plan.params, "expected": old})
    np.testing.assert_allclose(constant_covariance(older), C + 1e-4 * np.eye(P), rtol=1e-12)


def test_sigma_holds_with_an_ambient_frame_in_dark_pixels(bundle):
    """A plan with an ambient frame subtracts it from every frame: its own noise is in every output and counts as
    much as a frame's own read noise in the dark pixels of a narrowband plan (one frame per output); without it the
    darkest fifth's spread is about 1.3 times the sigma."""
    from specgpu.planning.correction import with_ambient_frame
    from specgpu.rig.scene import colorchecker_scene

    plan = make_plan("narrowband", bundle, step_nm=25.0)
    plan = with_ambient_frame(E.with_estimator(plan, bundle, "projection",
                                               noise=E.NoiseModel.from_rig(DESC, plan.exposure_s)))
    ratio, _ = _spread_over_sigma(plan, bundle, colorchecker_scene(H, W), draws=12, seed=700)
    assert 0.9 <= ratio[0] <= 1.1 and 0.85 <= ratio[-1] <= 1.2, ratio


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 9), st.integers(1, 4), st.integers(0, 2 ** 31 - 1), st.booleans())
def test_variance_rows_is_the_covariance_of_frames_above_an_ambient_frame(K, Q, seed, with_ambient):
    """rows . v equals the exact covariance of L (o - a) and R (o - a): frames of variance p_k + w (their own noise
    and the ambient light's and read noise they share in size), the ambient frame a of variance w subtracted from
    each (its decoder column zero); without an ambient frame, L diag(v) R^T."""
    rng = np.random.default_rng(seed)
    amb = int(rng.integers(K)) if with_ambient else None
    L, R = rng.normal(size=(Q, K)), rng.normal(size=(Q, K))
    p, w = rng.uniform(0, 3, K), float(rng.uniform(0, 2))
    if amb is None:
        np.testing.assert_allclose(variance_rows(L, R) @ p, np.einsum("qk,k,qk->q", L, p, R), rtol=1e-12)
        return
    L[:, amb] = R[:, amb] = 0.0
    T_L, T_R = L.copy(), R.copy()
    T_L[:, amb], T_R[:, amb] = -L.sum(axis=1), -R.sum(axis=1)  # y = T z over every frame, the ambient one too
    var = p + w
    var[amb] = w
    want = np.einsum("qk,k,qk->q", T_L, var, T_R)
    v = p.copy()
    v[amb] = w
    np.testing.assert_allclose(variance_rows(L, R, amb) @ v, want, rtol=1e-10, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.floats(-10, 1e4) | st.just(float("nan")))
def test_an_averaged_noise_lowers_shot_and_read_and_keeps_the_light(n):
    base = E.NoiseModel(30.0, 0.5, 0.01)
    if not (np.isfinite(n) and n >= 1):
        with pytest.raises(ValueError, match="averaged pixels"):
            base.averaged(n)
        return
    a = base.averaged(n)
    F = np.array([[10.0, 20.0], [5.0, 1.0]])
    prior = E.Prior(np.array([500.0, 600.0]), np.eye(2) * 0.01 + 0.2, np.array([0.4, 0.5]), 3, "test")
    full, avg = np.diag(base.covariance(F, prior)), np.diag(a.covariance(F, prior))
    light = (base.light_rms ** 2) * np.einsum("kb,bc,kc->k", F, prior.moment, F)
    np.testing.assert_allclose(avg - light, (full - light) / n, rtol=1e-9)


def test_a_decoder_for_another_noise_keeps_the_cameras_noise_model(bundle, prior):
    plan = make_plan("hadamard", bundle, bands=7)
    camera = E.NoiseModel.from_rig(DESC, plan.exposure_s)
    quiet = camera.averaged(50.0)
    w = E.with_estimator(plan, bundle, "wiener", prior=prior, noise=camera, decoder_noise=quiet)
    F = forward(bundle, plan, prior.wavelengths)
    Wout = output_weights(plan, prior.wavelengths)
    np.testing.assert_allclose(w.A, E.wiener_decoder(F, Wout, prior, quiet), rtol=1e-12)
    assert E.NoiseModel.from_params(w.params["noise"]) == camera  # the sigma maps use the camera's noise
    assert E.NoiseModel.from_params(w.params["decoder_noise"]) == quiet
    plain = E.with_estimator(plan, bundle, "wiener", prior=prior, noise=camera)
    # stated at the camera's noise the decoder for less noise does worse, at its own noise better
    assert w.params["expected"]["rmse"] > plain.params["expected"]["rmse"]
    assert w.params["expected"]["rmse_at_decoder_noise"] < plain.params["expected"]["rmse"]
    assert "decoder_noise" not in plain.params
    with pytest.raises(ValueError, match="projection has none"):
        E.with_estimator(plan, bundle, "projection", prior=prior, noise=camera, decoder_noise=quiet)
