"""colorimetry.cl through specgpu.engine.colorimetry against colour-science, on every device.

Per function, colour-science's four kinds of test: reference values, n-dimensional input, domain (several
illuminants / observers / grids) and NaN / inf behaviour; plus random and edge inputs against the float64
reference with the documented float32 tolerances (Lab 1e-4, CIEDE2000 1e-3 for in-range input).
"""

from __future__ import annotations

from pathlib import Path

import colour
import numpy as np
import pyopencl.array as cla
import pytest
from hypothesis import given
from hypothesis import strategies as st
from reference import (
    XYZ_to_Lab_ref,
    delta_E_ref,
    linear_ref,
    mask_ref,
    near_hue_discontinuity,
    random_Lab,
    reflectance_to_XYZ_ref,
    sharma_pairs,
)

from specgpu.core.spectra import OBSERVERS, XYZ_weights
from specgpu.engine.colorimetry import DELTA_E_METHODS, XYZ_to_Lab, delta_E, frames_to_delta_E, reflectance_to_XYZ

DATA = Path(__file__).resolve().parents[1] / "data"
METHODS = ["CIE 1976", "CIE 1994", "CIE 2000"]
# absolute tolerances: float32 Lab and CIEDE2000 as documented; CIE 1976/1994 relative to the difference
LAB_TOL = 1e-4
DE2000_TOL = 1e-3


def de_tolerance(method, expected):
    return DE2000_TOL if method == "CIE 2000" else 2e-6 * max(1.0, float(np.max(expected)))


# ------------------------------------------------------------------------------------------------- XYZ_to_Lab


