"""Property tests of the validators: valid input passes normalised, invalid input gets a one-line message."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from specgpu.core.validate import (
    check_band_wavelengths,
    check_frames,
    check_last_axis,
    check_matrix,
    validate_method,
)

METHODS = {"CIE 1976": 76, "CIE 1994": 94, "CIE 2000": 2000}


@given(st.sampled_from(list(METHODS)), st.booleans())
def test_validate_method_is_case_insensitive(name, upper):
    assert validate_method(name.upper() if upper else name.lower(), METHODS) == METHODS[name]


@given(st.text(max_size=12).filter(lambda t: t.lower() not in {m.lower() for m in METHODS}))
def test_validate_method_lists_the_valid_names(name):
    with pytest.raises(ValueError) as error:
        validate_method(name, METHODS)
    assert "'CIE 1976', 'CIE 1994', 'CIE 2000'" in str(error.value)


@given(hnp.arrays(st.sampled_from([np.uint8, np.uint16, np.float32, np.float64]),
                  hnp.array_shapes(min_dims=2, max_dims=4, min_side=1, max_side=5),
                  elements={"min_value": 0, "max_value": 255}))
def test_check_frames_accepts_and_normalises(frames):
    out, K = check_frames(frames)
    assert K == frames.shape[0] and out.shape == frames.shape
    assert out.dtype == (np.float32 if frames.dtype == np.float64 else frames.dtype)
    assert out.flags.c_contiguous


@given(hnp.arrays(st.sampled_from([np.int8, np.int32, np.int64, np.uint32, np.complex64, np.bool_]),
                  hnp.array_shapes(min_dims=2, max_dims=3, max_side=3)))
def test_check_frames_refuses_other_dtypes(frames):
    with pytest.raises(TypeError, match=f"frames has dtype {frames.dtype}"):
        check_frames(frames)


@given(rows=st.integers(1, 6), cols=st.integers(1, 6), K=st.integers(1, 6))
def test_check_matrix_columns(rows, cols, K):
    A = np.ones((rows, cols))
    if cols == K:
        assert check_matrix(A, columns=K).dtype == np.float32
    else:
        with pytest.raises(ValueError, match=f"A has {cols} columns but frames has K = {K} frames"):
            check_matrix(A, columns=K)


@given(hnp.arrays(np.float64, (3, 4), elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_check_matrix_refuses_non_finite(A):
    if np.all(np.isfinite(A)) and np.max(np.abs(A)) <= np.finfo(np.float32).max:
        check_matrix(A)
    else:
        with pytest.raises(ValueError):
            check_matrix(A)


@given(start=st.floats(300, 500), step=st.floats(0.5, 20), n=st.integers(2, 80))
def test_check_wavelengths_even_grids_pass(start, step, n):
    w = start + step * np.arange(n)
    np.testing.assert_array_equal(check_band_wavelengths(w, n), w)


@given(n=st.integers(3, 40), where=st.integers(0, 1000), shift=st.floats(0.1, 0.4))
def test_check_wavelengths_uneven_grids_fail(n, where, shift):
    w = 400 + 10.0 * np.arange(n)
    w[1 + where % (n - 2)] += shift * 10
    with pytest.raises(ValueError, match="evenly spaced"):
        check_band_wavelengths(w, n)


@given(hnp.array_shapes(min_dims=1, max_dims=4, max_side=4), st.integers(1, 5))
def test_check_last_axis(shape, size):
    a = np.zeros(shape)
    if shape[-1] == size:
        assert check_last_axis(a, "Lab", size).dtype == np.float32
    else:
        with pytest.raises(ValueError, match=f"Lab must have {size} channels on its last axis"):
            check_last_axis(a, "Lab", size)


def test_float64_frames_beyond_float32_are_refused():
    with pytest.raises(ValueError, match="frames has values beyond float32 range"):
        check_frames(np.full((2, 2, 2), 1e300))
