"""Motion compensation wherever frames are decoded: `specgpu batch --motion` and `specgpu stream --motion` give what
`specgpu recover --motion` gives on the same frames, and what cannot be compensated is refused in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from moving_helpers import CAM, MOTION, moving_capture

from specgpu.engine.colorimetry import delta_E
from specgpu.pipeline.batch import run_batch
from specgpu.pipeline.capture_folder import read_capture
from specgpu.pipeline.moving_decode import check_motion_options
from specgpu.pipeline.recovery import recover, to_Lab, to_XYZ
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.planning.correction import with_ambient_frame
from specgpu.rig import RigDescription, natural_scene

LAB_REF = [50.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """A sequence folder of 2 sequences of a 7-band narrowband plan on a twin whose scene drifts 2 px per frame
    in x and 1 in y, with its plan and calibration files."""
    return moving_capture(tmp_path_factory.mktemp("moving-decode"))


def recovered(root, sequence, motion):
    return recover(read_capture(root / "seq"), sequence=sequence, motion=motion)


def assert_close_nan(a, b, **tol):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(np.nan_to_num(a), np.nan_to_num(b), **tol)


def test_batch_with_motion_equals_recover_with_motion(moving, tmp_path, dask_scheduler):
    import zarr

    root, plan, bundle, _, _ = moving
    report = run_batch(root / "seq", plan, bundle, tmp_path / "out.zarr", outputs=("cube", "XYZ", "Lab", "dE"),
                       reference=LAB_REF, workers=1, progress=False, motion="global")
    assert report.computed == 2
    out = zarr.open_group(str(tmp_path / "out.zarr"), mode="r")
    assert out.attrs["motion"] == "global"
    for i in range(2):
        want = recovered(root, i, "global")
        assert 0 < np.isnan(want[..., 0]).mean() < 0.2  # the drift leaves a border seen outside the field
        assert_close_nan(out["cube"][i], want, rtol=1e-6, atol=1e-6)
        XYZ = to_XYZ(want, plan)
        assert_close_nan(out["XYZ"][i], XYZ, rtol=1e-5, atol=1e-6)
        assert_close_nan(out["Lab"][i], to_Lab(XYZ, plan), atol=1e-3)
        assert_close_nan(out["dE"][i], delta_E(np.array(LAB_REF, np.float32), to_Lab(XYZ, plan)), atol=1e-3)
    # the comparison can fail: the same frames decoded without compensation are far from it
    still = recovered(root, 1, "none")
    moved = np.asarray(out["cube"][1])
    ok = np.isfinite(moved[..., 0])
    assert np.abs(still[ok] - moved[ok]).mean() > 10 * np.abs(moved[ok] - recovered(root, 1, "global")[ok]).mean()
    assert np.abs(still[ok] - moved[ok]).mean() > 0.01


def test_options_that_are_not_motion_compensated_are_named(moving):
    _, plan, _, _, _ = moving
    assert check_motion_options("None", plan, outputs=("sigma",)) == "none"
    assert check_motion_options("global", plan, outputs=("cube", "sigma", "sigma_rms", "dE_sigma")) == "global"
    assert check_motion_options("global", with_ambient_frame(plan)) == "global"  # its ambient frame warped too
    with pytest.raises(ValueError, match="motion"):
        check_motion_options("sideways", plan)


def test_the_decoder_stacks_its_outputs_into_one_pass_equal_to_recover(moving):
    root, plan, bundle, _, _ = moving
    folder = read_capture(root / "seq")
    dec = SequenceDecoder(plan, bundle, ("cube", "XYZ"), motion="global")
    maps = dec.maps(folder.frames[0])
    assert dec.rows.shape == (plan.A.shape[0] + 3, plan.K)
    assert_close_nan(maps["cube"], recovered(root, 0, "global"), rtol=1e-6, atol=1e-6)
    assert maps["mask"].dtype == np.uint8 and maps["estimate"].shifts.shape == (plan.K, 2)
    np.testing.assert_allclose(maps["estimate"].shifts, (np.arange(plan.K) - plan.K // 2)[:, None] * [2.0, 1.0],
                               atol=0.1)


# ------------------------------------------------------------------------------------------------------ the stream

def twin_driver(plan, bundle, sequences, seed=7):
    from specgpu.capture.twin_driver import TwinDriver
    from specgpu.rig.twin import TwinRig

    rig = TwinRig(plan.rig_description(RigDescription(camera=CAM, motion=MOTION)), scene=natural_scene(240, 320))
    rig.seed = seed
    return TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K * sequences, pacing="free")


def streamed(plan, bundle, motion, sequences=2):
    from specgpu.pipeline.stream import Stream

    kept = []

    def keep(result):
        kept.append(({k: np.array(v) for k, v in result.arrays.items()}, np.array(result.frames), result.motion))

    report = Stream(twin_driver(plan, bundle, sequences), plan, bundle, outputs=("cube", "XYZ", "Lab", "dE"),
                    reference=LAB_REF, cube_dtype=np.float32, policy="block", sinks=[keep], motion=motion).run()
    assert report.sequences_out == sequences == len(kept)
    return kept


def test_a_stream_with_motion_equals_recover_with_motion_of_the_same_frames(moving):
    from pathlib import Path

    from specgpu.pipeline.capture_folder import SequenceFolder

    _, plan, bundle, _, _ = moving
    compensated = streamed(plan, bundle, "global")
    for maps, frames, estimate in compensated:
        folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
        want = recover(folder, sequence=0, motion="global")
        assert 0 < np.isnan(want[..., 0]).mean() < 0.2
        assert_close_nan(maps["cube"], want, rtol=1e-6, atol=1e-6)
        XYZ = to_XYZ(want, plan)
        assert_close_nan(maps["XYZ"], XYZ, rtol=1e-5, atol=1e-6)
        assert_close_nan(maps["dE"], delta_E(np.array(LAB_REF, np.float32), to_Lab(XYZ, plan)), atol=1e-3)
        np.testing.assert_allclose(estimate.shifts, (np.arange(plan.K) - plan.K // 2)[:, None] * [2.0, 1.0],
                                   atol=0.1)
    # the same moving twin streamed without compensation: the same frames (same seed), far from recover --motion
    plain = streamed(plan, bundle, "none")
    for (maps, frames, estimate), (still, still_frames, none) in zip(compensated, plain):
        np.testing.assert_array_equal(frames, still_frames)
        assert none is None
        ok = np.isfinite(maps["cube"][..., 0])
        assert np.abs(still["cube"][ok] - maps["cube"][ok]).mean() > 0.01


def test_a_stream_and_a_batch_with_a_flow_equal_recover_with_a_flow(moving, tmp_path, dask_scheduler):
    import zarr

    from specgpu.pipeline.capture_folder import SequenceFolder

    root, plan, bundle, _, _ = moving
    for maps, frames, estimate in streamed(plan, bundle, "flow"):
        folder = SequenceFolder(Path("mem"), frames[None], plan, bundle, [], {})
        want = recover(folder, sequence=0, motion="flow")
        assert 0 < np.isnan(want[..., 0]).mean() < 0.2
        assert_close_nan(maps["cube"], want, rtol=1e-6, atol=1e-6)
        Lab = to_Lab(to_XYZ(want, plan), plan)
        assert_close_nan(maps["dE"], delta_E(np.array(LAB_REF, np.float32), Lab), atol=1e-3)
        assert estimate.model == "flow" and estimate.shifts.shape == (plan.K, 2, *frames.shape[1:])
        # the drift is one translation: the flow is it, to a few hundredths of a px per frame
        drift = (np.arange(plan.K) - plan.K // 2)[:, None, None, None] * np.array([2.0, 1.0])[None, :, None, None]
        assert np.median(np.abs(estimate.shifts - drift)) < 0.1
    # the batch decodes in a worker process of its own, and the flow keeps or drops each tile's frames, and
    # chooses each pixel's decoding, by thresholds: once in a full run of the suite (not reproduced alone) a
    # region of the field came out up to 0.004 apart, as a tile's velocity a little different would make it. So
    # close, not equal: the same NaNs but for a few pixels, most values equal, none far
    run_batch(root / "seq", plan, bundle, tmp_path / "out.zarr", outputs=("cube",), workers=1, progress=False,
              motion="flow")
    out = zarr.open_group(str(tmp_path / "out.zarr"), mode="r")
    assert out.attrs["motion"] == "flow"
    got, want = np.asarray(out["cube"][1], np.float64), recovered(root, 1, "flow").astype(np.float64)
    both = np.isfinite(got) & np.isfinite(want)
    assert (np.isnan(got) != np.isnan(want)).mean() < 0.01 and both.mean() > 0.8
    assert np.abs(got - want)[both].max() < 0.02 and np.median(np.abs(got - want)[both]) < 1e-6


def test_a_sequence_that_fails_to_decode_ends_the_moving_stream_with_its_error(moving):
    from specgpu.pipeline.stream import Stream

    _, plan, bundle, _, _ = moving
    stream = Stream(twin_driver(plan, bundle, 4), plan, bundle, outputs=("cube",), policy="block", motion="global")
    calls = []
    decode = stream.decoder.maps

    def failing(frames):
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("no frame of the sequence has signal to register")
        return decode(frames)

    stream.decoder.maps = failing
    with pytest.raises(ValueError, match="no frame of the sequence has signal"):
        stream.run(30)
    assert len(calls) >= 2


def test_a_moving_stream_keeps_a_sequence_in_flight_for_each_decoding_thread(moving):
    """The decoding threads are only busy together with as many sequences in flight (and result buffers) as
    there are threads, whatever smaller depth was asked for."""
    from specgpu.pipeline.stream import MOTION_THREADS, Stream

    _, plan, bundle, _, _ = moving
    stream = Stream(twin_driver(plan, bundle, 1), plan, bundle, outputs=("cube",), motion="global", in_flight=1,
                    result_buffers=1)
    assert stream.in_flight == max(1, MOTION_THREADS) and stream.result_buffers == stream.in_flight
    still = Stream(twin_driver(plan, bundle, 1), plan, bundle, outputs=("cube",), in_flight=1, result_buffers=1)
    assert (still.in_flight, still.result_buffers) == (1, 1)


def test_affine_motion_decodes_as_recover_affine(moving):
    root, plan, bundle, _, _ = moving
    folder = read_capture(root / "seq")
    maps = SequenceDecoder(plan, bundle, ("cube",), motion="affine").maps(folder.frames[1])
    # the affine map or, where it explains no more of the field, the translation decoded beside it
    est = maps["estimate"]
    assert (est.model, est.shifts.shape) in {("affine", (plan.K, 2, 3)), ("translation", (plan.K, 2))}
    assert_close_nan(maps["cube"], recovered(root, 1, "affine"), rtol=1e-6, atol=1e-6)


def test_sigma_rms_with_motion_bounds_the_noise_of_the_compensated_cube(moving):
    """Two noise draws of the same moving sequence decoded with compensation: the RMS over the bands of their
    noise is at most the decoder's sigma_rms (an upper bound: interpolation averages neighbouring pixels' noise)
    and not far below it; NaN exactly where the cube is."""
    _, plan, bundle, _, _ = moving
    desc = RigDescription(camera=CAM, motion=MOTION)
    dec = SequenceDecoder(plan, bundle, ("cube", "sigma_rms"), motion="global")
    frames = [capture_plan(desc, plan, natural_scene(240, 320), noise_seed=seed, calibration=bundle).sequences[0].frames
              for seed in (11, 12)]
    draws = [dec.maps(f) for f in frames]
    alone = SequenceDecoder(plan, bundle, ("sigma_rms",), motion="global").maps(frames[0])
    assert set(alone) == {"sigma_rms", "mask", "estimate", "layers"}
    np.testing.assert_array_equal(alone["sigma_rms"], draws[0]["sigma_rms"])
    a, b = (np.asarray(d["cube"], np.float64) for d in draws)
    sigma = np.asarray(draws[0]["sigma_rms"], np.float64)
    np.testing.assert_array_equal(np.isnan(sigma), np.isnan(a[..., 0]))
    ok = np.isfinite(a[..., 0]) & np.isfinite(b[..., 0])
    noise_var = np.mean((a - b)[ok] ** 2, axis=-1) / 2.0
    ratio = np.sqrt(noise_var.mean() / np.mean(sigma[ok] ** 2))
    assert 0.6 < ratio < 1.05, ratio


def test_stream_accumulates_along_the_motion(moving, tmp_path):
    """``stream --motion global --accumulate N``: the running estimate moves with the scene (each step between
    sequences registered), so after a few sequences its noise is below one sequence's."""
    from specgpu.pipeline.accumulate import AccumulateSink
    from specgpu.pipeline.stream import Stream

    _, plan, bundle, _, _ = moving
    runs = {}
    for seed in (7, 8):
        sink = AccumulateSink(4, ("cube", "sigma_rms"), motion=True)
        single = []
        keep = lambda r: single.append(np.array(r.arrays["cube"]))  # noqa: E731
        report = Stream(twin_driver(plan, bundle, 5, seed=seed), plan, bundle, outputs=("cube", "sigma_rms"),
                        cube_dtype=np.float32, policy="block", sinks=[keep, sink], motion="global").run()
        assert report.sequences_out == 5
        runs[seed] = (single, sink)
    step = plan.K * np.array(MOTION.velocity_px_per_frame)
    np.testing.assert_allclose(runs[7][1].shifts, np.tile(step, (4, 1)), atol=0.1)
    last = {seed: (single[-1], sink.mean["cube"]) for seed, (single, sink) in runs.items()}
    ok = np.all([np.isfinite(m[..., 0]) for pair in last.values() for m in pair], axis=0)
    ok &= runs[7][1].counts == 4
    assert ok.mean() > 0.5
    one = np.std((last[7][0] - last[8][0])[ok])
    averaged = np.std((last[7][1] - last[8][1])[ok])
    assert averaged < 0.65 * one, (averaged, one)
