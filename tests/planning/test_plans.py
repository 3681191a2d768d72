"""Plans: every method's patterns and decoder, checked on the noise-free twin and against NumPy from the twin's
own physics (light column matrix, camera responsivity), not from the planner's model."""

from dataclasses import replace

import colour
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.calibration.bundle import oracle_calibration
from specgpu.engine.linear_map import apply_linear
from specgpu.planning import (
    PLAN_METHODS,
    Plan,
    load_plan,
    make_plan,
    save_plan,
)
from specgpu.planning.basis import COLORCHECKER_24_SETS, load_reflectances, pca_basis
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.light import LightParameters
from specgpu.rig.scene import SpectralScene, interpolation_matrix
from specgpu.rig.twin import TwinRig

H, W = 240, 320  # the camera's smallest ROI
DESC = RigDescription(camera=CameraParameters(roi_width=W, roi_height=H))


@pytest.fixture(scope="module")
def bundle():
    return oracle_calibration(DESC)


@pytest.fixture(scope="module")
def basis():
    return pca_basis(load_reflectances(exclude=COLORCHECKER_24_SETS))


@pytest.fixture(scope="module")
def twin():
    """The twin's ground-truth physics, for independent computations."""
    return TwinRig(DESC, scene="white")


def noise_free(plan, reflectance, wavelengths):
    """Noise-free frames (K, H, W) of a uniform scene photographed with the plan at its exposure."""
    refl = np.broadcast_to(np.asarray(reflectance, np.float32), (H, W, len(wavelengths)))
    d = plan.rig_description(DESC)
    assert d.camera.exposure_s == plan.exposure_s and d.camera.frame_rate_hz <= DESC.camera.frame_rate_hz
    rig = TwinRig(d, scene=SpectralScene(np.asarray(wavelengths, float), refl))
    rig.load_sequence(plan.patterns)
    return np.stack([rig.expected_frame(k) for k in range(plan.K)])


def recover(plan, bundle, frames):
    return apply_linear(frames, plan.A, bundle.dark_at(plan.exposure_s), bundle.flat_field)


def physics_F(twin, plan, wavelengths):
    """(K, B) DN above dark per unit reflectance at ``wavelengths``, from the twin's light and camera directly."""
    light, cam = twin.light, twin.camera
    e = light.pattern_to_spectrum(plan.patterns)  # (K, G) W m^-2 nm^-1
    r = cam.responsivity(light.wavelengths) / cam.params.gain_e_per_dn
    return plan.exposure_s * (e * r) @ interpolation_matrix(light.wavelengths, np.asarray(wavelengths, float))


def test_unknown_method_lists_the_valid_ones(bundle):
    with pytest.raises(ValueError, match="valid methods: narrowband, reciprocal, biased, symmetric, tristimulus, "
                                         "camera, steady, optimal, hadamard$"):
        make_plan("wiener", bundle)


@pytest.mark.parametrize("step, count", [(10.0, 31), (5.0, 61)])
def test_narrowband_decoder_is_one_over_c(bundle, twin, step, count):
    plan = make_plan("narrowband", bundle, step_nm=step)
    assert plan.K == count and plan.output == "reflectance"
    np.testing.assert_allclose(plan.output_wavelengths, np.arange(400, 700.1, step))
    # Each band lights exactly the columns within half a step of its centre, every mirror on.
    cw = twin.light.column_wavelengths
    for k, c in enumerate(plan.output_wavelengths):
        np.testing.assert_array_equal(plan.patterns[k], np.where(np.abs(cw - c) < step / 2, 768, 0))
    c_i = physics_F(twin, plan, [380.0, 780.0]).sum(axis=1)  # eq. (3): response to a flat reflectance of 1
    np.testing.assert_allclose(plan.A, np.diag(1.0 / c_i), rtol=1e-9)


