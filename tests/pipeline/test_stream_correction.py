"""The stream's white-reference drift correction and uncertainty outputs against ``specgpu recover``'s, at 320 x 240.

A twin recording of the colorchecker with a 0.99 white tile above it (symmetric plan, K = 9, 31 bands) is
replayed through :class:`specgpu.pipeline.stream.Stream`; every streamed sequence is compared with the offline path on
the frames its ids name: ``pipeline.recover(..., white_roi=...)`` for the drift correction, ``pipeline.uncertainty``
and ``pipeline.outputs.sigma_with_rms`` / ``delta_E_sigma_map`` (what ``recover --sigma`` / ``--delta-e-sigma``
write) for the uncertainty.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from correction_helpers import white_stream_setup

from specgpu.engine.colorimetry import delta_E
from specgpu.io.recording import ZarrRecorder, open_recording
from specgpu.pipeline import Stream
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.outputs import delta_E_sigma_map, sigma_with_rms
from specgpu.pipeline.recovery import recover, to_Lab, to_XYZ, uncertainty
from specgpu.pipeline.stream_report import LatencyHistogram
from specgpu.planning import NoiseModel, delta_E_sigma
from specgpu.planning.correction import corrected_decoder, white_gains
from specgpu.rig.scene import white_tile_roi

SEQUENCES = 3
H, W = 240, 320


@pytest.fixture(scope="module")
def setup():
    """The twin recording, its plan given a noise model (and the expected error on a smooth prior)."""
    return white_stream_setup(W, H, SEQUENCES)


@pytest.fixture(scope="module")
def drifted(setup):
    """The same recording as if the lamp had dimmed and reddened since calibration: each pattern's signal above
    dark scaled by 0.9-1.06 across the sequence (a colour change, so the full refit of the decoder runs)."""
    K = setup.plan.K
    dark = setup.bundle.dark_at(setup.plan.exposure_s)
    scale = np.linspace(0.9, 1.06, K)
    f = setup.frames.astype(np.float64).reshape(-1, K, H, W)
    f = dark + (f - dark) * scale[None, :, None, None]
    frames = np.clip(np.rint(f), 0, setup.bundle.max_code - 1).astype(setup.frames.dtype).reshape(setup.frames.shape)
    return replace(setup, frames=frames)


ROI = ",".join(str(v) for v in white_tile_roi(H, W))


def folder_of(setup, frames):
    return SequenceFolder(Path("."), frames[None], setup.plan, setup.bundle, [], {})


def run_stream(setup, outputs, **kw):
    got = {}

    def keep(r):
        i = setup.recorded_sequence(r.frame_ids)
        got[i] = ({k: v.copy() for k, v in r.arrays.items()}, None if r.white_gains is None else r.white_gains.copy())

    stream = Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=outputs, reference=kw.pop(
        "reference", setup.reference if "dE" in outputs else None), policy="block", sinks=[keep],
        cube_dtype=np.float32, **kw)
    report = stream.run()
    assert report.sequences_out == SEQUENCES and sorted(got) == list(range(SEQUENCES))
    return got, report


def seq_frames(setup, i):
    K = setup.plan.K
    return setup.frames[i * K:(i + 1) * K]


def close(got, want, rel=2e-5, name=""):
    scale = float(np.nanmax(np.abs(want)))
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=name)
    np.testing.assert_allclose(got, want, rtol=0, atol=rel * scale, err_msg=name)


def test_white_roi_stream_equals_recover_white_roi(drifted):
    s = drifted
    got, _ = run_stream(s, ("coefficients", "cube", "XYZ", "dE"), white_roi=ROI, white_reflectance=0.99)
    for i, (arrays, gains) in got.items():
        frames = seq_frames(s, i)
        folder = folder_of(s, frames)
        want_gains = white_gains(frames, s.plan, s.bundle, ROI, 0.99)
        np.testing.assert_allclose(gains, want_gains, rtol=1e-12)
        assert np.ptp(gains) > 0.1  # the drift is seen, and corrected, per pattern
        cube = recover(folder, sequence=0, white_roi=ROI, white_reflectance=0.99)
        XYZ = to_XYZ(cube, s.plan)
        close(arrays["cube"], cube, name="cube")
        close(arrays["XYZ"], XYZ, name="XYZ")
        np.testing.assert_allclose(arrays["dE"], delta_E(s.reference, to_Lab(XYZ, s.plan)), rtol=0, atol=2e-3)
    # and the correction matters: without it the cube is off by the drift
    plain, _ = run_stream(s, ("cube",))
    assert np.nanmax(np.abs(plain[0][0]["cube"] - got[0][0]["cube"])) > 0.02


def test_white_roi_coefficients_rebuild_the_corrected_cube(drifted):
    s = drifted
    stream = Stream(s.driver(loops=1), s.plan, s.bundle, outputs=("coefficients", "cube"), policy="block",
                    cube_dtype=np.float32, white_roi=ROI)
    got = []
    stream.sinks.append(lambda r: got.append({k: v.copy() for k, v in r.arrays.items()}))
    stream.run()
    U = stream.decoder.basis
    for arrays in got:
        close(arrays["coefficients"] @ U.T, arrays["cube"], rel=5e-5, name="coefficients @ U.T")


def test_white_roi_without_drift_follows_recover_too(setup):
    got, _ = run_stream(setup, ("XYZ",), white_roi=ROI)
    for i, (arrays, gains) in got.items():
        frames = seq_frames(setup, i)
        gains_want = white_gains(frames, setup.plan, setup.bundle, ROI)
        A = corrected_decoder(setup.plan, gains_want, setup.bundle)
        np.testing.assert_allclose(gains, gains_want, rtol=1e-12)
        cube = recover(folder_of(setup, frames), sequence=0, white_roi=ROI)
        close(arrays["XYZ"], to_XYZ(cube, setup.plan), name="XYZ")
        assert A.shape == setup.plan.A.shape


def test_sigma_and_dE_sigma_equal_recover(setup):
    got, _ = run_stream(setup, ("XYZ", "sigma", "sigma_rms", "dE_sigma"))
    for i, (arrays, _) in got.items():
        folder = folder_of(setup, seq_frames(setup, i))
        sigma, cov = uncertainty(folder, sequence=0, illuminant="D65")
        want, names = sigma_with_rms(sigma, setup.plan.output_labels)  # what recover --sigma writes
        assert names[-1] == "sigma_rms"
        rms = want[..., -1:]
        assert arrays["sigma"].shape == (H, W, setup.plan.A.shape[0] + 1)
        close(arrays["sigma"], want, rel=1e-5, name="sigma")
        close(arrays["sigma_rms"], rms[..., 0], rel=1e-5, name="sigma_rms")
        xyz = to_XYZ(recover(folder, sequence=0), setup.plan)
        des = delta_E_sigma_map(xyz, cov, setup.plan.white_XYZ("D65"))  # what recover --delta-e-sigma writes
        assert float(np.median(des)) > 0.05
        np.testing.assert_allclose(arrays["dE_sigma"], des, rtol=1e-4, atol=1e-5)
        assert "XYZ_cov" not in arrays


def test_dE_sigma_alone_leaves_no_helper_maps(setup):
    got, _ = run_stream(setup, ("dE_sigma",))
    assert set(got[0][0]) == {"dE_sigma"}


def test_sigma_with_white_roi_uses_the_corrected_decoder(drifted):
    s = drifted
    got, _ = run_stream(s, ("sigma",), white_roi=ROI)
    from specgpu.planning import sigma_map

    frames = seq_frames(s, 0)
    A = corrected_decoder(s.plan, white_gains(frames, s.plan, s.bundle, ROI), s.bundle)
    # the white's per-sequence gains divide each frame's light fluctuation out: no light term
    sig = sigma_map(frames, replace(s.plan, A=A), s.bundle.dark_at(s.plan.exposure_s), s.bundle.flat_field,
                    light=False)
    close(got[0][0]["sigma"][..., :-1], sig, rel=1e-5, name="sigma (corrected decoder)")
    # and recover --sigma --white-roi writes the same (its uncertainty follows the decoder recover used)
    want, _ = uncertainty(folder_of(s, frames), sequence=0, white_roi=ROI)
    close(got[0][0]["sigma"][..., :-1], want, rel=1e-5, name="uncertainty(white_roi)")


@pytest.mark.parametrize("roi, message", [
    (f"{W - 5},0,10,10", "outside"),
    ("0,0,0,10", ">= 1"),
    ("a,b,c,d", "X,Y,W,H"),
])
def test_bad_white_roi_is_refused_before_streaming(setup, roi, message):
    with pytest.raises(ValueError, match=message) as err:
        Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=("XYZ",), white_roi=roi)
    assert "--white-roi" in str(err.value) and "\n" not in str(err.value)


def test_white_reflectance_needs_white_roi(setup):
    with pytest.raises(ValueError, match="--white-reflectance needs --white-roi"):
        Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=("XYZ",), white_reflectance=0.98)


def test_saturated_or_dark_white_stops_the_stream_with_one_line(setup):
    frames = setup.frames.copy()
    x, y, w, h = white_tile_roi(H, W)
    frames[2, y + 1, x + 1] = setup.bundle.max_code  # one saturated sample in frame 2 of sequence 0
    with pytest.raises(ValueError, match="saturated in frame 2"):
        Stream(replace(setup, frames=frames).driver(loops=1), setup.plan, setup.bundle, outputs=("XYZ",),
               white_roi=ROI, policy="block").run()
    # an ROI where the frames hold only the dark level (the chart's surround reflects ~3 %, a signal): no signal
    dark = np.rint(setup.bundle.dark_at(setup.plan.exposure_s)[:4, :4]).astype(setup.frames.dtype)
    frames = setup.frames.copy()
    frames[:, :4, :4] = dark
    with pytest.raises(ValueError, match="gives no signal"):
        Stream(replace(setup, frames=frames).driver(loops=1), setup.plan, setup.bundle, outputs=("XYZ",),
               white_roi="0,0,4,4", policy="block").run()


def test_sigma_needs_a_noise_model(setup):
    plan = replace(setup.plan, params={k: v for k, v in setup.plan.params.items() if k != "noise"})
    with pytest.raises(ValueError, match="no noise model"):
        Stream(setup.driver(loops=1), plan, setup.bundle, outputs=("sigma",))


def test_recording_keeps_gains_and_uncertainty(drifted, tmp_path):
    s = drifted
    rec = ZarrRecorder(tmp_path / "rec.zarr", s.plan)
    stream = Stream(s.driver(loops=1), s.plan, s.bundle, outputs=("XYZ", "sigma", "dE_sigma"), policy="block",
                    sinks=[rec], white_roi=ROI)
    stream.run()
    open_recording(tmp_path / "rec.zarr")  # a valid recording with the new maps
    import zarr

    g = zarr.open_group(str(tmp_path / "rec.zarr"), mode="r")
    gains = np.asarray(g["white_gains"])
    assert gains.shape == (SEQUENCES, s.plan.K)
    for i in range(SEQUENCES):
        np.testing.assert_allclose(gains[i], white_gains(seq_frames(s, i), s.plan, s.bundle, ROI), rtol=1e-12)
    assert g["sigma"].shape == (SEQUENCES, H, W, s.plan.A.shape[0] + 1)
    assert g["sigma"].attrs["channels"][-1] == "sigma_rms"
    assert g["dE_sigma"].shape == (SEQUENCES, H, W)
    assert sorted(g.attrs["outputs"]) == ["XYZ", "dE_sigma", "sigma"]


def test_latency_histogram_is_bounded_and_exact_in_count():
    rng = np.random.default_rng(1)
    hist = LatencyHistogram()
    size = hist.nbytes
    values = rng.lognormal(np.log(0.02), 0.5, 200_000)
    for v in values:
        hist.add(v)
    assert hist.nbytes == size  # a long run's memory for it does not grow
    assert hist.count == values.size
    assert hist.min == values.min() and hist.max == values.max()
    np.testing.assert_allclose(hist.mean, values.mean(), rtol=1e-12)
    for q in (0.01, 0.5, 0.9, 0.99, 0.999):
        assert abs(hist.quantile(q) / np.quantile(values, q) - 1) < 0.012
    assert np.isnan(LatencyHistogram().quantile(0.5))


def test_stream_latency_counts_every_result(setup):
    got, report = run_stream(setup, ("XYZ",))
    assert report.latency.count == report.sequences_out == SEQUENCES
    assert report.latency.min <= report.latency_ms(50) / 1e3 <= report.latency.max


# ---- the kernels behind them, against float64 NumPy references, in both variants on each device ---------------
@pytest.mark.usefixtures("kernel_variant")
@pytest.mark.parametrize("B, out_layout, out_dtype", [(3, 1, np.float32), (12, 1, np.float32), (62, 1, np.float32),
                                                      (7, 0, np.float32), (62, 0, np.float16), (12, 1, np.float16),
                                                      (130, 1, np.float32)])
def test_linear_square_root_output_is_sigma_of_a_linear_variance(queue, B, out_layout, out_dtype):
    """OUT_SQRT: sqrt(max(A (o - dark) * gain + offset_b, 0)) for every output, with a negative offset clamping some
    pixels to 0 (the variance's floor)."""
    import pyopencl as cl

    from specgpu import engine

    rng = np.random.default_rng(B + out_layout)
    K, n = 9, 1001
    A = rng.uniform(0, 1e-4, (B, K))
    offsets = rng.uniform(-0.3, 0.3, B)
    dark_h = rng.uniform(0, 5, n).astype(np.float32)
    gain_h = rng.uniform(0.8, 1.2, n).astype(np.float32)
    frames_h = rng.integers(0, 1024, (K, n)).astype(np.uint16)
    lin = engine.prepare_linear(queue, np.uint16, A, n=n, dark=engine.to_device(queue, dark_h),
                                gain=engine.to_device(queue, gain_h), out_dtype=out_dtype, out_layout=out_layout,
                                sqrt_offsets=offsets)
    got = np.empty(B * n, out_dtype)
    cl.enqueue_copy(queue, got, lin.enqueue(engine.to_device(queue, frames_h.reshape(-1)).data)["out"])
    var = (A @ (frames_h - dark_h.astype(np.float64))) * gain_h + offsets[:, None]  # (B, n)
    want = np.sqrt(np.maximum(var, 0.0))
    got = got.reshape(n, B).T if out_layout == 1 else got.reshape(B, n)
    assert (var < 0).any() and (var > 0).any()
    # compared as variances: near a zero variance the square root magnifies float32 rounding of the sum
    tol = 4e-3 if out_dtype == np.float16 else 1e-5
    np.testing.assert_allclose(got.astype(np.float64) ** 2, want ** 2, rtol=tol, atol=tol * (want ** 2).max())
    assert np.all(got[var <= 0] == 0)


@pytest.mark.usefixtures("kernel_variant")
@pytest.mark.parametrize("B, K", [(12, 9), (5, 130)])
def test_linear_squared_samples_are_the_light_fluctuation_variance(queue, B, K):
    """square=(q, c): each sample above the dark, x, enters the matrix as x + q (x - c)^2 (the frame variance with
    the light's fluctuation, NoiseModel.light_square), for K kept in registers and K re-read per output (> 128)."""
    import pyopencl as cl

    from specgpu import engine

    rng = np.random.default_rng(K)
    n = 1001
    noise = NoiseModel(30.0, 0.3, 0.02)
    q, c = noise.light_square()
    A = rng.uniform(0, 1e-4, (B, K))
    offsets = rng.uniform(0, 1e-3, B)
    dark_h = rng.uniform(10, 20, n).astype(np.float32) - np.float32(c)
    gain_h = rng.uniform(0.8, 1.2, n).astype(np.float32) ** 2
    frames_h = rng.integers(0, 4000, (K, n)).astype(np.uint16)
    lin = engine.prepare_linear(queue, np.uint16, A, n=n, dark=engine.to_device(queue, dark_h),
                                gain=engine.to_device(queue, gain_h), out_layout=1, sqrt_offsets=offsets,
                                square=(q, c))
    got = np.empty(B * n, np.float32)
    cl.enqueue_copy(queue, got, lin.enqueue(engine.to_device(queue, frames_h.reshape(-1)).data)["out"])
    x = frames_h - dark_h.astype(np.float64)
    var = (A @ (x + q * (x - c) ** 2)) * gain_h + offsets[:, None]
    np.testing.assert_allclose(got.reshape(n, B).T.astype(np.float64) ** 2, var, rtol=1e-5)
    # the squared term is what the light adds: without it the variance is a few times smaller here
    assert np.median(var / ((A @ x) * gain_h + offsets[:, None])) > 2
    with pytest.raises(ValueError, match="square"):
        engine.prepare_linear(queue, np.uint16, A, n=n, square=(q, float("nan")))


@pytest.mark.usefixtures("kernel_variant")
def test_delta_e_sigma_kernel_equals_the_host_propagation(queue):
    """The device's first-order dE2000 sigma against estimators.delta_E_sigma (float64) on colours from near black
    (the linear branch of the CIE function) to near white, with random positive definite covariances."""
    import pyopencl as cl

    from specgpu import engine
    from specgpu.core.spectra import white_point_XYZ

    rng = np.random.default_rng(7)
    n = 999
    xyz = rng.uniform(0.0005, 0.95, (n, 3))
    xyz[:50] *= 0.005  # below (24/116)^3 of the white
    R = rng.normal(0, 1e-3, (n, 3, 3))
    cov = R @ np.transpose(R, (0, 2, 1))
    const = np.diag([1e-7, 2e-7, 3e-7])
    six = np.stack([cov[:, i, j] for i in range(3) for j in range(i, 3)], axis=-1).astype(np.float32)
    white = white_point_XYZ("D65")
    launch = engine.prepare_delta_E_sigma(queue, white, const, n=n)
    out = launch.enqueue(engine.to_device(queue, xyz.astype(np.float32).reshape(-1)).data,
                         inputs={1: engine.to_device(queue, six.reshape(-1)).data})
    got = np.empty(n, np.float32)
    cl.enqueue_copy(queue, got, out["dE_sigma"])
    want = delta_E_sigma(xyz.astype(np.float32), six_to_full(six) + const, "D65")
    # a GPU contracts the chain into FMAs and its float32 division and square root may round differently (OpenCL
    # allows 2.5 and 3 ulp): an H100 differs from the host by up to 2.6e-4 relative; a sigma needs no more
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-6)