@pytest.mark.usefixtures("kernel_variant")  # both kernel variants on every device
class TestXYZ_to_Lab:
    def test_reference_values(self, queue):
        # colour-science's documented example (D65's tabulated chromaticity, CIE 1931 2 degree)
        XYZ = np.array([0.20654008, 0.12197225, 0.05136952])
        xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
        np.testing.assert_allclose(XYZ_to_Lab(XYZ, xy, device=queue), [41.52787529, 52.63858304, 26.92317922],
                                   atol=LAB_TOL)
        # the white of a named illuminant (with no grid: the diffuser over 360-780 nm at 1 nm) maps to
        # L* = 100, a* = b* = 0; black to 0
        white = reflectance_to_XYZ(np.ones(421), np.arange(360.0, 781.0), device=queue)
        np.testing.assert_allclose(XYZ_to_Lab(white, device=queue), [100, 0, 0], atol=LAB_TOL)
        np.testing.assert_allclose(XYZ_to_Lab(np.zeros(3), device=queue), [0, 0, 0], atol=LAB_TOL)

    def test_random_and_edges_vs_colour(self, queue):
        rng = np.random.default_rng(1)
        XYZ = rng.uniform(0, 1.1, (97, 3)).astype(np.float32)
        # the two branches of f(t) and the threshold itself
        t = (24 / 116) ** 3
        XYZ[:6] = [[t, t, t], [t * 0.999, t * 1.001, t], [1e-7, 0, 1e-6], [0.95047, 1.0, 1.08883],
                   [1.2, 1.3, 1.5], [0.0, 0.5, 0.0]]
        np.testing.assert_allclose(XYZ_to_Lab(XYZ, device=queue), XYZ_to_Lab_ref(XYZ), atol=LAB_TOL, rtol=0)

    def test_n_dimensional(self, queue):
        XYZ = np.array([0.20654008, 0.12197225, 0.05136952], np.float32)
        expected = XYZ_to_Lab_ref(XYZ)
        for shape in [(6, 3), (2, 3, 3), (1, 2, 3, 3)]:
            Lab = XYZ_to_Lab(np.broadcast_to(XYZ, shape), device=queue)
            assert Lab.shape == shape and Lab.dtype == np.float32
            np.testing.assert_allclose(Lab, np.broadcast_to(expected, shape), atol=LAB_TOL)

    @pytest.mark.parametrize("illuminant", ["D65", "A", "D50", "E", "FL2"])
    def test_domain_illuminants(self, queue, illuminant):
        rng = np.random.default_rng(2)
        XYZ = rng.uniform(0, 1, (33, 3))
        np.testing.assert_allclose(XYZ_to_Lab(XYZ, illuminant, device=queue), XYZ_to_Lab_ref(XYZ, illuminant),
                                   atol=LAB_TOL)

    def test_domain_white_forms(self, queue):
        XYZ = np.array([[0.3, 0.4, 0.5]])
        xy = np.array([0.34567, 0.35850])
        expected = XYZ_to_Lab_ref(XYZ, xy)
        np.testing.assert_allclose(XYZ_to_Lab(XYZ, xy, device=queue), expected, atol=LAB_TOL)
        np.testing.assert_allclose(XYZ_to_Lab(XYZ, colour.xy_to_XYZ(xy), device=queue), expected, atol=LAB_TOL)
        with pytest.raises(ValueError, match="'D66' has no spectrum"):
            XYZ_to_Lab(XYZ, "D66")
        with pytest.raises(ValueError, match="xy"):
            XYZ_to_Lab(XYZ, [0.3, 0.4, 0.5, 0.6])

    def test_nan_and_inf(self, queue):
        XYZ = np.array([[np.nan, 0.5, 0.5], [0.5, np.inf, 0.5], [-np.inf, 0.5, 0.5], [0.2, 0.3, 0.4]])
        Lab = XYZ_to_Lab(XYZ, device=queue)
        # documented: a non-finite component gives non-finite results in the components it enters
        assert np.isnan(Lab[0, 2]) is np.False_ and np.isnan(Lab[0, 1])  # b* does not use X
        assert not np.all(np.isfinite(Lab[1])) and not np.isfinite(Lab[2, 1])
        np.testing.assert_allclose(Lab[3], XYZ_to_Lab_ref(XYZ[3]), atol=LAB_TOL)
        ref = XYZ_to_Lab_ref(XYZ)
        np.testing.assert_array_equal(np.isfinite(Lab), np.isfinite(ref))

    def test_device_arrays(self, queue):
        XYZ = np.random.default_rng(3).uniform(0, 1, (5, 7, 3)).astype(np.float32)
        Lab = XYZ_to_Lab(cla.to_device(queue, XYZ))
        assert isinstance(Lab, cla.Array) and Lab.shape == (5, 7, 3)
        np.testing.assert_allclose(Lab.get(), XYZ_to_Lab_ref(XYZ), atol=LAB_TOL)

    def test_bad_shape(self, queue):
        with pytest.raises(ValueError, match=r"3 channels on its last axis, got shape \(4, 2\)"):
            XYZ_to_Lab(np.zeros((4, 2)), device=queue)


# ---------------------------------------------------------------------------------------------------- delta_E


