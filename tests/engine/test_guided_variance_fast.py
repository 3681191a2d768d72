"""The guided filter's variance from its windows' running sums (kernels/guided_variance.cl: each weight a polynomial
in the two pixels' guide values, its coefficients prefix and suffix sums over the pixel's windows, eight pixels of a
row at once inside the image, one at a time at the borders) against the float64 reference written window by window:
every radius carried, a textured guide with an edge, pixels with no own variance, a NaN total, flagged pixels,
images narrower than the windows."""

from __future__ import annotations

import numpy as np
import pytest
from guided_variance_helpers import reference_filtered_variance

from specgpu.core.mask import Mask
from specgpu.engine.guided_variance import MAX_RADIUS, box_box_squares, filtered_variance


def textured(h, w, seed):
    """A guide with texture at several scales, a strong edge and noise, on the scale ``--denoise`` gives its guide."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    g = 0.5 + 0.2 * np.sin(xx / 2.3) * np.cos(yy / 3.1) + 0.3 * (xx > w // 2) + rng.normal(0, 0.02, (h, w))
    return g


def case(h, w, C, D, seed):
    rng = np.random.default_rng(seed)
    guide = textured(h, w, seed)
    own = rng.uniform(0.1, 2.0, (h, w, C))
    total = own + rng.uniform(0.0, 1.0, own.shape)
    slopes = rng.standard_normal((h, w, D)) * 0.3 + guide[..., None]
    guide_var = rng.uniform(0.0, 1e-3, (h, w))
    terms = [[(c % D, c % D, 1.0)] if c % 2 == 0 else [(0, D - 1, 0.5), (D - 1, D - 1, 0.5)] for c in range(C)]
    return guide, own, total, slopes, guide_var, terms


def compare(guide, own, total, slopes, guide_var, terms, radius, eps=1e-4, mask=None, bits=0, offsets=None,
            sqrt=False):
    got = filtered_variance(own, total, guide, radius=radius, eps=eps, slopes=slopes, guide_var=guide_var,
                            terms=terms, offsets=offsets, sqrt=sqrt, mask=mask, mask_bits=bits)
    want = reference_filtered_variance(own, total, guide, radius, eps, slopes, guide_var, terms, offsets, sqrt,
                                       mask, bits)
    assert got.dtype == np.float32 and got.shape == own.shape
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(np.nan_to_num(got), np.nan_to_num(want), rtol=3e-5, atol=1e-7)
    return got, want


@pytest.mark.parametrize("radius", range(1, MAX_RADIUS + 1))
@pytest.mark.parametrize("channels", [1, 3])
def test_every_radius_on_a_textured_guide_equals_the_float64_reference(radius, channels):
    # wide enough for whole rows of eight interior pixels at radius 4 (columns 8 .. 36) and border pixels about them
    h, w = 4 * radius + 9, 45
    guide, own, total, slopes, guide_var, terms = case(h, w, channels, 2, radius * 10 + channels)
    got, want = compare(guide, own, total, slopes, guide_var, terms, radius)
    # the texture and the edge make the weights follow the guide: far from the mean of box means (a flat guide)
    flat, _ = compare(np.ones((h, w)), own, total, slopes, guide_var, terms, radius)
    assert np.max(np.abs(got - flat) / flat) > 0.1


@pytest.mark.parametrize("radius", [2, 4])
def test_no_own_variance_a_nan_total_and_flagged_pixels_inside_and_at_the_borders(radius):
    h, w = 4 * radius + 11, 48
    guide, own, total, slopes, guide_var, terms = case(h, w, 3, 3, radius)
    y = h // 2
    own[y, 20, 0] = np.nan  # inside: adds nothing to its neighbours
    own[0, 0, 1] = np.inf  # a corner
    total[y, 27, 2] = np.nan  # stays NaN, its own part not spread
    total[h - 1, w - 2, 0] = np.nan
    mask = np.zeros((h, w), np.uint8)
    mask[y + 1, 17] = Mask.SATURATED  # inside, among the bits asked
    mask[1, w - 1] = Mask.SATURATED  # at a border
    mask[y - 1, 30] = Mask.OUTSIDE  # not among the bits asked: spread as any pixel
    offsets = np.array([0.1, 0.0, 0.3])
    for sqrt in (False, True):
        got, _ = compare(guide, own, total, slopes, guide_var, terms, radius, mask=mask, bits=int(Mask.SATURATED),
                         offsets=offsets, sqrt=sqrt)
        assert np.isnan(got[y, 27, 2]) and np.isnan(got[h - 1, w - 2, 0])
        assert np.isfinite(got[y, 20, 0]) and np.isfinite(got[0, 0, 1])
    # without the mask the saturated pixels' own parts reach their neighbours (within 2 radius)
    unmasked, _ = compare(guide, own, total, slopes, guide_var, terms, radius, offsets=offsets)
    masked, _ = compare(guide, own, total, slopes, guide_var, terms, radius, mask=mask, bits=int(Mask.SATURATED),
                        offsets=offsets)
    changed = np.any(unmasked != masked, axis=-1)  # beyond 2 radius the sums are the same, term for term
    assert changed[y + 1, 17 + 2 * radius] and not changed[y + 1, 17 + 2 * radius + 1]


@pytest.mark.parametrize("shape", [(3, 5), (9, 7), (6, 40), (40, 6)])
def test_images_narrower_than_the_windows(shape):
    h, w = shape
    guide, own, total, slopes, guide_var, terms = case(h, w, 2, 2, h * w)
    for radius in (2, MAX_RADIUS):
        compare(guide, own, total, slopes, guide_var, terms, radius)


def test_a_flat_guide_inside_leaves_the_box_box_variance():
    h, w, r = 24, 48, 2
    v = np.full((h, w, 1), 2.0)
    z = np.zeros((h, w, 1))
    got = filtered_variance(v, v, np.full((h, w), 0.7), radius=r, eps=1e-4, slopes=z, guide_var=z[..., 0],
                            terms=[[]])[..., 0]
    want = 2.0 * box_box_squares(r).sum() ** 2
    np.testing.assert_allclose(got[2 * r:h - 2 * r, 2 * r:w - 2 * r], want, rtol=1e-5)
