"""register_gradients' keywords for a caller that knows more: a start (no coarse search), a row stride at full
resolution, a pyramid level read back, the coarse candidates and their rival ratio; bad values refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from specgpu.engine.gradients import gradient_images
from specgpu.engine.registration import register_gradients

H, W = 120, 160
SHIFTS = np.array([[-3.35, 1.6], [-1.1, 0.7], [0.0, 0.0], [0.45, -0.9], [2.3, -1.55]])


@pytest.fixture(scope="module")
def images():
    """Gradient images (device) of a textured scene seen by frame k at x + SHIFTS[k] (frame 2 the reference)."""
    rng = np.random.default_rng(7)
    m = 24
    base = ndimage.gaussian_filter(rng.normal(size=(H + 2 * m, W + 2 * m)), 2.0) * 400 + 1000
    frames = np.stack([ndimage.shift(base, (dy, dx), order=3, mode="nearest")[m:m + H, m:m + W]
                       for dx, dy in SHIFTS]).astype(np.float32)
    return gradient_images(frames)


def test_candidates_and_their_rival_ratio_come_with_the_search(images):
    got = register_gradients(images, 2)
    assert got.usable.all()
    np.testing.assert_allclose(got.shifts, SHIFTS, atol=0.05)
    assert len(got.candidates) == 5 and len(got.candidates[2]) == 0 and np.isnan(got.rival[2])
    for k in (0, 1, 3, 4):
        c = got.candidates[k]
        assert c.shape[1] == 3 and np.all(np.diff(c[:, 2]) <= 0)  # highest first
        assert np.abs(c[0, :2] - SHIFTS[k]).max() < 4.0  # the best within a coarse pixel of the truth
        assert 0.0 <= got.rival[k] < 1.0
    assert not got.edge.any()


def test_a_start_skips_the_search_and_a_finer_start_level_gives_the_same_shifts(images):
    full = register_gradients(images, 2)
    start = np.rint(SHIFTS)
    for level in (None, 1, 0):
        got = register_gradients(images, 2, start=start, start_level=level)
        assert got.usable.all() and all(len(c) == 0 for c in got.candidates)
        np.testing.assert_allclose(got.shifts, full.shifts, atol=0.02)
    lost = start.copy()
    lost[4] = np.nan  # a NaN start: that frame is not registered
    got = register_gradients(images, 2, start=lost)
    assert got.usable.tolist() == [True, True, True, True, False] and np.isnan(got.shifts[4]).all()


def test_every_other_row_at_full_resolution_registers_as_closely(images):
    got = register_gradients(images, 2, full_rows=2, full_iterations=2)
    np.testing.assert_allclose(got.shifts, SHIFTS, atol=0.05)


def test_a_level_is_read_back_when_asked(images):
    got = register_gradients(images, 2, keep_level=1)
    assert got.level.shape == (5, H // 2, W // 2)
    np.testing.assert_allclose(got.level.mean(axis=(1, 2)), images.get().mean(axis=(1, 2)), rtol=0.02)
    assert register_gradients(images, 2).level is None


@pytest.mark.parametrize("kw, message", [({"start": np.zeros((4, 2))}, "start must be"),
                                         ({"start": np.zeros((5, 2)), "start_level": 9}, "start_level must be"),
                                         ({"full_rows": 0}, "full_rows and full_iterations"),
                                         ({"keep_level": 0}, "keep_level must be"),
                                         ({"choose": lambda c, g: np.zeros((2, 2))}, "choose must return")])
def test_bad_values_are_refused_in_one_line(images, kw, message):
    with pytest.raises(ValueError, match=message):
        register_gradients(images, 2, **kw)