def test_narrowband_parameters(bundle):
    plan = make_plan("narrowband", bundle, centres=[450.0, 550.0, 650.0], bandwidth_nm=20.0)
    assert plan.K == 3 and plan.params["bandwidth_nm"] == 20.0
    assert all(np.count_nonzero(p) in (51, 52) for p in plan.patterns)  # 20 nm / 0.39 nm per column
    with pytest.raises(ValueError, match="strictly increasing"):
        make_plan("narrowband", bundle, centres=[500.0, 450.0])
    with pytest.raises(ValueError, match="holds no DMD column"):
        make_plan("narrowband", bundle, centres=[300.0])


def test_narrowband_recovers_smooth_spectra_at_band_centres(bundle):
    wl = np.arange(380.0, 781.0, 5.0)
    smooth = 0.45 + 0.25 * np.sin((wl - 380) / 60.0)
    for step in (10.0, 5.0):
        plan = make_plan("narrowband", bundle, step_nm=step)
        y = recover(plan, bundle, noise_free(plan, smooth, wl))
        truth = np.interp(plan.output_wavelengths, wl, smooth)
        err = np.abs(y - truth).max()
        assert err < 0.004, (step, err)


def test_reciprocal_frames_read_the_reflectance(bundle, twin):
    plan = make_plan("reciprocal", bundle)
    d = np.diag(plan.A)
    np.testing.assert_allclose(plan.A, np.diag(d))
    np.testing.assert_allclose(d, 1.0 / physics_F(twin, plan, [380.0, 780.0]).sum(axis=1), rtol=1e-9)
    np.testing.assert_allclose(d, d.mean(), rtol=0.01)  # equal bands: A is a multiple of I
    # On a white, every band gives the same frame.
    wl = np.array([380.0, 780.0])
    frames = noise_free(plan, [0.8, 0.8], wl) - bundle.dark_at(plan.exposure_s)
    centre = frames[:, H // 2, W // 2]
    np.testing.assert_allclose(centre, centre.mean(), rtol=0.01)
    # Shaped as 1/V inside each band: a column's level times its response is the same across the band.
    k = plan.K // 2
    cols = np.flatnonzero(plan.patterns[k])
    q = bundle.system_matrix.sum(axis=0)[cols]
    resp = q * plan.patterns[k, cols]
    assert np.abs(plan.patterns[k, cols] - resp.mean() / q).max() <= 1.0  # 1/V up to mirror rounding


@pytest.mark.parametrize("method, frames", [("biased", 6), ("symmetric", 9)])
def test_basis_methods_recover_in_span_spectra_to_float_precision(bundle, basis, method, frames):
    plan = make_plan(method, bundle, basis, m=5)
    assert plan.K == frames
    rng = np.random.default_rng(3)
    for _ in range(3):
        sigma = np.r_[rng.uniform(1.5, 3.0), rng.uniform(-0.4, 0.4, 4)]
        s = basis.first(5) @ sigma
        s = np.clip(s, 0.0, None) if s.min() < 0 else s
        s = basis.project(s, 5)
        if s.min() < 0:
            continue
        y = recover(plan, bundle, noise_free(plan, s, basis.wavelengths))
        assert np.abs(y - s).max() < 5e-6 * max(1.0, s.max())


@pytest.mark.parametrize("method", ["biased", "symmetric"])
def test_basis_decoder_against_numpy(bundle, basis, twin, method):
    m = 5
    plan = make_plan(method, bundle, basis, m=m)
    phi = basis.first(m)
    F = physics_F(twin, plan, basis.wavelengths)  # independent of the planner's model
    # The decoder is a left inverse on the span: A F Phi = Phi.
    np.testing.assert_allclose(plan.A @ F @ phi, phi, atol=1e-9)
    # And it is the paper's combination (sigma_j = O_j+/a - O_j-/a, or O_j/a - K O_K/a) up to the small
    # correction of non-ideal frames: compare with Phi D built here from the frames' realized scales.
    parts = []
    if method == "symmetric":
        for j in range(m):
            for sign in (1.0, -1.0):
                part = np.clip(sign * phi[:, j], 0, None)
                if np.any(part > 0):
                    parts.append((j, sign, part))
    else:
        bias = max(0.0, (-phi).max())
        parts = [(j, 1.0, phi[:, j] + bias) for j in range(m)] + [(None, -bias, np.ones(phi.shape[0]))]
    assert len(parts) == plan.K
    D = np.zeros((m, plan.K))
    for k, (j, sign, part) in enumerate(parts):
        # Each frame realizes its target: I V proportional to the basis part, within the slit's blur. Samples
        # within 10 nm of the range ends are left out: no 5 nm band can follow the step to zero at 400 / 700 nm
        # (and the end samples carry only half a trapezoid).
        inner = slice(3, -3)
        a = F[k][inner] @ part[inner] / (part[inner] @ part[inner])
        assert np.linalg.norm((F[k] - a * part)[inner]) / np.linalg.norm((a * part)[inner]) < 0.03
        if j is None:
            D[:, k] = sign / a
        else:
            D[j, k] = sign / a
    # The correction (D F Phi)^-1 is small: it mostly undoes the frames' deviation at the 700 nm edge.
    assert np.linalg.norm(plan.A - phi @ D) / np.linalg.norm(phi @ D) < 0.10  # measured: biased < 0.05, symmetric 0.08


def test_basis_plan_refuses_a_centred_basis(bundle):
    centred = pca_basis(load_reflectances(["PMC", "CIE 1995 TCS"]), centred=True)
    with pytest.raises(ValueError, match="uncentred basis"):
        make_plan("symmetric", bundle, centred)


def _sd_to_XYZ(values, wl, illuminant, cmfs="CIE 1931 2 Degree Standard Observer"):
    """colour-science's XYZ over the light's range (observer trimmed to 380-780 nm), Y = 1 for the white."""
    c = colour.MSDS_CMFS[cmfs].copy().trim(colour.SpectralShape(380, 780, 1))
    sd = colour.SpectralDistribution(dict(zip(wl, values)))
    ill = colour.SDS_ILLUMINANTS[illuminant]
    return colour.sd_to_XYZ(sd, c, ill, method="Integration") / 100.0


@pytest.mark.parametrize("illuminant", ["D65", "A"])
def test_tristimulus_gives_colour_science_XYZ_in_span(bundle, basis, illuminant):
    plan = make_plan("tristimulus", bundle, illuminant=illuminant, correction="span", basis=basis, m=3)
    assert plan.K == 3 and plan.output == "XYZ" and plan.A.shape == (3, 3)
    wl = bundle.wavelengths  # 1 nm, 380-780: the spectrum is defined where colour integrates it
    phi = interpolation_matrix(wl, basis.wavelengths) @ basis.first(3)
    for sigma in ([2.2, 0.3, -0.2], [1.5, -0.4, 0.3]):
        s = phi @ np.array(sigma)
        assert s.min() > 0
        y = recover(plan, bundle, noise_free(plan, s, wl))[H // 2, W // 2]
        np.testing.assert_allclose(y, _sd_to_XYZ(s, wl, illuminant), rtol=2e-5)


def test_tristimulus_diagonal_decoder(bundle, twin):
    plan = make_plan("tristimulus", bundle, illuminant="D65")
    np.testing.assert_allclose(plan.A, np.diag(np.diag(plan.A)))  # the paper's A = diag(k)
    wl = bundle.wavelengths
    F = physics_F(twin, plan, wl)
    white = colour.sd_to_XYZ(colour.SpectralDistribution(dict(zip(wl, np.ones(wl.size)))),
                             colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().trim(
                                 colour.SpectralShape(380, 780, 1)), colour.SDS_ILLUMINANTS["D65"],
                             method="Integration") / 100
    np.testing.assert_allclose(np.diag(plan.A), white / F.sum(axis=1), rtol=1e-9)
    # Each frame is E_T times a colour-matching function, divided by V (eq. (10)).
    cm = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    e = np.interp(wl, colour.SDS_ILLUMINANTS["D65"].wavelengths, colour.SDS_ILLUMINANTS["D65"].values)
    for k in range(3):
        want = e * np.interp(wl, cm.wavelengths, cm.values[:, k])
        a = F[k] @ want / (want @ want)
        assert np.linalg.norm(F[k] - a * want) / np.linalg.norm(a * want) < 0.01
    # Natural spectra: close to colour-science even without the span correction.
    s = 0.3 + 0.5 * np.exp(-0.5 * ((wl - 600) / 50) ** 2)
    y = recover(plan, bundle, noise_free(plan, s, wl))[H // 2, W // 2]
    np.testing.assert_allclose(y, _sd_to_XYZ(s, wl, "D65"), rtol=3e-3)


def test_camera_simulator(bundle, basis, twin):
    plan = make_plan("camera", bundle, camera="Nikon 5100 (NPL)", illuminant="D65")
    assert plan.output == "RGB" and plan.K == 3 and plan.A.shape == (3, 3)
    wl = bundle.wavelengths
    y = recover(plan, bundle, noise_free(plan, np.ones(wl.size) * 0.5, wl))[H // 2, W // 2]
    assert y[1] == pytest.approx(0.5, rel=1e-5)  # G = 1 for the perfect white
    # A response with a negative lobe takes two frames for that channel (symmetric split), and the span
    # correction makes it exact in the span.
    lobes = np.stack([np.exp(-0.5 * ((wl - 450) / 30) ** 2),
                      np.exp(-0.5 * ((wl - 550) / 30) ** 2) - 0.3 * np.exp(-0.5 * ((wl - 470) / 20) ** 2),
                      np.exp(-0.5 * ((wl - 620) / 30) ** 2)], axis=1)
    msds = colour.MultiSpectralDistributions(lobes, wl, labels=["r", "g", "b"], name="lobes")
    plan = make_plan("camera", bundle, camera=msds, illuminant="E", correction="span", basis=basis, m=3)
    assert plan.K == 4
    phi = interpolation_matrix(wl, basis.wavelengths) @ basis.first(3)
    s = phi @ np.array([2.0, 0.3, -0.1])
    y = recover(plan, bundle, noise_free(plan, s, wl))[H // 2, W // 2]
    e = np.interp(wl, colour.SDS_ILLUMINANTS["E"].wavelengths, colour.SDS_ILLUMINANTS["E"].values)
    want = (s * e) @ lobes / ((e * lobes[:, 1]).sum())
    np.testing.assert_allclose(y, want, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="unknown camera"):
        make_plan("camera", bundle, camera="Canon 1D")


def test_steady_state_emits_the_target(bundle, twin):
    plan = make_plan("steady", bundle, spectrum="D65")
    assert plan.K == 1
    emitted = twin.light.pattern_to_spectrum(plan.patterns[0])
    target = plan.target_spectra[0]
    sel = (bundle.wavelengths >= 400) & (bundle.wavelengths <= 730)
    assert np.sqrt(np.mean((emitted - target)[sel] ** 2)) / target[sel].max() < 0.02
    assert plan.patterns.max() == 768  # as bright as the lamp allows
    np.testing.assert_allclose(plan.A, [[1.0 / physics_F(twin, plan, [380.0, 780.0]).sum()]], rtol=1e-9)


ALL = [("narrowband", {}), ("reciprocal", {}), ("biased", {"m": 5}), ("symmetric", {"m": 5}),
       ("tristimulus", {"illuminant": "A"}), ("camera", {}), ("steady", {"spectrum": "D65"})]


@pytest.mark.parametrize("method, kw", ALL)
def test_plans_respect_the_light_and_camera_limits(bundle, basis, method, kw):
    args = (basis,) if method in ("biased", "symmetric") else ()
    plan = make_plan(method, bundle, *args, **kw)
    assert method in PLAN_METHODS
    assert plan.patterns.dtype == np.int32
    assert plan.patterns.min() >= 0 and plan.patterns.max() <= 768
    assert plan.exposure_s >= 80e-6
    assert np.all(plan.expected_level <= 0.9 + 1e-9) and plan.expected_level.max() > 0.02
    assert plan.calibration == bundle.hash


def test_exposure_is_chosen_to_use_the_range(bundle):
    plan = make_plan("tristimulus", bundle, illuminant="D65", level=0.8)
    assert plan.expected_level.max() == pytest.approx(0.8)
    short = make_plan("narrowband", bundle, max_exposure_s=1e-3)
    assert short.exposure_s == pytest.approx(1e-3) and short.expected_level.max() < 0.8
    bright = LightParameters(illuminance_lux=1e7)
    hot = oracle_calibration(replace(DESC, light=bright))
    # the light's switch time bounds the exposure from below: a light too bright even then is refused, since
    # every frame of a white would saturate
    with pytest.raises(ValueError, match=r"shortest exposure \(80 us\) saturates a white"):
        make_plan("tristimulus", hot)
    warm = oracle_calibration(replace(DESC, light=LightParameters(illuminance_lux=1.1e6)))  # floor binds, fits
    floor = make_plan("tristimulus", warm)
    assert floor.exposure_s == pytest.approx(80e-6) and floor.expected_level.max() <= 1.0


def test_plan_refuses_out_of_range_content(bundle):
    plan = make_plan("narrowband", bundle, centres=[500.0, 600.0])
    with pytest.raises(ValueError, match=r"must lie in \[0, 768\]"):
        replace(plan, patterns=plan.patterns * 2)
    with pytest.raises(ValueError, match=r"must lie in \[0, 768\]"):
        replace(plan, patterns=-plan.patterns)
    with pytest.raises(ValueError, match="below the light's switch time"):
        replace(plan, exposure_s=50e-6)
    with pytest.raises(ValueError, match="decoder A must be finite"):
        replace(plan, A=plan.A[:, :1])


def test_plan_file_round_trip_and_refusals(tmp_path, bundle, basis):
    plan = make_plan("symmetric", bundle, basis, m=5)
    path = tmp_path / "sym.npz"
    assert save_plan(path, plan) == plan.hash
    back = load_plan(path, calibration=bundle)
    assert back.hash == plan.hash and back.method == "symmetric"
    np.testing.assert_array_equal(back.A, plan.A)
    np.testing.assert_array_equal(back.patterns, plan.patterns)
    # Stale: the rig was recalibrated (another bundle).
    other = oracle_calibration(replace(DESC, light=LightParameters(lamp_colour_temperature_k=5500)))
    with pytest.raises(ValueError, match=r"sym\.npz is stale: made from calibration"):
        load_plan(path, calibration=other)
    data = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[:-100])
    with pytest.raises(ValueError, match=r"cut\.npz: corrupt"):
        load_plan(tmp_path / "cut.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["A"] = arrays["A"] + 1e-9
    np.savez(tmp_path / "edit.npz", **arrays)
    with pytest.raises(ValueError, match=r"edit\.npz: corrupt specgpu.plan file"):
        load_plan(tmp_path / "edit.npz")
    meta = str(arrays["__meta__"]).replace('"version": 1', '"version": 7')
    arrays["A"] = arrays["A"] - 1e-9
    arrays["__meta__"] = np.array(meta)
    np.savez(tmp_path / "v7.npz", **arrays)
    with pytest.raises(ValueError, match=r"v7\.npz: unknown specgpu.plan version 7"):
        load_plan(tmp_path / "v7.npz")


def test_plan_is_a_plan(bundle):
    assert isinstance(make_plan("steady", bundle, spectrum="A"), Plan)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(-5, 800), min_size=1, max_size=8), st.floats(1e-6, 1e-2))
def test_plan_validator_property(counts, exposure):
    """A plan is accepted exactly when its mirror counts lie in [0, 768] and its exposure is >= 80 us."""
    pat = np.zeros((1, 1024), np.int64)
    pat[0, : len(counts)] = counts
    kw = dict(method="narrowband", patterns=pat, target_spectra=np.zeros((1, 3)), light_wavelengths=[1.0, 2.0, 3.0],
              exposure_s=exposure, A=np.ones((1, 1)), output="relative", output_wavelengths=[],
              output_labels=("r",), illuminant="", observer="", calibration="x", rows=768, min_exposure_s=80e-6,
              expected_level=[0.5])
    ok = min(counts) >= 0 and max(counts) <= 768 and exposure >= 80e-6
    if ok:
        assert Plan(**kw).patterns.dtype == np.int32
    else:
        with pytest.raises(ValueError, match="mirrors|switch time"):
            Plan(**kw)
