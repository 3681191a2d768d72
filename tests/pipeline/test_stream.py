"""The streaming pipeline end to end at 320 x 240: offline equality, fault injection, backpressure, shutdown, sinks.

Frames come from the twin (faults injected by frame id) or from a replayed twin recording, through the same ring
buffer and assembler as hardware frames; every result is checked against the offline path on the frames its ids
name, so a sequence built across a lost or shifted frame cannot pass.
"""

from __future__ import annotations

import _thread
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest
from stream_helpers import shared_stream_setup
from zarr_helpers import disk_full_after

from specgpu import io
from specgpu.capture.session import capture_sequences
from specgpu.capture.twin_driver import TwinDriver
from specgpu.engine.colorimetry import delta_E
from specgpu.io.recording import ZarrRecorder, open_recording
from specgpu.pipeline import ExrSequenceWriter, PreviewSink, Stream
from specgpu.pipeline.capture_folder import SequenceFolder
from specgpu.pipeline.recovery import recover, to_Lab, to_XYZ
from specgpu.pipeline.sinks import ResultsRing
from specgpu.pipeline.twin_replay import offline_maps
from specgpu.rig.twin import FaultSchedule, TwinRig

ALL = ("coefficients", "cube", "XYZ", "Lab", "dE")


@pytest.fixture(scope="module")
def setup():
    """A calibrated 320 x 240 twin at 200 fps, a symmetric plan (K = 9, 31 bands) and 4 recorded sequences."""
    return shared_stream_setup(320, 240, sequences=4, output_step_nm=10.0)


@pytest.fixture(scope="module")
def expected(setup):
    return {i: offline_maps(setup, i) for i in range(4)}


def offline(setup, frames):
    """The offline path (``pipeline.recover`` + ``to_XYZ`` / ``to_Lab`` + ``delta_E``) on one sequence's frames."""
    folder = SequenceFolder(Path("."), frames[None], setup.plan, setup.bundle, [], {})
    cube = recover(folder, sequence=0)
    XYZ = to_XYZ(cube, setup.plan)
    Lab = to_Lab(XYZ, setup.plan)
    return {"cube": cube, "XYZ": XYZ, "Lab": Lab, "dE": delta_E(setup.reference, Lab)}


def assert_maps_equal(got: dict, want: dict):
    for name in ("cube", "XYZ", "Lab"):
        if name in got:
            scale = np.max(np.abs(want[name]))
            np.testing.assert_allclose(got[name], want[name], rtol=0, atol=2e-5 * scale, err_msg=name)
    if "dE" in got:
        np.testing.assert_allclose(got["dE"], want["dE"], rtol=0, atol=2e-3, err_msg="dE")


class Collect:
    """A sink keeping copies of every result (ids and maps)."""

    def __init__(self, delay_s: float = 0.0):
        self.results = []
        self.delay_s = delay_s
        self.closed = False

    def write(self, r):
        self.results.append((r.frame_ids.copy(), {k: v.copy() for k, v in r.arrays.items()}))
        if self.delay_s:
            time.sleep(self.delay_s)

    def close(self):
        self.closed = True


def aligned(setup, ids) -> bool:
    return bool(np.all(np.diff(ids) == 1)) and int(ids[0]) % setup.plan.K == 0


def test_stream_equals_offline_recover(setup, expected):
    sink = Collect()
    stream = Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=ALL, cube_dtype=np.float32,
                    reference=setup.reference, policy="block", sinks=[sink])
    report = stream.run()
    assert report.sequences_out == 4 and len(sink.results) == 4 and sink.closed
    assert report.accounting()["balanced"] and report.frames_in == 36
    for ids, maps in sink.results:
        assert aligned(setup, ids)
        i = setup.recorded_sequence(ids)
        assert_maps_equal(maps, expected[i])
        # the coefficients rebuild the cube through the decoder's output basis
        rebuilt = maps["coefficients"] @ stream.decoder.basis.T
        np.testing.assert_allclose(rebuilt, maps["cube"], atol=1e-4 * np.max(np.abs(maps["cube"])))


