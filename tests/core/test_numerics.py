"""Bounded least squares of light levels, against SciPy's solver, and the Lipschitz bound that sets its step."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear

from specgpu.core.numerics import DEAD_PIXEL_GAIN, fit_levels, lipschitz_bound, live_gain


def banded(rows: int, cols: int, width: float, seed: int) -> np.ndarray:
    """A narrow-banded, nonnegative system like the light's column spectra (one Gaussian per column)."""
    rng = np.random.default_rng(seed)
    centres = np.linspace(0, rows - 1, cols)
    g = np.exp(-0.5 * ((np.arange(rows)[:, None] - centres[None]) / width) ** 2)
    return g * rng.uniform(0.5, 1.5, cols)


@pytest.mark.parametrize("upper", [1.0, None])
def test_fit_levels_matches_scipys_bounded_least_squares(upper):
    m = banded(120, 40, 2.5, 1)
    target = 0.6 * m.sum(axis=1) * np.linspace(0.2, 1.1, 120)  # reachable in the middle, clipped at the ends
    f = fit_levels(m, target, upper=upper, iterations=3000)
    ref = lsq_linear(m, target, bounds=(0.0, np.inf if upper is None else upper), tol=1e-12).x
    assert f.min() >= 0.0 and (upper is None or f.max() <= upper)
    residual, best = np.linalg.norm(m @ f - target), np.linalg.norm(m @ ref - target)
    assert residual <= best * (1 + 1e-3) + 1e-9


def test_fit_levels_zero_columns_are_off_and_a_bad_target_is_an_error():
    m = banded(50, 10, 2.0, 2)
    m[:, 3] = 0.0
    assert fit_levels(m, m.sum(axis=1) * 0.5)[3] == 0.0
    with pytest.raises(ValueError, match=r"target must have shape \(50,\), got \(49,\)"):
        fit_levels(m, np.ones(49))


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(2, 60), cols=st.integers(1, 30), seed=st.integers(0, 2**32 - 1))
def test_lipschitz_bound_bounds_the_largest_eigenvalue(rows, cols, seed):
    m = np.random.default_rng(seed).uniform(0, 1, (rows, cols))
    top = float(np.linalg.eigvalsh(m.T @ m)[-1])
    assert top <= lipschitz_bound(m) <= 1.06 * top + 1e-12


def test_lipschitz_bound_of_a_zero_matrix_is_one():
    assert lipschitz_bound(np.zeros((4, 3))) == 1.0


def test_live_gain_marks_only_the_dead_gains():
    g = np.array([[1.0, 2.5], [DEAD_PIXEL_GAIN, 49.9]], np.float32)
    out = live_gain(g)
    assert np.isnan(out[1, 0]) and np.array_equal(out[[0, 0, 1], [0, 1, 1]], g[[0, 0, 1], [0, 1, 1]])
    assert g[1, 0] == DEAD_PIXEL_GAIN  # the caller's map is left as it was
    assert live_gain(None) is None
    ones = np.ones((2, 2))
    assert live_gain(ones).dtype == np.float32 and np.array_equal(live_gain(ones), ones)


# ------------------------------------------------------------------------------------- BLAS on one thread

_BLAS_THREADS = ("import json, sys\n"
                 "from threadpoolctl import threadpool_info\n"
                 "from specgpu.core.numerics import one_blas_thread\n"
                 "applied = one_blas_thread()\n"
                 "import scipy.linalg  # a BLAS loaded after the limit\n"
                 "threads = sorted({i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'})\n"
                 "print(json.dumps([applied, threads]))\n")


def _blas_threads(env):
    import json
    import os
    import subprocess
    import sys

    from specgpu.core.numerics import BLAS_THREAD_VARIABLES

    clean = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", _BLAS_THREADS], env={**clean, **env}, capture_output=True, text=True,
                         check=True).stdout
    return json.loads(out)


def test_one_blas_thread_limits_every_blas_of_the_process_unless_the_environment_chose():
    applied, threads = _blas_threads({})
    assert applied is True and threads == [1]
    applied, threads = _blas_threads({"OPENBLAS_NUM_THREADS": "2"})
    assert applied is False and threads == [2]  # the user's choice stands
