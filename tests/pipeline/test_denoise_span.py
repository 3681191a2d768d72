"""Outputs that are linear maps of others (XYZ of the cube or of the coefficients) are not filtered again: the guided
filter run on the outputs' coordinates in their decoder's span (recover's denoising), or on the channels no earlier
channel makes (the motion-compensated decoding: the others made from them), with the same result as filtering every
channel; flagged pixels and their neighbourhood as before."""

from __future__ import annotations

import numpy as np
import pytest
from moving_helpers import MOTION, frames_of, moving_setup

import specgpu.pipeline.denoise as denoise
from specgpu.core.mask import Mask
from specgpu.engine.guided import guided_filter
from specgpu.pipeline.sequence_decoder import SequenceDecoder


@pytest.fixture
def channels_filtered(monkeypatch):
    """The channel count of every image the denoising hands the guided filter (patched where it looks it up)."""
    seen = []
    inner = denoise.guided_filter

    def counting(image, guide, **kw):
        seen.append(np.shape(image)[-1])
        return inner(image, guide, **kw)

    monkeypatch.setattr(denoise, "guided_filter", counting)
    return seen


def outputs_of_a_decoder(h=40, w=56, seed=3):
    """Seven channels and three linear maps of them (as a cube and its XYZ), decoded by rows (10, 9) of rank 7."""
    rng = np.random.default_rng(seed)
    samples = rng.uniform(0.2, 1.0, (h, w, 9)).astype(np.float32)
    samples[:, w // 2:] *= 1.8  # an edge the guide shows
    A = rng.standard_normal((7, 9))
    M = rng.uniform(0.0, 1.0, (3, 7))
    rows = np.vstack([A, M @ A])
    return samples @ rows.T.astype(np.float32), samples.sum(axis=-1), rows


def test_filtering_in_the_span_equals_filtering_every_channel(channels_filtered):
    y, guide, rows = outputs_of_a_decoder()
    g = guide / np.percentile(guide, 99)
    span = denoise.column_span(rows)
    assert span.shape == (10, 7)
    got = denoise.filter_in_span(y, g, span, radius=2, eps=1e-4)
    assert channels_filtered == [7]
    want = guided_filter(y, g, radius=2, eps=1e-4)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5 * np.abs(want).max())
    # the derived channels stay the same linear map of the others
    np.testing.assert_allclose(got[..., 7:], got[..., :7] @ (rows[7:] @ np.linalg.pinv(rows[:7])).T, rtol=1e-3,
                               atol=1e-4 * np.abs(got).max())


def test_the_compensated_denoising_in_the_span_keeps_flagged_pixels_and_their_neighbours(channels_filtered):
    y, guide, rows = outputs_of_a_decoder(seed=4)
    mask = np.zeros(guide.shape, np.uint8)
    mask[20, 10] = Mask.SATURATED
    y[5, 40] = np.nan  # a pixel with no value
    before = y.copy()
    got = denoise.denoise_compensated(y, guide, mask, radius=2, eps=1e-4, rows=rows)
    want = denoise.denoise_compensated(y, guide, mask, radius=2, eps=1e-4)
    np.testing.assert_array_equal(y, before)  # the outputs handed in are not written to
    assert channels_filtered == [7, 10]
    # the channels kept are filtered as they are: the same as filtering them alone, bit for bit
    alone = denoise.denoise_compensated(y[..., :7], guide, mask, radius=2, eps=1e-4)
    np.testing.assert_array_equal(got[..., :7], alone)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(got[5, 40]).all()
    # the pixels whose filter would read a flagged one keep their decoded values, bit for bit
    np.testing.assert_array_equal(got[20, 6:15], y[20, 6:15])
    np.testing.assert_allclose(np.nan_to_num(got), np.nan_to_num(want), rtol=2e-4,
                               atol=2e-5 * np.nanmax(np.abs(want)))


def test_the_motion_compensated_decoder_filters_xyz_as_the_cubes_map(channels_filtered, monkeypatch):
    desc, bundle, plan, scene = moving_setup()
    frames, _ = frames_of(desc, plan, scene, MOTION)
    decoder = SequenceDecoder(plan, bundle, ("cube", "XYZ", "dE"), reference=(50.0, 0.0, 0.0), motion="global",
                              denoise=(2, 1e-4))
    got = decoder.maps(frames)
    B = plan.A.shape[0]
    assert channels_filtered == [B]  # the cube's 7 bands; XYZ is their map, not 3 channels more

    def every(rows):  # every channel through the filter
        return np.arange(len(rows)), np.zeros(0, np.intp), np.zeros((0, len(rows)))

    monkeypatch.setattr(denoise, "derived_channels", every)
    want = decoder.maps(frames)
    assert channels_filtered == [B, B + 3]
    for name in ("cube", "XYZ", "dE"):
        a, b = got[name], want[name]
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), rtol=1e-3, atol=1e-4 * np.nanmax(b))
    assert np.isfinite(got["XYZ"]).mean() > 0.5


def test_a_channel_is_made_from_others_only_where_that_keeps_its_rounding():
    rng = np.random.default_rng(9)
    A = rng.standard_normal((4, 6))
    M = rng.uniform(0.0, 1.0, (3, 4))
    kept, others, L = denoise.derived_channels(np.vstack([A, M @ A]))
    assert kept.tolist() == [0, 1, 2, 3] and others.tolist() == [4, 5, 6]
    np.testing.assert_allclose(L, M, atol=1e-12)
    # a row in the span only through near-collinear rows (a difference 1e-4 of their size) is filtered itself
    near = np.vstack([A[0], A[0] + 1e-4 * A[1], A[1]])
    kept, others, _ = denoise.derived_channels(near)
    assert kept.tolist() == [0, 1, 2] and others.size == 0
    # a row outside the span of the earlier ones is filtered, and so is a later combination of it
    kept, others, L = denoise.derived_channels(np.vstack([A[:2], A[0] + A[1], A[2], A[2] - A[0]]))
    assert kept.tolist() == [0, 1, 3] and others.tolist() == [2, 4]
    np.testing.assert_allclose(L, [[1, 1, 0], [-1, 0, 1]], atol=1e-12)