def six_to_full(six):
    out = np.empty(six.shape[:-1] + (3, 3))
    for m, (i, j) in enumerate((i, j) for i in range(3) for j in range(i, 3)):
        out[..., i, j] = out[..., j, i] = six[..., m]
    return out


def test_delta_E_sigma_matches_a_monte_carlo_of_ciede2000():
    """The first-order propagation (analytic Jacobian) against the spread of dE2000 over small XYZ perturbations
    drawn from the covariance: the RMS dE2000 of the draws is the predicted sigma (to sampling error)."""
    import colour

    from specgpu.engine.colorimetry import XYZ_to_Lab

    rng = np.random.default_rng(3)
    xyz = np.array([0.2, 0.25, 0.3])
    C = np.diag([2e-7, 3e-7, 1e-7]) + 5e-8
    draws = rng.multivariate_normal(xyz, C, 20000)
    lab0 = colour.XYZ_to_Lab(xyz, colour.XYZ_to_xy(colour.xy_to_XYZ([0.3127, 0.3290])))
    lab = np.asarray(XYZ_to_Lab(draws, "D65"), np.float64)
    lab0 = np.asarray(XYZ_to_Lab(xyz[None], "D65"), np.float64)[0]
    rms = float(np.sqrt(np.mean(colour.delta_E(lab0, lab, method="CIE 2000") ** 2)))
    assert abs(float(delta_E_sigma(xyz, C)) / rms - 1) < 0.03