@pytest.mark.usefixtures("kernel_variant")  # both kernel variants on every device
class TestDeltaE:
    def test_sharma_2005_pairs(self, queue):
        """The 34 published CIEDE2000 pairs, both argument orders (dE2000 is symmetric)."""
        L1, L2, expected = sharma_pairs(DATA / "ciede2000_sharma2005.csv")
        assert len(expected) == 34
        # published to 4 decimals
        np.testing.assert_allclose(delta_E(L1, L2, "CIE 2000", device=queue), expected, atol=1e-4, rtol=0)
        np.testing.assert_allclose(delta_E(L2, L1, "CIE 2000", device=queue), expected, atol=1e-4, rtol=0)

    def test_reference_values(self, queue):
        # Sharma's pair 25 (published dE00 1.2644), with colour-science 0.4's float64 values for each formula
        Lab_1 = np.array([60.2574, -34.0099, 36.2677])
        Lab_2 = np.array([60.4626, -34.1751, 39.4387])
        assert delta_E(Lab_1, Lab_2, "CIE 1976", device=queue) == pytest.approx(3.1819238, abs=1e-5)
        assert delta_E(Lab_1, Lab_2, "CIE 1994", device=queue) == pytest.approx(1.3909947, abs=1e-5)
        assert delta_E(Lab_1, Lab_2, "CIE 2000", device=queue) == pytest.approx(1.2644200, abs=1e-4)

    @pytest.mark.parametrize("method", METHODS)
    def test_random_vs_colour(self, queue, method):
        rng = np.random.default_rng(4)
        Lab_1 = random_Lab(rng, (40, 25)).astype(np.float32)
        Lab_2 = random_Lab(rng, (40, 25)).astype(np.float32)
        keep = ~near_hue_discontinuity(Lab_1, Lab_2)
        expected = delta_E_ref(Lab_1, Lab_2, method)
        got = delta_E(Lab_1, Lab_2, method, device=queue)
        assert got.shape == (40, 25) and got.dtype == np.float32
        assert np.max(np.abs(got - expected)[keep]) <= de_tolerance(method, expected)

    @pytest.mark.parametrize("method", METHODS)
    def test_edges_vs_colour(self, queue, method):
        """Achromatic colours, pure axes, identical colours, large differences, hues 90 and 270 degrees apart."""
        Lab_1 = np.array([[50, 0, 0], [50, 0, 0], [50, 10, 0], [50, 0, 10], [0, 0, 0], [100, 0, 0],
                          [30, 20, -20], [50, 60, 0], [50, -60, 0], [70, 0.001, -0.001]], np.float64)
        Lab_2 = np.array([[50, 0, 0], [60, 0, 0], [50, 0, 10], [50, -10, 0], [100, 0, 0], [0, 0, 0],
                          [30, 20, -20], [50, 0, 60], [50, 0, -60], [70, -0.001, 0.001]], np.float64)
        expected = delta_E_ref(Lab_1, Lab_2, method)
        got = delta_E(Lab_1, Lab_2, method, device=queue)
        np.testing.assert_allclose(got, expected, atol=de_tolerance(method, expected), rtol=0)
        assert got[0] == 0 and got[6] == 0

    @pytest.mark.parametrize("method", METHODS)
    def test_single_reference_either_side(self, queue, method):
        rng = np.random.default_rng(5)
        image = random_Lab(rng, (9, 11)).astype(np.float32)
        single = np.array([45.0, -12.5, 30.25], np.float32)
        keep = ~near_hue_discontinuity(single, image)
        for a, b in ((single, image), (image, single)):
            expected = delta_E_ref(a, b, method)
            got = delta_E(a, b, method, device=queue)
            assert got.shape == (9, 11)
            assert np.max(np.abs(got - expected)[keep]) <= de_tolerance(method, expected)

    def test_cie1994_reference_is_the_first(self, queue):
        """CIE 1994 weights chroma by the first (reference) colour, as colour-science does: not symmetric."""
        a, b = np.array([50.0, 60.0, 0.0]), np.array([50.0, 10.0, 5.0])
        ab, ba = delta_E(a, b, "CIE 1994", device=queue), delta_E(b, a, "CIE 1994", device=queue)
        assert ab == pytest.approx(delta_E_ref(a, b, "CIE 1994"), abs=1e-4)
        assert ba == pytest.approx(delta_E_ref(b, a, "CIE 1994"), abs=1e-4)
        assert abs(ab - ba) > 1.0

    def test_n_dimensional(self, queue):
        a, b = np.array([60.2574, -34.0099, 36.2677]), np.array([60.4626, -34.1751, 39.4387])
        for shape in [(6, 3), (2, 3, 3), (1, 2, 3, 3)]:
            d = delta_E(np.broadcast_to(a, shape), np.broadcast_to(b, shape), device=queue)
            assert d.shape == shape[:-1]
            np.testing.assert_allclose(d, 1.2644200, atol=1e-4)

    @pytest.mark.parametrize("method", METHODS)
    def test_nan_and_inf(self, queue, method):
        Lab_1 = np.array([[np.nan, 0, 0], [50, np.inf, 0], [50, 10, 10]])
        Lab_2 = np.array([[50, 0, 0], [50, 0, 0], [50, 10, 12]])
        d = delta_E(Lab_1, Lab_2, method, device=queue)
        assert np.isnan(d[0]) and not np.isfinite(d[1])
        assert d[2] == pytest.approx(delta_E_ref(Lab_1[2], Lab_2[2], method), abs=1e-4)

    def test_method_names(self, queue):
        a, b = np.array([50.0, 1, 1]), np.array([50.0, 2, 2])
        assert delta_E(a, b, "cie2000", device=queue) == delta_E(a, b, "CIE 2000", device=queue)
        assert delta_E(a, b, "cie 1976", device=queue) == delta_E(a, b, "CIE 1976", device=queue)
        with pytest.raises(ValueError, match="method='CMC' is not one of 'CIE 1976', 'CIE 1994', 'CIE 2000'"):
            delta_E(a, b, "CMC", device=queue)

    def test_shape_mismatch(self, queue):
        with pytest.raises(ValueError, match="must have the same shape"):
            delta_E(np.zeros((4, 3)), np.zeros((5, 3)), device=queue)

    @given(
        Lab=st.lists(st.tuples(st.floats(0, 100), st.floats(-120, 120), st.floats(-120, 120)), min_size=2,
                     max_size=24),
        method=st.sampled_from(["CIE 1976", "CIE 2000"]),
    )
    def test_symmetric_and_zero_on_the_diagonal(self, Lab, method):
        Lab = np.asarray(Lab, np.float32)
        other = Lab[::-1].copy()
        forward, backward = delta_E(Lab, other, method), delta_E(other, Lab, method)
        assert np.all(forward >= 0)
        keep = ~near_hue_discontinuity(Lab, other, 1e-3)
        np.testing.assert_allclose(forward[keep], backward[keep], atol=1e-3)
        np.testing.assert_array_equal(delta_E(Lab, Lab, method), 0)