@pytest.mark.parametrize("readback,upload", [("copy", "copy"), ("map", "pinned"), ("pinned", "pinned")])
def test_transfer_modes_give_the_same_results(setup, expected, readback, upload):
    sink = Collect()
    stream = Stream(setup.driver(loops=2), setup.plan, setup.bundle, outputs=("cube", "dE"), cube_dtype=np.float32,
                    reference=setup.reference, policy="block", sinks=[sink], readback=readback, upload=upload,
                    in_flight=2, result_buffers=2)
    report = stream.run()
    assert report.sequences_out == 8
    for ids, maps in sink.results:
        assert_maps_equal(maps, expected[setup.recorded_sequence(ids)])


def test_injected_faults_counted_exactly_and_never_misaligned(setup):
    """Drops, a duplicate and a missed trigger on the twin: the stream's counts equal the schedule's, its sequences
    are exactly the capture path's, and each map equals the offline recovery of the frames its ids name."""
    K = setup.plan.K
    faults = FaultSchedule(dropped={5, 30}, duplicated={12, 50}, missed_triggers={40})
    n_frames = 8 * K

    def twin():
        rig = TwinRig(setup.plan.rig_description(setup.description), scene=_scene(setup))
        rig.seed = 11
        return TwinDriver(rig, patterns=setup.plan.patterns, n_frames=n_frames, faults=faults, pacing="free")

    sink = Collect()
    report = Stream(twin(), setup.plan, setup.bundle, outputs=("XYZ", "Lab", "dE"), reference=setup.reference,
                    policy="block", sinks=[sink]).run()
    capture = capture_sequences(twin(), K)
    a = report.assembly
    assert (a.dropped, a.duplicates, a.missed_triggers) == (2, 2, 1)
    assert a.as_dict() == capture.assembly.as_dict()
    assert report.ring.dropped == 0 and report.accounting()["balanced"]
    assert [list(ids) for ids, _ in sink.results] == [list(s.frame_ids) for s in capture.sequences]
    # sequences hit by a fault are discarded: 0-8 (drop 5), 27-35 (drop 30), and after the missed trigger at 40
    # the light is one pattern behind, so sequences start at ids = 1 (mod K)
    starts = [int(ids[0]) for ids, _ in sink.results]
    assert 0 not in starts and 27 not in starts and all(s % K == 1 for s in starts if s > 40)
    for (ids, maps), seq in zip(sink.results, capture.sequences):
        assert_maps_equal(maps, offline(setup, seq.frames))


def _scene(setup):
    from specgpu.rig.scene import colorchecker_scene

    h, w = setup.frames.shape[1:]
    return colorchecker_scene(h, w)


@pytest.mark.parametrize("policy", ["drop_newest", "drop_oldest"])
def test_stalling_sink_makes_the_ring_policy_act(setup, expected, policy):
    """A sink slower than the camera: result buffers run out, the device thread waits, the frame ring fills and
    its policy drops frames; every drop is counted (ring = id gaps) and every result is still aligned."""
    sink = Collect(delay_s=0.08)  # ~12 sequences/s against 200 / 9 = 22 offered
    stream = Stream(setup.driver(pacing="paced"), setup.plan, setup.bundle, outputs=("XYZ", "dE"),
                    reference=setup.reference, policy=policy, sinks=[sink], n_slots=18, result_buffers=2,
                    in_flight=1)
    report = stream.run(1.5)
    r, a = report.ring, report.assembly
    assert r.dropped > 0
    assert (r.dropped_newest if policy == "drop_newest" else r.dropped_oldest) == r.dropped
    assert a.dropped == r.dropped  # the replay loses nothing itself: every gap is a ring drop
    assert report.frames_in == report.end.last_frame_id + 1
    assert report.accounting()["balanced"] and a.sequences_discarded > 0
    assert report.sequences_out == len(sink.results) > 0
    for ids, maps in sink.results:
        assert aligned(setup, ids)
        assert_maps_equal(maps, expected[setup.recorded_sequence(ids)])