# ---- corrections recover applies before the linear map: linearisation, per-pattern flat field, ambient frame ----
@pytest.fixture(scope="module")
def corrected(setup):
    """The recording with a calibration that measured a sensor compression and a wavelength-dependent flat field
    (a left-right tilt that grows to the red), so frames need host-side corrections before the linear map."""
    b = setup.bundle
    tilt = np.linspace(-1.0, 1.0, W, dtype=np.float32)[None, :]
    flats = np.stack([b.flat_field * (1 + 0.04 * s * tilt) for s in (-1.0, 1.0)])
    bundle = replace(b, flat_fields=flats, flat_wavelengths=np.array([450.0, 650.0]),
                     reports={**b.reports, "linearity_c_per_dn2": 4e-8})
    return replace(setup, bundle=bundle, plan=replace(setup.plan, calibration=bundle.hash))


def test_stream_applies_recovers_frame_corrections(corrected):
    s = corrected
    assert s.bundle.flat_ratio(s.plan.patterns) is not None
    frames = s.frames.copy()
    frames[4, 10, 20] = s.bundle.max_code  # a saturated sample: NaN in both
    s = replace(s, frames=frames)
    got, _ = run_stream(s, ("cube", "XYZ", "sigma_rms"))
    bare = replace(s.bundle, flat_fields=None, flat_wavelengths=None,
                   reports={k: v for k, v in s.bundle.reports.items() if k != "linearity_c_per_dn2"})
    seen = []
    report = Stream(s.driver(loops=1), replace(s.plan, calibration=bare.hash), bare, outputs=("cube",),
                    policy="block", cube_dtype=np.float32,
                    sinks=[lambda r: seen.append(r.arrays["cube"].copy())]).run()
    assert report.sequences_out == SEQUENCES, report
    for i, (arrays, _) in got.items():
        cube = recover(folder_of(s, seq_frames(s, i)), sequence=0)
        close(arrays["cube"], cube, rel=1e-5, name="cube")
        close(arrays["XYZ"], to_XYZ(cube, s.plan), rel=1e-5, name="XYZ")
        assert np.isnan(arrays["cube"][10, 20]).all() == (i == 0)
        assert np.isfinite(arrays["sigma_rms"]).mean() > 0.99
        sigma, _ = uncertainty(folder_of(s, seq_frames(s, i)), sequence=0)  # recover --sigma, corrected frames
        rms = np.sqrt(np.mean(sigma.astype(np.float64) ** 2, axis=-1)).astype(np.float32)
        close(arrays["sigma_rms"], rms, rel=1e-5, name="sigma_rms")
    # the corrections matter: without them the stream would differ from recover by the tilt
    assert np.nanmax(np.abs(seen[0] - got[0][0]["cube"])) > 0.01


