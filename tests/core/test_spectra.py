"""Colorimetric tables from colour-science: the XYZ weights of a grid, white points and named data."""

from __future__ import annotations

import colour
import numpy as np
import pytest

from specgpu.core.spectra import DEFAULT_CMFS, OBSERVERS, XYZ_weights, resolve_cmfs, resolve_illuminant_sd, \
    white_point_XYZ

GRID = np.arange(400.0, 701.0, 10.0)


@pytest.mark.parametrize("illuminant", ["D65", "A", "FL2"])
def test_XYZ_weights_equal_colour_sciences_integration(illuminant):
    rng = np.random.default_rng(0)
    R = rng.uniform(0.05, 0.95, (5, GRID.size))
    shape = colour.SpectralShape(400, 700, 10)
    cmfs = colour.MSDS_CMFS[DEFAULT_CMFS].copy().align(shape)
    sd = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape)
    ref = colour.msds_to_XYZ(R, cmfs, sd, method="Integration", shape=shape) / 100.0
    np.testing.assert_allclose(R @ XYZ_weights(GRID, illuminant).T, ref, rtol=1e-9, atol=1e-12)


def test_the_perfect_diffuser_has_Y_one_and_the_white_point_of_its_illuminant():
    W = XYZ_weights(GRID, "D65")
    assert W[1].sum() == pytest.approx(1.0)
    white = white_point_XYZ("D65")
    expected = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS[DEFAULT_CMFS]["D65"])
    np.testing.assert_allclose(white / white[1], expected, rtol=2e-3)


def test_named_weights_are_cached_but_never_shared():
    a = XYZ_weights(GRID, "D65")
    a[:] = 0.0  # a caller writing into its copy does not change the next caller's weights
    assert XYZ_weights(GRID, "D65")[1].sum() == pytest.approx(1.0)


def test_observers_and_unknown_names():
    assert DEFAULT_CMFS in OBSERVERS
    assert resolve_cmfs(DEFAULT_CMFS).shape.interval == 1
    with pytest.raises(ValueError, match="no-such-light"):
        resolve_illuminant_sd("no-such-light")
    with pytest.raises(ValueError, match="no-such-observer"):
        resolve_cmfs("no-such-observer")