# ------------------------------------------------------------------------------------------- reflectance_to_XYZ


class TestReflectanceToXYZ:
    def test_reference_values(self, queue):
        # the perfect reflector gives the white, Y = 1; a flat 0.5 reflector half of it
        wl = np.arange(380, 781, 5)
        white = reflectance_to_XYZ(np.ones(wl.size), wl, device=queue)
        assert white[1] == pytest.approx(1.0, abs=1e-6)
        np.testing.assert_allclose(white, reflectance_to_XYZ_ref(np.ones(wl.size), wl), atol=1e-6)
        np.testing.assert_allclose(reflectance_to_XYZ(np.full(wl.size, 0.5), wl, device=queue), white / 2,
                                   atol=1e-6)

    def test_colorchecker_vs_colour(self, queue):
        sds = list(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values())
        wl = np.arange(400, 701, 10)
        R = np.array([sd.copy().align(colour.SpectralShape(400, 700, 10)).values for sd in sds])
        np.testing.assert_allclose(reflectance_to_XYZ(R, wl, device=queue), reflectance_to_XYZ_ref(R, wl),
                                   atol=1e-5)

    @pytest.mark.parametrize(
        "start, stop, step, illuminant, cmfs",
        [
            (400, 700, 10, "D65", "CIE 1931 2 Degree Standard Observer"),
            (380, 780, 5, "A", "CIE 1931 2 Degree Standard Observer"),
            (400, 700, 5, "D50", "CIE 1964 10 Degree Standard Observer"),
            (360, 830, 1, "D65", "CIE 1931 2 Degree Standard Observer"),
        ],
    )
    def test_domain(self, queue, start, stop, step, illuminant, cmfs):
        wl = np.arange(start, stop + 1, step)
        R = np.random.default_rng(step).uniform(0, 1, (5, 3, wl.size)).astype(np.float32)
        XYZ = reflectance_to_XYZ(R, wl, illuminant, cmfs, device=queue)
        assert XYZ.shape == (5, 3, 3) and XYZ.dtype == np.float32
        np.testing.assert_allclose(XYZ, reflectance_to_XYZ_ref(R, wl, illuminant, cmfs), atol=1e-5)

    def test_81_bands_at_camera_resolution(self, queue):
        """The built-in scenes' 380-780 nm / 5 nm cubes at 320 x 240 (this once overflowed PoCL's stack)."""
        wl = np.arange(380, 781, 5)
        R = np.random.default_rng(81).uniform(0, 1, (240, 320, wl.size)).astype(np.float32)
        XYZ = reflectance_to_XYZ(R, wl, device=queue)
        rows = slice(None, None, 37)
        np.testing.assert_allclose(XYZ[rows], reflectance_to_XYZ_ref(R[rows], wl), atol=1e-5)

    def test_n_dimensional(self, queue):
        wl = np.arange(400, 701, 10)
        R = np.linspace(0.1, 0.9, wl.size)
        expected = reflectance_to_XYZ_ref(R, wl)
        for shape in [(4, wl.size), (2, 2, wl.size), (1, 2, 2, wl.size)]:
            np.testing.assert_allclose(reflectance_to_XYZ(np.broadcast_to(R, shape), wl, device=queue),
                                       np.broadcast_to(expected, (*shape[:-1], 3)), atol=1e-5)

    def test_nan(self, queue):
        wl = np.arange(400, 701, 10)
        R = np.full((2, wl.size), 0.5)
        R[0, 7] = np.nan
        XYZ = reflectance_to_XYZ(R, wl, device=queue)
        assert np.all(np.isnan(XYZ[0])) and np.all(np.isfinite(XYZ[1]))

    def test_bad_wavelengths(self, queue):
        R = np.zeros((4, 31))
        with pytest.raises(ValueError, match="wavelengths has 30 entries but the data has 31 bands"):
            reflectance_to_XYZ(R, np.arange(400, 700, 10))
        with pytest.raises(ValueError, match="evenly spaced"):
            reflectance_to_XYZ(R, np.r_[np.arange(400, 690, 10), 695, 700])
        with pytest.raises(ValueError, match="strictly increasing"):
            reflectance_to_XYZ(R, np.arange(700, 399, -10))
        with pytest.raises(ValueError, match="no spectrum"):
            reflectance_to_XYZ(R, np.arange(400, 701, 10), illuminant="D66")


