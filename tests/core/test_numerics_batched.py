"""Bounded least squares of several targets at once, and over a system whose columns reach a band of rows only:
the same levels as the plain projected gradient, one target at a time, over every entry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from specgpu.core.numerics import fit_levels, lipschitz_bound


def plain_fit(m, t, upper, iterations):
    """The projected gradient with Nesterov momentum written out with the full matrix, one target."""
    hi = np.inf if upper is None else upper
    full = m.sum(axis=1)
    peak = np.argmax(m, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.clip(np.nan_to_num(np.where(full[peak] > 0, t[peak] / full[peak], 0.0)), 0.0, hi)
    step = 1.0 / lipschitz_bound(m)
    y, tk = f.copy(), 1.0
    for _ in range(iterations):
        f_new = np.clip(y - step * (m.T @ (m @ y - t)), 0.0, hi)
        tk_new = 0.5 * (1 + math.sqrt(1 + 4 * tk * tk))
        y = f_new + ((tk - 1) / tk_new) * (f_new - f)
        f, tk = f_new, tk_new
    f[m.sum(axis=0) <= 0] = 0.0
    return f


def light_like(rows: int, cols: int, seed: int) -> np.ndarray:
    """Column spectra zero beyond 12 rows of their centre (the light's system matrix is mostly zeros), the first
    150 columns dark (a block of columns that reaches no row)."""
    rng = np.random.default_rng(seed)
    centres = np.linspace(0, rows - 1, cols)
    d = np.arange(rows)[:, None] - centres[None]
    m = np.where(np.abs(d) <= 12, np.exp(-0.5 * (d / 5.0) ** 2), 0.0) * rng.uniform(0.5, 1.5, cols)
    m[:, :150] = 0.0
    return m


@pytest.mark.parametrize("upper", [1.0, None])
def test_several_targets_fit_at_once_give_each_targets_own_levels(upper):
    m = light_like(200, 520, 3)
    g = np.arange(200.0)
    targets = np.stack([np.exp(-0.5 * ((g - c) / 30.0) ** 2) for c in (60.0, 110.0, 170.0)], axis=1)
    together = fit_levels(m, targets, upper=upper, iterations=150)
    assert together.shape == (520, 3)
    for k in range(3):
        alone = fit_levels(m, targets[:, k], upper=upper, iterations=150)
        np.testing.assert_allclose(together[:, k], alone, rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("system", ["banded", "dense"])
def test_the_fit_equals_the_plain_gradient_over_every_entry(system):
    rng = np.random.default_rng(5)
    m = light_like(200, 520, 4) if system == "banded" else rng.uniform(0.0, 1.0, (60, 300))
    t = 0.4 * m.sum(axis=1) * np.linspace(0.3, 1.2, m.shape[0])
    f = fit_levels(m, t, upper=1.0, iterations=120)
    ref = plain_fit(m, t, 1.0, 120)
    np.testing.assert_allclose(f, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    if system == "banded":
        assert np.all(f[:150] == 0.0) and f[150:].max() > 0  # the dark columns stay off


def test_a_target_of_the_wrong_rows_is_an_error_naming_both_shapes():
    m = light_like(200, 520, 6)
    with pytest.raises(ValueError, match=r"target must have shape \(200,\), got \(199, 2\) \(or \(200, K\)"):
        fit_levels(m, np.ones((199, 2)))
