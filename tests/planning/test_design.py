"""Illumination design: the Wiener objective's gradient, optimal plans within every limit of the light, one-line
refusals, Hadamard multiplexing's S-matrix, and both made by name through the one plan registry."""

import numpy as np
import pytest
from estimator_helpers import DESC, H, W, noise_at  # the bundle fixture: tests/planning/conftest.py

import specgpu.planning as E
from specgpu.engine.linear_map import apply_linear
from specgpu.planning import design as D
from specgpu.planning import make_plan
from specgpu.planning.estimators import forward, output_weights
from specgpu.planning.priors import held_out_basis, held_out_spectra, training_spectra
from specgpu.rig.scene import patch_scene
from specgpu.rig.twin import TwinRig


@pytest.fixture(scope="module")
def prior():
    return E.default_prior()


def test_objective_gradient_matches_finite_differences(prior):
    rng = np.random.default_rng(0)
    F = rng.uniform(0, 20, (5, prior.wavelengths.size))
    P = np.eye(prior.wavelengths.size) / prior.wavelengths.size
    n = E.NoiseModel(30.0, 0.5, 0.01)
    J, g = D.wiener_objective(F, prior, n, P)
    for _ in range(3):
        d = rng.normal(size=F.shape) * 1e-4
        J2, _ = D.wiener_objective(F + d, prior, n, P)
        assert J2 - J == pytest.approx((g * d).sum(), rel=1e-3)
    # the objective is the Wiener decoder's expected error
    A = E.wiener_decoder(F, np.eye(F.shape[1]), prior, n)
    assert J == pytest.approx(E.expected_error(A, F, np.eye(F.shape[1]), prior, n)["mse"].mean(), rel=1e-9)


@pytest.fixture(scope="module")
def optimal6(bundle, prior):
    return D.plan_optimal(bundle, prior, noise_at, frames=6, starts=2)


def test_optimal_plan_respects_every_limit(bundle, optimal6):
    p = optimal6
    assert p.K == 6 and p.patterns.shape == (6, bundle.columns)
    assert p.patterns.min() >= 0 and p.patterns.max() <= bundle.rows  # rows (mirrors per column)
    assert np.all(p.patterns.sum(axis=1) > 0)
    assert bundle.min_exposure_s <= p.exposure_s <= 0.25  # exposure within the light's switch time and the cap
    assert p.expected_level.max() <= 0.9 + 1e-9  # no frame saturates a white
    d = p.rig_description(DESC)  # the frame time follows the exposure plus the switch time
    assert 1.0 / d.camera.frame_rate_hz >= p.exposure_s + DESC.light.switch_time_s
    lit = np.flatnonzero(p.patterns.any(axis=0))  # only columns the light has
    assert lit.max() < bundle.columns
    TwinRig(d, scene="white").load_sequence(p.patterns)  # the twin's light accepts the sequence


def test_optimal_beats_the_paper_design_in_expectation(bundle, prior, optimal6):
    basis = held_out_basis()
    biased = make_plan("biased", bundle, basis, m=5, output_wavelengths=np.arange(400.0, 701.0, 10.0))
    w = E.with_estimator(biased, bundle, "wiener", prior=prior, noise=noise_at(biased.exposure_s))
    assert optimal6.params["expected"]["rmse"] < 0.8 * w.params["expected"]["rmse"]
    assert optimal6.params["estimator"] == "wiener" and optimal6.params["objective"] == "rmse"


def test_optimal_plan_recovers_the_held_out_chart_noise_free(bundle, optimal6):
    names, wl, spec = held_out_spectra()
    scene = patch_scene(names, wl, spec, H, W)
    rig = TwinRig(optimal6.rig_description(DESC), scene=scene)
    rig.load_sequence(optimal6.patterns)
    frames = np.stack([rig.expected_frame(k) for k in range(optimal6.K)])
    y = apply_linear(frames, optimal6.A, bundle.dark_at(optimal6.exposure_s), bundle.flat_field)
    from specgpu.pipeline.evaluate import truth_cube

    mask = np.any(list(scene.masks.values()), axis=0)
    err = np.sqrt(((y - truth_cube(scene, optimal6.output_wavelengths)) ** 2).mean(axis=-1))[mask].mean()
    assert err < 1.3 * optimal6.params["expected"]["rmse"]


def test_unreachable_objective_and_empty_training_are_one_line(bundle, prior):
    with pytest.raises(ValueError, match="unreachable") as info:
        D.plan_optimal(bundle, prior, noise_at, frames=3, target=1e-4, starts=1)
    assert "\n" not in str(info.value)
    empty = E.Prior(prior.wavelengths, np.zeros_like(prior.moment), np.zeros_like(prior.mean), 0)
    with pytest.raises(ValueError, match="training set is empty"):
        D.plan_optimal(bundle, empty, noise_at, frames=3)
    with pytest.raises(ValueError, match="objective"):
        D.plan_optimal(bundle, prior, noise_at, frames=3, objective="psnr")
    with pytest.raises(ValueError, match="exposure_s"):
        D.plan_optimal(bundle, prior, noise_at, frames=3, exposure_s=10.0)