def test_ctrl_c_drains_every_buffered_frame(setup, expected, request):
    """KeyboardInterrupt in the thread running the stream: capture stops at a sequence boundary, every frame
    already in the ring is assembled and computed, every result reaches the sinks, and the counters balance."""
    import signal

    # interrupt_main does nothing unless Python handles SIGINT: the default handler, whatever ran before
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    request.addfinalizer(lambda: signal.signal(signal.SIGINT, previous))
    sink = Collect(delay_s=0.01)
    stream = Stream(setup.driver(), setup.plan, setup.bundle, outputs=("XYZ", "dE"), reference=setup.reference,
                    policy="block", sinks=[sink])
    # armed from the first status call, so the interrupt lands once the stream runs (never in a kernel build)
    timer = threading.Timer(0.5, _thread.interrupt_main)
    pending_at_interrupt = []

    def look(status):
        if not pending_at_interrupt:
            timer.start()
        pending_at_interrupt.append(status["pending"])

    try:
        report = stream.run(30.0, on_status=look, status_interval_s=0.1)
    finally:
        timer.cancel()
    assert report.interrupted and report.seconds < 10
    assert max(pending_at_interrupt) > 0  # frames were buffered while running
    assert report.ring.pending == 0 and report.ring.delivered == report.ring.finalized
    a = report.assembly
    assert report.frames_in % setup.plan.K == 0 and a.frames_unused == 0 and a.sequences_discarded == 0
    assert report.sequences_out == a.sequences_complete == len(sink.results) == report.frames_in // setup.plan.K
    assert report.accounting()["balanced"] and sink.closed
    for ids, maps in sink.results[-3:]:
        assert aligned(setup, ids)
        assert_maps_equal(maps, expected[setup.recorded_sequence(ids)])


def test_stop_mid_sequence_reports_the_partial_one(setup):
    """A stop whose sequence can never complete (the driver's stream ends 4 frames into it): the partial
    sequence's frames are reported as unused, one sequence discarded."""
    K = setup.plan.K
    frames, infos = setup.frames[:K + 4], setup.infos[:K + 4]
    from specgpu.capture.replay import ReplayDriver

    report = Stream(ReplayDriver(frames, infos, setup.light), setup.plan, setup.bundle, outputs=("XYZ",),
                    policy="block").run()
    a = report.assembly
    assert report.sequences_out == 1 and a.frames_unused == 4 and a.sequences_discarded == 1
    assert report.accounting()["balanced"]


def test_one_result_buffer_never_hangs_when_frames_are_waiting(setup):
    """Recorded frames replayed as fast as they are read, one result buffer: the next sequence is assembled from
    frames already in the ring before the previous one's device work has finished. Its token comes back only once
    that previous result reaches the sinks, so the device thread hands it over instead of waiting for it."""
    from specgpu.capture.replay import ReplayDriver

    done = {}

    def run():
        done["report"] = Stream(ReplayDriver(setup.frames, setup.infos, setup.light, loops=4), setup.plan,
                                setup.bundle, outputs=("cube", "XYZ"), policy="block", result_buffers=1,
                                in_flight=1, n_slots=4 * setup.plan.K).run()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(120)
    assert not thread.is_alive(), "the stream hung waiting for a result buffer"
    assert done["report"].sequences_out == 16 and done["report"].accounting()["balanced"]


def test_a_slot_refilled_the_moment_it_is_released_loses_no_frame(setup, monkeypatch):
    """The driver's thread may take a released slot back at once (its metadata reset while it is filled): the
    stream reads what it needs of a frame before it releases the slot, so every frame keeps its arrival stamp."""
    from specgpu.capture.replay import ReplayDriver
    from specgpu.capture.ringbuffer import RingBuffer

    release = RingBuffer.release

    def release_and_refill(self, slot):
        slot.info = None  # what an acquire for filling does to the slot the moment it is free
        release(self, slot)

    monkeypatch.setattr(RingBuffer, "release", release_and_refill)
    report = Stream(ReplayDriver(setup.frames, setup.infos, setup.light, loops=2), setup.plan, setup.bundle,
                    outputs=("XYZ",), policy="block").run()
    assert report.sequences_out == 8 and report.accounting()["balanced"] and not report.sink_errors
    assert report.latency.count == 8 and np.isfinite(report.latency.mean)  # each result timed from its frame