@pytest.mark.parametrize("white", [True, False])
def test_stream_subtracts_the_ambient_frame_as_recover_does(setup, white):
    from specgpu.capture.replay import record
    from specgpu.capture.twin_driver import TwinDriver
    from specgpu.planning.correction import with_ambient_frame
    from specgpu.rig.scene import colorchecker_scene
    from specgpu.rig.twin import TwinRig

    plan = with_ambient_frame(setup.plan)
    from specgpu.rig.realism import Realism

    description = replace(setup.description, realism=Realism(ambient_lux=1000.0))  # a lit room
    rig = TwinRig(plan.rig_description(description), scene=colorchecker_scene(H, W, white_tile=0.99))
    rig.seed = 3
    frames, infos, light = record(TwinDriver(rig, patterns=plan.patterns, pacing="free"), plan.K * SEQUENCES)
    s = replace(setup, plan=plan, frames=frames, infos=infos, light=light)
    amb = frames[plan.K - 1].astype(np.float64) - setup.bundle.dark_at(plan.exposure_s)
    assert np.median(amb) > 2  # the room light is in every frame, and the ambient frame sees it
    roi = ROI if white else None
    got, _ = run_stream(s, ("cube", "XYZ", "sigma", "dE_sigma"), white_roi=roi)
    for i, (arrays, _) in got.items():
        fr = frames[i * plan.K:(i + 1) * plan.K]
        cube = recover(folder_of(s, fr), sequence=0, white_roi=roi)
        close(arrays["cube"], cube, rel=1e-5, name="cube")
        close(arrays["XYZ"], to_XYZ(cube, plan), rel=1e-5, name="XYZ")
        # the ambient frame as the dark level, its own noise and the room light's shot noise in the sigma
        sigma, cov = uncertainty(folder_of(s, fr), sequence=0, white_roi=roi, illuminant="D65")
        close(arrays["sigma"][..., :-1], sigma, rel=1e-5, name="sigma")
        des = delta_E_sigma(np.nan_to_num(to_XYZ(cube, plan)), np.nan_to_num(cov), plan.white_XYZ("D65"))
        np.testing.assert_allclose(arrays["dE_sigma"], des, rtol=1e-4, atol=1e-5)
