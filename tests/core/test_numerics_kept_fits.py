"""The fits fit_levels keeps: the same fit asked again is the kept answer (not redone), a copy the caller may
change, and anything that changes the fit (the system, the target, the bound, the step count) is fitted afresh."""

from __future__ import annotations

import numpy as np
import pytest

from specgpu.core import numerics
from specgpu.core.numerics import fit_levels


def system(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = np.linspace(0, 59, 20)
    return np.exp(-0.5 * ((np.arange(60)[:, None] - centres[None]) / 2.0) ** 2) * rng.uniform(0.5, 1.5, 20)


@pytest.fixture
def counted(monkeypatch):
    """The uncached fit, counted; the kept fits emptied for the test (and restored after it)."""
    calls = []
    fit = numerics._fit

    def counting(*args):
        calls.append(args)
        return fit(*args)

    monkeypatch.setattr(numerics, "_fit", counting)
    monkeypatch.setattr(numerics, "_fits", type(numerics._fits)())
    return calls


def test_the_same_fit_again_is_the_kept_answer_and_a_copy(counted):
    m = system(1)
    target = 0.5 * m.sum(axis=1)
    first = fit_levels(m, target, iterations=50)
    first[:] = -1.0  # the caller's copy: changing it changes nothing kept
    again = fit_levels(m.copy(), target.copy(), iterations=50)
    assert len(counted) == 1
    np.testing.assert_array_equal(again, numerics._fit(m, target, 1.0, 50))
    assert again.min() >= 0.0


@pytest.mark.parametrize("change", ["system", "target", "upper", "iterations"])
def test_whatever_changes_the_fit_is_fitted_afresh(counted, change):
    m, upper, iterations = system(2), 1.0, 50
    target = 0.5 * m.sum(axis=1)
    fit_levels(m, target, upper=upper, iterations=iterations)
    if change == "system":
        m = m.copy()
        m[10, 3] += 1e-9
    elif change == "target":
        target = target.copy()
        target[0] += 1e-9
    elif change == "upper":
        upper = None
    else:
        iterations += 1
    fit_levels(m, target, upper=upper, iterations=iterations)
    assert len(counted) == 2


def test_only_the_last_fits_are_kept(counted):
    m = system(3)
    targets = [s * m.sum(axis=1) for s in np.linspace(0.1, 0.9, numerics._FITS_KEPT + 1)]
    for target in targets:
        fit_levels(m, target, iterations=5)
    assert len(numerics._fits) == numerics._FITS_KEPT
    fit_levels(m, targets[-1], iterations=5)  # kept
    assert len(counted) == numerics._FITS_KEPT + 1
    fit_levels(m, targets[0], iterations=5)  # the oldest was dropped
    assert len(counted) == numerics._FITS_KEPT + 2