def test_a_failing_sink_stops_the_stream_and_the_captured_sequences_reach_the_others(setup):
    """A sink that is not optional fails on its 2nd result: it is named in one line, capture stops at a sequence
    boundary (not at the time limit), and every sequence captured still reaches the sink after it."""
    calls = []

    def bad(result):
        calls.append(result.index)
        if len(calls) == 2:
            raise ValueError("disk full")

    after = Collect()
    report = Stream(setup.driver(), setup.plan, setup.bundle, outputs=("XYZ",), policy="block",
                    sinks=[bad, after]).run(20)
    assert report.sink_errors == ["CallbackSink: ValueError: disk full"] and report.seconds < 10
    assert report.accounting()["balanced"] and not report.sinks_stopped
    assert calls == [0, 1]  # stopped at its failure
    assert len(after.results) == report.sequences_out >= 2  # nothing captured was lost to the sink after it


def test_sinks_write_readable_files(setup, expected, tmp_path):
    ring = ResultsRing(capacity=2)
    preview = PreviewSink(tmp_path / "preview.png", interval_s=0.0)
    rec = ZarrRecorder(tmp_path / "rec.zarr", setup.plan, frames=True, metadata={"run": "test"})
    exr = ExrSequenceWriter(tmp_path / "exr", wavelengths=setup.plan.output_wavelengths, every=4)
    report = Stream(setup.driver(loops=2), setup.plan, setup.bundle, outputs=("cube", "XYZ", "dE"),
                    cube_dtype=np.float16, reference=setup.reference, policy="block",
                    sinks=[ring, preview, rec, exr]).run()
    assert report.sequences_out == 8 and report.sink_errors == []
    assert len(ring) == 2 and ring.dropped == 6 and ring.written == 8
    last = ring.get(0)
    assert last.index == 6 and ring.get(0).index == 7 and ring.get(0) is None
    recording = open_recording(tmp_path / "rec.zarr")
    assert recording.sequences == 8 and recording.attrs["metadata"] == {"run": "test"}
    assert recording.attrs["status"] == "complete" and recording.attrs["plan_hash"] == setup.plan.hash
    dE = recording.read("dE", slice(None))
    cube = recording.read("cube", slice(None))
    frame_ids = recording.read("frame_id", slice(None))
    assert dE.shape == (8, 240, 320) and cube.dtype == np.float16 and frame_ids.shape == (8, setup.plan.K)
    for j, ids in enumerate(frame_ids):
        i = setup.recorded_sequence(ids)
        want = expected[i]
        np.testing.assert_allclose(dE[j], want["dE"], atol=2e-3)
        np.testing.assert_allclose(cube[j], want["cube"], atol=2e-3 * np.max(want["cube"]))
        # the raw frames are the replayed recording's, bit for bit
        K = setup.plan.K
        assert np.array_equal(recording.read("frames", j), setup.frames[i * K:(i + 1) * K])
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == [
        f"{n}-{i:06d}.exr" for n in ("XYZ", "cube", "dE") for i in (0, 4)]
    data, _, meta = io.read_map(tmp_path / "exr" / "dE-000004.exr")
    assert meta["frame_ids"] == frame_ids[4].tolist()
    np.testing.assert_allclose(data[..., 0], dE[4], atol=1e-6)
    # the preview renders on its own thread, latest wins: at least one rendering, and at the end the last result's
    assert 1 <= preview.updates <= 8 and (tmp_path / "preview.png").is_file()
    final = PreviewSink(interval_s=0.0, background=False)
    final.write(types.SimpleNamespace(arrays={"XYZ": recording.read("XYZ", 7)}))
    assert preview.image.shape == (240, 320, 3) and np.array_equal(preview.image, final.image)
    with pytest.raises(FileExistsError, match="already exists"):
        ZarrRecorder(tmp_path / "rec.zarr", setup.plan)


def test_bad_arguments_are_one_line_errors(setup):
    args = (setup.driver(), setup.plan, setup.bundle)
    with pytest.raises(ValueError, match="stream output"):
        Stream(*args, outputs=("spectrum",))
    with pytest.raises(ValueError, match="needs a reference"):
        Stream(*args, outputs=("dE",))
    with pytest.raises(ValueError, match="unknown ring policy"):
        Stream(*args, outputs=("XYZ",), policy="wait")
    with pytest.raises(ValueError, match="in_flight"):
        Stream(*args, outputs=("XYZ",), in_flight=4, result_buffers=2)
    with pytest.raises(ValueError, match=r"must be \(3,\) or \(240, 320, 3\)"):
        Stream(*args, outputs=("dE",), reference=np.zeros((2, 3)))


