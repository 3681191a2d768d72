"""Colorimetric tables from colour-science: the XYZ weights of a grid, white points and named data."""

from __future__ import annotations

import warnings

import colour
import numpy as np
import pytest

from specgpu.core.spectra import (
    DEFAULT_CMFS,
    OBSERVERS,
    WHITE_WAVELENGTHS,
    XYZ_weights,
    resolve_cmfs,
    resolve_illuminant_sd,
    resolve_integration,
    white_point_XYZ,
)
from specgpu.core.validate import BadArgument

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


# ---- one white: the perfect diffuser integrated with the cube's own weights ------------------------------------

#: grids the package takes: 1, 5, 10 and 20 nm (ASTM E308's intervals), one reaching past 360-780 nm, and odd ones
#: only the rectangle rule takes (7 nm, 2.5 nm)
ASTM_GRIDS = [np.arange(400.0, 701.0, 1.0), np.arange(380.0, 781.0, 5.0), np.arange(400.0, 701.0, 10.0),
              np.arange(400.0, 701.0, 20.0), np.arange(340.0, 831.0, 10.0)]
GRIDS = [*ASTM_GRIDS, np.arange(403.0, 698.0, 7.0), np.arange(420.0, 680.1, 2.5)]
ILLUMINANTS = sorted(colour.SDS_ILLUMINANTS)


def grid_id(w):
    return f"{w[0]:g}-{w[-1]:g}/{w[1] - w[0]:g}"


def Lab_of(XYZ, white):
    return colour.XYZ_to_Lab(XYZ, colour.XYZ_to_xy(white))


@pytest.mark.parametrize("observer", OBSERVERS)
@pytest.mark.parametrize("wavelengths", GRIDS, ids=grid_id)
def test_a_perfect_white_is_Lab_100_0_0_under_every_illuminant(wavelengths, observer):
    """The rectangle rule on every grid, under each of colour-science's illuminants, for either observer: the white
    is the sum of the weights, so the perfect diffuser's Lab is (100, 0, 0) (with the tabulated chromaticity it
    was (100, -0.185, 0.120) under D65 on 400-700 nm at 10 nm)."""
    worst = 0.0
    for illuminant in ILLUMINANTS:
        W = XYZ_weights(wavelengths, illuminant, observer)
        white = white_point_XYZ(illuminant, observer, wavelengths=wavelengths)
        np.testing.assert_allclose(white, W.sum(axis=1), rtol=1e-12)
        assert white[1] == pytest.approx(1.0, rel=1e-12)
        worst = max(worst, float(np.abs(Lab_of(W @ np.ones(wavelengths.size), white) - [100, 0, 0]).max()))
    assert worst < 1e-9


@pytest.mark.parametrize("observer", OBSERVERS)
@pytest.mark.parametrize("wavelengths", ASTM_GRIDS, ids=grid_id)
def test_ASTM_E308_equals_colour_sciences_sd_to_XYZ(wavelengths, observer):
    """XYZ_weights(integration="ASTM E308") gives colour-science's sd_to_XYZ(method="ASTM E308") of any reflectance
    (to rounding: within 1e-4 in its 0-100 scale, measured ~1e-13), and its white is its own weights' sum."""
    rng = np.random.default_rng(5)
    R = rng.uniform(0.0, 1.0, (3, wavelengths.size))
    cmfs = colour.MSDS_CMFS[observer]
    for illuminant in ("D65", "A", "FL2"):
        W = XYZ_weights(wavelengths, illuminant, observer, integration="ASTM E308")
        sd = colour.SDS_ILLUMINANTS[illuminant]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            want = np.array([colour.sd_to_XYZ(colour.SpectralDistribution(r, wavelengths), cmfs, sd,
                                              method="ASTM E308") for r in R])
        assert float(np.abs(100.0 * (R @ W.T) - want).max()) < 1e-4
        white = white_point_XYZ(illuminant, observer, wavelengths=wavelengths, integration="astm-e308")
        np.testing.assert_allclose(white, W.sum(axis=1), rtol=1e-12)
        np.testing.assert_allclose(Lab_of(white, white), [100, 0, 0], atol=1e-9)


@pytest.mark.parametrize("wavelengths, why", [
    (np.arange(403.0, 698.0, 7.0), "every 7 nm"),
    (np.arange(405.0, 696.0, 10.0), "starting at 405 nm"),
    (np.arange(400.5, 700.0, 1.0), "starting at 400.5 nm"),
    (np.array([550.0]), "every 0 nm"),
], ids=["7nm", "10nm-off-tenths", "1nm-off-integers", "one-band"])
def test_ASTM_E308_refuses_a_grid_it_has_no_table_for_in_one_line(wavelengths, why):
    with pytest.raises(BadArgument, match="ASTM E308") as error:  # the caller's choice: a usage error
        XYZ_weights(wavelengths, "D65", integration="ASTM E308")
    assert why in str(error.value) and "\n" not in str(error.value)


def test_the_integration_is_named_in_any_case_and_an_unknown_one_lists_the_valid():
    assert resolve_integration("astm e308") == "ASTM E308" and resolve_integration("ASTM-E308") == "ASTM E308"
    assert resolve_integration("Rectangle") == "rectangle"
    with pytest.raises(ValueError, match="integration='simpson' is not one of 'rectangle', 'ASTM E308'"):
        XYZ_weights(GRID, "D65", integration="simpson")


def test_a_white_given_outright_is_used_as_given_and_a_name_needs_a_spectrum():
    np.testing.assert_allclose(white_point_XYZ([0.3127, 0.3290], wavelengths=GRID),
                               colour.xy_to_XYZ([0.3127, 0.3290]))
    np.testing.assert_array_equal(white_point_XYZ(np.array([0.9, 1.0, 1.1])), [0.9, 1.0, 1.1])
    # without a grid: the diffuser on colour-science's default shape, 360-780 nm at 1 nm
    np.testing.assert_allclose(white_point_XYZ("D65"), XYZ_weights(WHITE_WAVELENGTHS, "D65").sum(axis=1))
    with pytest.raises(ValueError, match="'DCI-P3' has no spectrum"):
        white_point_XYZ("DCI-P3")