# -------------------------------------------------------------------------------------------- frames_to_delta_E


def fused_inputs(rng, K=9, shape=(23, 17), B=5):
    frames = rng.integers(0, 1000, (K, *shape), dtype=np.uint16)
    A = rng.uniform(0, 1, (B, K)) / (K * 1023)
    C = rng.uniform(0.2, 1, (3, B))
    C /= C.sum(axis=1, keepdims=True)
    return frames, A, C


@pytest.mark.usefixtures("kernel_variant")  # both kernel variants on every device
class TestFramesToDeltaE:
    @pytest.mark.parametrize("method", METHODS)
    @pytest.mark.parametrize("reference_kind", ["single", "image"])
    def test_vs_colour_chain(self, queue, method, reference_kind):
        rng = np.random.default_rng(9)
        frames, A, C = fused_inputs(rng)
        XYZ = linear_ref(frames, C @ A)
        Lab = XYZ_to_Lab_ref(XYZ)
        reference = (np.array([50.0, 10.0, -5.0]) if reference_kind == "single"
                     else random_Lab(rng, frames.shape[1:])).astype(np.float32)
        keep = ~near_hue_discontinuity(reference, Lab)
        expected = delta_E_ref(reference, Lab, method)
        res = frames_to_delta_E(frames, A, reference, C=C, method=method, return_XYZ=True, return_Lab=True,
                                device=queue)
        np.testing.assert_allclose(res.XYZ, XYZ, atol=1e-5)
        np.testing.assert_allclose(res.Lab, Lab, atol=5e-4)
        assert np.max(np.abs(res.delta_E - expected)[keep]) <= de_tolerance(method, expected)
        assert res.mask is None
        # without intermediates: the dE map alone, the same values (a compiler may contract the two programs'
        # multiply-adds differently, e.g. FMA on a GPU: one float32 ulp of the dE, never more)
        np.testing.assert_allclose(frames_to_delta_E(frames, A, reference, C=C, method=method, device=queue),
                                   res.delta_E, rtol=4e-7, atol=1e-6)

    def test_matrix_already_xyz_dark_gain_mask(self, queue):
        rng = np.random.default_rng(10)
        frames, A, C = fused_inputs(rng, K=6, shape=(31,))
        frames[2, 5] = 1023
        M = C @ A
        dark = rng.uniform(0, 5, frames.shape).astype(np.float32)  # one dark frame per frame
        gain = rng.uniform(0.9, 1.1, frames.shape[1:]).astype(np.float32)
        res = frames_to_delta_E(frames, M, np.array([60.0, 0, 0]), dark=dark, gain=gain, saturation=1023,
                                illuminant="A", method="CIE 2000", return_XYZ=True, return_mask=True,
                                device=queue)
        XYZ = linear_ref(frames, M, dark, gain)
        np.testing.assert_allclose(res.XYZ, XYZ, atol=1e-5)
        np.testing.assert_array_equal(res.mask, mask_ref(frames, 1023))
        expected = delta_E_ref(np.array([60.0, 0, 0]), XYZ_to_Lab_ref(XYZ, "A"), "CIE 2000")
        np.testing.assert_allclose(res.delta_E, expected, atol=DE2000_TOL)

    def test_device_arrays(self, queue):
        rng = np.random.default_rng(12)
        frames, A, C = fused_inputs(rng)
        reference = random_Lab(rng, frames.shape[1:]).astype(np.float32)
        host = frames_to_delta_E(frames, A, reference, C=C, device=queue)
        dev = frames_to_delta_E(cla.to_device(queue, frames), A, cla.to_device(queue, reference), C=C)
        assert isinstance(dev, cla.Array)
        np.testing.assert_array_equal(dev.get(), host)

    def test_nan_frames(self, queue):
        rng = np.random.default_rng(13)
        frames = rng.uniform(0, 1, (3, 4, 4)).astype(np.float32)
        frames[1, 2, 2] = np.nan
        res = frames_to_delta_E(frames, np.eye(3) * 0.5, np.array([50.0, 0, 0]), return_mask=True, device=queue)
        assert np.isnan(res.delta_E[2, 2]) and res.mask[2, 2] == 2
        assert np.isfinite(np.delete(res.delta_E.ravel(), 10)).all()

    @pytest.mark.parametrize(
        "kwargs, message",
        [
            (dict(A=np.ones((3, 8))), "A has 8 columns but frames has K = 9"),
            (dict(A=np.ones((5, 9))), "A has 5 rows, expected 3"),
            (dict(A=np.ones((5, 9)), C=np.ones((3, 4))), "C has 4 columns but A (rows) has K = 5"),
            (dict(A=np.ones((5, 9)), C=np.ones((2, 5))), "C must map the outputs to XYZ"),
            (dict(A=np.ones((3, 9)), reference=np.ones((4, 4, 3))), "reference has shape (4, 4, 3)"),
            (dict(A=np.ones((3, 9)), reference=np.ones(4)), "3 channels on its last axis"),
            (dict(A=np.ones((3, 9)), method="dE2000"), "method='dE2000' is not one of"),
            (dict(A=np.ones((3, 9)), dark=np.ones((2, 23, 17))), "dark has shape (2, 23, 17)"),
        ],
    )
    def test_bad_input(self, queue, kwargs, message):
        frames = np.zeros((9, 23, 17), np.uint16)
        kwargs.setdefault("reference", np.array([50.0, 0, 0]))
        with pytest.raises(ValueError) as error:
            frames_to_delta_E(frames, device=queue, **kwargs)
        assert message in str(error.value)