def test_colour_objective_design(bundle, prior):
    p = D.plan_optimal(bundle, prior, noise_at, frames=3, objective="dEab", training=training_spectra(), starts=1)
    assert p.params["objective"] == "dEab" and p.params["expected"]["dEab"] > 0
    assert p.patterns.max() <= bundle.rows and p.expected_level.max() <= 0.9 + 1e-9


def test_s_matrix():
    for n in (3, 7, 15, 31):
        S = D.s_matrix(n)
        assert S.shape == (n, n) and set(np.unique(S)) == {0, 1}
        assert np.all(S.sum(axis=1) == (n + 1) // 2)
        np.testing.assert_allclose(np.linalg.inv(S.astype(float)), 2 / (n + 1) * (2 * S.T - 1), atol=1e-12)
    with pytest.raises(ValueError, match="hadamard bands"):
        D.s_matrix(10)


def test_the_registry_makes_optimal_and_hadamard_plans_with_their_own_signatures(bundle, prior):
    """make_plan dispatches to the designs with their own arguments: the same plans as calling them directly."""
    had = make_plan("hadamard", bundle, bands=7)
    assert had.method == "hadamard" and had.K == 7
    np.testing.assert_array_equal(had.A, D.plan_hadamard(bundle, bands=7).A)
    opt = make_plan("optimal", bundle, prior, noise_at, frames=3, starts=1, iterations=20)
    assert opt.method == "optimal" and opt.K == 3 and opt.params["estimator"] == "wiener"
    np.testing.assert_array_equal(opt.patterns, D.plan_optimal(bundle, prior, noise_at, frames=3, starts=1,
                                                               iterations=20).patterns)


def test_a_design_lights_only_the_wavelengths_its_prior_knows(bundle, prior):
    from specgpu.planning.budget import budget_plan

    plan = budget_plan("optimal", bundle, 0.060, prior, noise_at, frames=9, starts=1, iterations=100,
                       min_frame_period_s=DESC.camera.min_frame_period_s)
    inside = D.columns_within(bundle, prior.wavelengths)
    assert inside.any() and not inside.all()
    assert not plan.patterns[:, ~inside].any()
    # a surface that differs from another only beyond the prior's 700 nm (a leaf's red edge) decodes the same
    wl = bundle.wavelengths
    F = forward(bundle, plan, wl)
    r = np.interp(wl, prior.wavelengths, prior.mean)
    edge = r + np.where(wl > 705.0, 0.4 * np.minimum((wl - 705.0) / 40.0, 1.0), 0.0)
    shift = plan.A @ F @ (edge - r)
    assert np.sqrt(np.mean(shift ** 2)) < 0.003
    # a prior on a narrower range narrows the light the same way
    keep = (prior.wavelengths >= 450) & (prior.wavelengths <= 650)
    narrow = E.Prior(prior.wavelengths[keep], prior.moment[np.ix_(keep, keep)], prior.mean[keep], prior.n, "narrow")
    npl = budget_plan("optimal", bundle, 0.060, narrow, noise_at, frames=4, starts=1, iterations=50,
                      min_frame_period_s=DESC.camera.min_frame_period_s)
    light = forward(bundle, npl, wl)
    within = light[:, (wl >= 450) & (wl <= 650)].sum(axis=1) / light.sum(axis=1)
    assert within.min() >= 0.99 - 1e-9


def test_a_design_for_denoising_trades_averaged_noise_for_shape(bundle, prior):
    from specgpu.engine.guided import flat_variance_reduction
    from specgpu.planning.budget import budget_plan

    kw = dict(frames=6, starts=1, iterations=100, min_frame_period_s=DESC.camera.min_frame_period_s)
    plain = budget_plan("optimal", bundle, 0.040, prior, noise_at, **kw)
    for_filter = budget_plan("optimal", bundle, 0.040, prior, noise_at, denoise_radius=2, **kw)
    n = flat_variance_reduction(2)
    assert for_filter.params["denoise"] == {"radius": 2, "variance_reduction": n}
    assert E.NoiseModel.from_params(for_filter.params["noise"]) == noise_at(for_filter.exposure_s)
    quiet = noise_at(for_filter.exposure_s).averaged(n)

    def at(plan, noise):  # the expected RMSE of the plan's decoder at a noise
        F = forward(bundle, plan, prior.wavelengths)
        return E.expected_error(plan.A, F, output_weights(plan, prior.wavelengths), prior, noise)["rmse"]

    # where the filter flattens the noise the plan designed for it is better; at the camera's noise, worse
    assert at(for_filter, quiet) < at(plain, noise_at(plain.exposure_s).averaged(n))
    assert at(for_filter, quiet) == pytest.approx(for_filter.params["expected"]["rmse_at_decoder_noise"], rel=1e-9)
    assert for_filter.params["expected"]["rmse"] > plain.params["expected"]["rmse"]
