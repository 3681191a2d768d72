"""The limit of K-frame designs: the lower bound lies below the Wiener error of every feasible design (random
frames within the box, and the designer's own), above the prior's noise-free rank limit; its pieces against brute
force; ``specgpu bound`` prints it and refuses a budget too short in one line."""

import itertools
import math

import numpy as np
import pytest
from estimator_helpers import noise_at  # the bundle fixture: tests/planning/conftest.py

import specgpu.planning as E
from specgpu.planning import design as D
from specgpu.planning.bound import design_bound, frame_information, waterfill_mse


@pytest.fixture(scope="module")
def prior():
    return E.default_prior()


def test_frame_information_is_the_box_maximum():
    rng = np.random.default_rng(3)
    u, m = rng.uniform(0.1, 5, 8), rng.uniform(0.01, 1, 8)
    a = 2.0
    brute = max((np.where(v, u, 0) @ np.where(v, u, 0)) / (a + m @ np.where(v, u, 0))
                for v in itertools.product([0, 1], repeat=8))
    assert frame_information(u, m, a) == pytest.approx(brute, rel=1e-12)
    F = rng.uniform(0, 1, (2000, 8)) * u
    assert np.max(np.sum(F ** 2, 1) / (a + F @ m)) <= brute
    cap = 0.3 * u.sum()  # under a cap on the white signal: still above every capped frame's value
    Fc = F[F.sum(axis=1) <= cap]
    assert np.max(np.sum(Fc ** 2, 1) / (a + Fc @ m)) <= frame_information(u, m, a, cap) <= brute + 1e-12


def test_waterfill_against_a_search():
    s = np.array([5.0, 2.0, 0.5, 0.1, 0.01])
    got = waterfill_mse(s, 2, 3.0)
    rng = np.random.default_rng(0)
    for _ in range(3000):  # any split of the 2 x 3 information over any two directions does no better
        d = np.zeros(5)
        idx = rng.choice(5, 2, replace=False)
        d[idx] = rng.dirichlet([1, 1]) * 6.0
        assert np.sum(s / (1 + s * d)) >= got - 1e-12
    assert waterfill_mse(s, 2, 0.0) == pytest.approx(s.sum())
    assert got >= s[2:].sum()


def test_bound_lies_below_every_feasible_design(bundle, prior):
    K, T = 4, 0.04
    b = design_bound(bundle, prior, noise_at, frames=K, sequence_s=T, starts=1, iterations=60)
    assert b.noise_free_rmse <= b.lower_rmse <= b.achieved_rmse
    t = b.exposure_s
    assert K * (t + bundle.min_exposure_s) <= T * (1 + 1e-9)
    Sb = D._system_on(bundle, prior.wavelengths)
    n = noise_at(t)
    B = prior.wavelengths.size
    cap = 0.9 * (bundle.max_code - float(np.mean(bundle.dark)))
    rng = np.random.default_rng(5)
    for _ in range(30):  # random mirror levels at the budget's exposure, dimmed to the camera's range
        x = rng.uniform(0, 1, (K, Sb.shape[0])) ** rng.uniform(0.2, 5)
        F = t * x @ Sb
        F *= np.minimum(1.0, cap / F.sum(axis=1))[:, None]
        J, _ = D.wiener_objective(F, prior, n, np.eye(B) / B)
        assert math.sqrt(J) >= b.lower_rmse
    plan = E.plan_optimal(bundle, prior, noise_at, frames=K, sequence_s=T, starts=1, iterations=60,
                          output_wavelengths=prior.wavelengths)
    assert plan.params["expected"]["rmse"] >= b.lower_rmse


def test_the_limit_where_a_filter_flattens_the_noise_is_lower_and_says_so(bundle, prior):
    kw = dict(frames=4, sequence_s=0.04, starts=1, iterations=60)
    one = design_bound(bundle, prior, noise_at, **kw)
    flat = design_bound(bundle, prior, noise_at, averaged=54.0, **kw)
    assert flat.noise_free_rmse == pytest.approx(one.noise_free_rmse)
    assert flat.noise_free_rmse <= flat.lower_rmse < one.lower_rmse
    assert flat.achieved_rmse < one.achieved_rmse
    assert "averaged over 54 pixels" in " ".join(flat.lines()) and "averaged" not in " ".join(one.lines())
    # a design for the filtered noise, stated at that noise, lies above its limit
    plan = E.plan_optimal(bundle, prior, noise_at, frames=4, sequence_s=0.04, starts=1, iterations=60,
                          output_wavelengths=prior.wavelengths, denoise_radius=2)
    assert plan.params["expected"]["rmse_at_decoder_noise"] >= design_bound(
        bundle, prior, noise_at, averaged=plan.params["denoise"]["variance_reduction"], **kw).lower_rmse