def test_method_table_lists_colour_science_names():
    assert {"CIE 1976", "CIE 1994", "CIE 2000"} <= set(DELTA_E_METHODS)


# ------------------------------------------------------------------------------- a perfect white through each path

#: every grid kind the package takes: ASTM E308's 1, 5, 10 and 20 nm intervals (one reaching past 360-780 nm), and
#: grids only the rectangle rule takes (7 nm, 2.5 nm); illuminants of each family (daylight, tungsten, equal
#: energy, fluorescent, LED, ISO 7589's 350-690 nm table). Every illuminant colour-science has is checked on
#: every grid on the host (tests/core/test_spectra.py); the device applies whatever white the host gives it.
ASTM_GRIDS = [np.arange(400.0, 701.0, 1.0), np.arange(380.0, 781.0, 5.0), np.arange(400.0, 701.0, 10.0),
              np.arange(400.0, 701.0, 20.0), np.arange(340.0, 831.0, 10.0)]
WHITE_ILLUMINANTS = ["D65", "A", "D50", "E", "FL2", "FL3.1", "LED-B5", "ISO 7589 Photoflood"]
WHITE_CASES = ([(w, "rectangle") for w in [*ASTM_GRIDS, np.arange(403.0, 698.0, 7.0), np.arange(420.0, 680.1, 2.5)]]
               + [(w, "ASTM E308") for w in ASTM_GRIDS])