def test_arrival_stamps_stay_bounded_under_drop_oldest(setup):
    """Frames the ring discards unread never reach the device thread; their arrival stamps must not pile up."""
    stream = Stream(setup.driver(pacing="paced"), setup.plan, setup.bundle, outputs=("XYZ",), policy="drop_oldest",
                    sinks=[lambda r: time.sleep(0.1)], n_slots=9, result_buffers=1, in_flight=1)
    report = stream.run(1.0)
    assert report.ring.dropped_oldest > 18
    assert len(stream.driver.arrivals) <= 2 * stream.n_slots + 1


def test_a_driver_error_ends_the_stream_and_is_raised(setup):
    """A camera failing mid-stream: the error reaches the caller; the threads have ended and nothing hangs."""
    inner = setup.driver()
    calls = [0]
    fill = inner.fill

    def failing(out):
        calls[0] += 1
        if calls[0] == 40:
            raise OSError("camera link lost")
        return fill(out)

    inner.fill = failing
    stream = Stream(inner, setup.plan, setup.bundle, outputs=("XYZ",), policy="block")
    t = time.perf_counter()
    with pytest.raises(OSError, match="camera link lost"):
        stream.run(20)
    assert time.perf_counter() - t < 10
    assert not [th for th in threading.enumerate() if th.name.startswith("specgpu-stream")]


def test_saturated_pixels_are_nan_as_offline(setup):
    """A pixel at the sensor's maximum code in any frame of a sequence has no valid measurement: NaN in every
    output of the stream, exactly where ``pipeline.recover`` puts NaN, and the count is on the result."""
    from dataclasses import replace

    frames = setup.frames.copy()
    frames[3, 10:12, 20:25] = setup.bundle.max_code  # sequence 0, pattern 3: 10 pixels
    frames[9 + 8, 100, 200] = setup.bundle.max_code + 5  # sequence 1, last pattern: 1 pixel above the maximum
    sat = replace(setup, frames=frames)
    sink = Collect()
    counts = []
    report = Stream(sat.driver(loops=1), sat.plan, sat.bundle, outputs=ALL, cube_dtype=np.float32,
                    reference=sat.reference, policy="block",
                    sinks=[sink, lambda r: counts.append(r.saturated_pixels)]).run()
    assert report.sequences_out == 4 and counts == [10, 1, 0, 0]
    for ids, maps in sink.results:
        want = offline_maps(sat, sat.recorded_sequence(ids))
        for name in ALL:
            got_nan = np.isnan(maps[name]).reshape(240, 320, -1).any(axis=-1)
            want_nan = np.isnan(want["cube" if name == "coefficients" else name]).reshape(240, 320, -1).any(axis=-1)
            assert np.array_equal(got_nan, want_nan), name
        assert_maps_equal({k: np.nan_to_num(v) for k, v in maps.items() if k != "coefficients"},
                          {k: np.nan_to_num(v) for k, v in want.items()})


def test_a_full_disk_stops_capture_and_keeps_the_committed_sequences(setup, expected, tmp_path, monkeypatch):
    """The recorder fails on its 4th sequence: capture stops at the next sequence boundary (not at the time
    limit), the 3 committed sequences stay readable (xarray too), and the partial one is not in the recording."""
    import xarray as xr

    disk_full_after(monkeypatch, 3)
    rec = ZarrRecorder(tmp_path / "rec.zarr", setup.plan)
    report = Stream(setup.driver(pacing="paced"), setup.plan, setup.bundle, outputs=("XYZ", "dE"),
                    reference=setup.reference, sinks=[rec]).run(30)
    assert report.seconds < 10 and len(report.sink_errors) == 1 and "No space left" in report.sink_errors[0]
    assert report.accounting()["balanced"] and rec.committed == 3
    monkeypatch.undo()
    opened = open_recording(tmp_path / "rec.zarr")
    assert opened.sequences == 3 and opened.attrs["status"] == "failed"
    ds = xr.open_zarr(tmp_path / "rec.zarr")
    assert ds.sizes["time"] == 3 and not np.isnan(ds["dE"].values).all(axis=(1, 2)).any()
    for j in range(3):
        want = expected[setup.recorded_sequence(ds["frame_id"].values[j])]
        np.testing.assert_allclose(ds["dE"].values[j], want["dE"], atol=2e-3)