@pytest.mark.parametrize("observer", OBSERVERS)
@pytest.mark.parametrize("wavelengths, integration", WHITE_CASES,
                         ids=[f"{w[0]:g}-{w[-1]:g}/{w[1] - w[0]:g}-{i}" for w, i in WHITE_CASES])
def test_a_perfect_white_is_Lab_100_0_0_through_every_device_path(queue, wavelengths, integration, observer):
    """The perfect diffuser through reflectance_to_XYZ then XYZ_to_Lab, and as frames through the fused
    frames_to_delta_E (a one-frame decoder giving reflectance 1 in every band, C the XYZ weights): L* = 100,
    a* = b* = 0 within 1e-3 and dE2000 against (100, 0, 0) below 1e-3, each path taking its white from
    white_point_XYZ for the grid and integration its XYZ was made with."""
    B = wavelengths.size
    colours = dict(observer=observer, wavelengths=wavelengths, integration=integration)
    for illuminant in WHITE_ILLUMINANTS:
        XYZ = reflectance_to_XYZ(np.ones((2, B)), wavelengths, illuminant, observer, integration=integration,
                                 device=queue)
        Lab = XYZ_to_Lab(XYZ, illuminant, device=queue, **colours)
        np.testing.assert_allclose(Lab, [[100, 0, 0]] * 2, atol=1e-3, err_msg=illuminant)
        C = XYZ_weights(wavelengths, illuminant, observer, integration=integration)
        fused = frames_to_delta_E(np.ones((1, 2, 2), np.float32), np.ones((B, 1)), np.array([100.0, 0, 0]), C=C,
                                  illuminant=illuminant, return_Lab=True, device=queue, **colours)
        np.testing.assert_allclose(fused.Lab.reshape(-1, 3), [[100, 0, 0]] * 4, atol=1e-3, err_msg=illuminant)
        assert float(fused.delta_E.max()) < 1e-3, illuminant


def test_the_white_of_another_grid_is_not_neutral(queue):
    """What the one white mends: XYZ integrated on 400-700 nm at 10 nm under D65 against the white of another grid
    (360-780 nm at 1 nm, what a name with no grid means) is off neutral by more than the 1e-3 asked of a white."""
    wavelengths = np.arange(400.0, 701.0, 10.0)
    XYZ = reflectance_to_XYZ(np.ones(31), wavelengths, device=queue)
    assert float(np.abs(XYZ_to_Lab(XYZ, device=queue)[1:]).max()) > 0.05
    np.testing.assert_allclose(XYZ_to_Lab(XYZ, wavelengths=wavelengths, device=queue), [100, 0, 0], atol=1e-4)
