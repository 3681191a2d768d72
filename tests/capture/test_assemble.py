"""Sequence assembly and fault drills: only aligned sequences, counters equal to the injected faults."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from specgpu.capture import capture_sequences, open_driver
from specgpu.capture.assemble import SequenceAssembler
from specgpu.capture.driver import FrameInfo, StreamEnd
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.light import LightParameters
from specgpu.rig.twin import FaultSchedule, TwinRig


# ---- an independent model of the rig's behaviour under faults --------------------------------------------------
def simulate(n_frames, k, dropped, duplicated, missed):
    """Per exposure: (frame id, absolute pattern count, delivered?), and the delivery order with duplicates."""
    n, exposures, delivered = -1, [], []
    for fid in range(n_frames):
        if fid == 0 or fid not in missed:
            n += 1
        exposures.append((fid, n, fid not in dropped))
        if fid not in dropped:
            delivered.append((fid, n % k))
            if fid in duplicated:
                delivered.append((fid, n % k))
    return exposures, delivered


def expected_sequences(exposures, k):
    """Cycles that must come out (with their frame ids) and the number that must be discarded."""
    cycles = {}
    for fid, n, ok in exposures:
        cycles.setdefault(n // k, []).append((fid, n % k, ok))
    emitted, discarded = {}, 0
    for c, frames in sorted(cycles.items()):
        for i in range(len(frames) - k + 1):
            run = frames[i:i + k]
            if (all(ok for _, _, ok in run) and [p for _, p, _ in run] == list(range(k))
                    and run[-1][0] - run[0][0] == k - 1):
                emitted[c] = [fid for fid, _, _ in run]
        if c not in emitted and any(ok for _, _, ok in frames):
            discarded += 1
    return emitted, discarded


def max_missed_between_deliveries(n_frames, dropped, missed):
    worst, count = 0, 0
    for fid in range(n_frames):
        if fid in missed:
            count += 1
        if fid not in dropped:
            worst, count = max(worst, count), 0
    return max(worst, count)


@st.composite
def schedules(draw, max_frames=90):
    k = draw(st.integers(1, 6))
    n = draw(st.integers(0, max_frames))
    ids = st.integers(0, max(n - 1, 0))
    dropped = draw(st.frozensets(ids, max_size=n // 4 + 1)) if n else frozenset()
    duplicated = (draw(st.frozensets(ids, max_size=n // 4 + 1)) - dropped) if n else frozenset()
    missed = draw(st.frozensets(st.integers(1, max(n - 1, 1)), max_size=n // 4 + 1)) if n > 1 else frozenset()
    missed = frozenset(m for m in missed if m < n)
    return n, k, dropped, duplicated, missed


# ---- assembler alone, on synthetic streams: many schedules ----------------------------------------------------
@settings(max_examples=300, deadline=None)
@given(schedules())
def test_assembler_counts_equal_injected_faults(schedule):
    n, k, dropped, duplicated, missed = schedule
    # More than K-1 missed triggers between two received frames cannot be told apart by pattern index at all.
    assume(max_missed_between_deliveries(n, dropped, missed) < k)
    exposures, delivered = simulate(n, k, dropped, duplicated, missed)
    asm = SequenceAssembler(k)
    out = []
    for fid, p in delivered:
        frame = np.array([[fid, p]], np.int64)  # content records which frame and which pattern lit it
        seq = asm.push(frame, FrameInfo(fid, p, fid * 0.01, 0.005))
        if seq is not None:
            out.append(seq)
    last = exposures[-1] if exposures else None
    stats = asm.finish(StreamEnd(last[0], last[1] % k) if last else StreamEnd(-1, -1))
    emitted, discarded = expected_sequences(exposures, k)
    assert stats.dropped == len(dropped)
    assert stats.duplicates == len(duplicated)
    assert stats.missed_triggers == len(missed)
    assert stats.sequences_complete == len(out) == len(emitted)
    assert stats.sequences_discarded == discarded
    assert stats.frames_received == len(delivered)
    assert stats.frames_unused == len(delivered) - len(duplicated) - k * len(out)
    for seq in out:
        # Never a frame in another illuminant's slot: slot j holds a frame lit by pattern j; ids consecutive.
        np.testing.assert_array_equal(seq.frames[:, 0, 1], np.arange(k))
        np.testing.assert_array_equal(seq.frame_ids, seq.frames[:, 0, 0])
        np.testing.assert_array_equal(np.diff(seq.frame_ids), 1)
        assert emitted[seq.cycle] == list(seq.frame_ids)


def test_a_worked_example():
    k = 3
    exposures, delivered = simulate(12, k, dropped={4}, duplicated={1}, missed={8})
    asm = SequenceAssembler(k)
    seqs = [s for fid, p in delivered if (s := asm.push(np.zeros((1, 1)), FrameInfo(fid, p, 0.0, 1e-3)))]
    stats = asm.finish(StreamEnd(11, exposures[-1][1] % k))
    # cycle 0: frames 0-2 (frame 1 twice) -> out; cycle 1: frame 4 lost -> discarded;
    # cycle 2: frames 6, 7 then 8 repeats pattern 1 (missed trigger) -> discarded; cycle 3: frames 10, 11 + end.
    assert [s.cycle for s in seqs] == [0]
    assert [list(s.frame_ids) for s in seqs] == [[0, 1, 2]]
    assert seqs[0].frame_records()[2] == {"frame_id": 2, "pattern_index": 2, "exposure_s": 1e-3, "timestamp_s": 0.0}
    assert stats.as_dict() == dict(frames_received=12, duplicates=1, out_of_order=0, dropped=1, missed_triggers=1,
                                   sync_failures=0, sequences_complete=1, sequences_discarded=3, frames_unused=8)


def test_sync_frame_guards_against_a_lying_pattern_index():
    # Hardware that reports pattern indices it did not show: the dark sync frame catches it.
    asm = SequenceAssembler(3, sync_pattern=0, sync_max_dn=10.0)
    dark, bright = np.zeros((2, 2)), np.full((2, 2), 500.0)
    assert asm.push(bright, FrameInfo(0, 0, 0.0, 1e-3)) is None
    assert asm.push(bright, FrameInfo(1, 1, 0.0, 1e-3)) is None
    assert asm.push(bright, FrameInfo(2, 2, 0.0, 1e-3)) is None
    assert asm.stats.sync_failures == 1 and asm.stats.sequences_complete == 0
    asm.push(dark, FrameInfo(3, 0, 0.0, 1e-3))
    asm.push(bright, FrameInfo(4, 1, 0.0, 1e-3))
    seq = asm.push(bright, FrameInfo(5, 2, 0.0, 1e-3))
    assert seq is not None and list(seq.frame_ids) == [3, 4, 5]
    with pytest.raises(ValueError, match="sync_max_dn is required"):
        SequenceAssembler(3, sync_pattern=0)


def test_assembler_rejects_bad_input():
    asm = SequenceAssembler(2)
    with pytest.raises(ValueError, match=r"frame 0: pattern_index 2 outside \[0, 1\] for a 2-pattern sequence"):
        asm.push(np.zeros((1, 1)), FrameInfo(0, 2, 0.0, 1e-3))
    asm.push(np.zeros((1, 1)), FrameInfo(0, 0, 0.0, 1e-3))
    with pytest.raises(ValueError, match=r"frame 1: shape \(2, 2\) differs from the stream's \(1, 1\)"):
        asm.push(np.zeros((2, 2)), FrameInfo(1, 1, 0.0, 1e-3))
    asm.push(np.zeros((1, 1)), FrameInfo(5, 1, 0.0, 1e-3))
    assert asm.push(np.zeros((1, 1)), FrameInfo(3, 1, 0.0, 1e-3)) is None
    assert asm.stats.out_of_order == 1
    asm.finish()
    with pytest.raises(RuntimeError, match="after finish"):
        asm.push(np.zeros((1, 1)), FrameInfo(9, 1, 0.0, 1e-3))
    with pytest.raises(ValueError, match="n_patterns must be >= 1"):
        SequenceAssembler(0)


# ---- the whole path: twin driver -> ring buffer (threads) -> assembler ------------------------------------------
K = 4
LEVELS = (0, 24, 48, 96)  # mirrors on per column: dark, then about 1/8, 1/4, 1/2 of the full well on white


@pytest.fixture(scope="module")
def drill_rig():
    rig = TwinRig(RigDescription(camera=CameraParameters(roi_width=320, roi_height=240),
                                 light=LightParameters(fluctuation_rms=0.0)), scene="white")
    rig.load_sequence(np.stack([np.full(1024, lv, np.int32) for lv in LEVELS]))
    return rig


@settings(max_examples=25, deadline=None)
@given(n=st.integers(8, 60), data=st.data())
def test_fault_drill_through_twin_ring_and_assembler(drill_rig, n, data):
    ids = st.integers(0, n - 1)
    dropped = data.draw(st.frozensets(ids, max_size=n // 5))
    duplicated = data.draw(st.frozensets(ids, max_size=n // 5)) - dropped
    missed = data.draw(st.frozensets(st.integers(1, n - 1), max_size=n // 5))
    assume(max_missed_between_deliveries(n, dropped, missed) < K)
    jitter = data.draw(st.sampled_from([0.0, 5e-6]))  # timing jitter must not matter: ids and indices do
    faults = FaultSchedule(dropped=dropped, duplicated=duplicated, missed_triggers=missed, jitter_s=jitter)
    driver = open_driver("twin", rig=drill_rig, faults=faults, n_frames=n)
    result = capture_sequences(driver, K, n_slots=3, policy="block", sync_pattern=0, sync_max_dn=40.0)
    exposures, _ = simulate(n, K, dropped, duplicated, missed)
    emitted, discarded = expected_sequences(exposures, K)
    a = result.assembly
    assert (a.dropped, a.duplicates, a.missed_triggers) == (len(dropped), len(duplicated), len(missed))
    assert a.sequences_discarded == discarded and a.sync_failures == 0
    assert [s.cycle for s in result.sequences] == sorted(emitted)
    assert result.ring.dropped == 0 and result.ring.finalized == n - len(dropped) + len(duplicated)
    means = np.array([drill_rig.expected_frame(j).mean() for j in range(K)])
    for seq in result.sequences:
        assert list(seq.frame_ids) == emitted[seq.cycle]
        # The pixels say it too: slot j is lit by pattern j (levels are hundreds of DN apart, noise a few DN).
        np.testing.assert_allclose(seq.frames.reshape(K, -1).mean(axis=1), means, atol=2.0)


def test_drop_newest_ring_losses_are_counted_as_gaps(drill_rig):
    """A consumer too slow for the ring: its losses show up as id gaps, and no sequence straddles one."""
    import threading

    from specgpu.capture.assemble import assemble_stream
    from specgpu.capture.ringbuffer import RingBuffer, run_producer

    ring = RingBuffer(2, (240, 320), policy="drop_newest")
    driver = open_driver("twin", rig=drill_rig, n_frames=200)
    driver.start()
    t = threading.Thread(target=run_producer, args=(driver, ring))
    asm = SequenceAssembler(K)
    seqs = []
    t.start()
    for seq in assemble_stream(ring, asm):
        seqs.append(seq)
        threading.Event().wait(0.02)  # a consumer far slower than the twin renders
    t.join()
    stats = asm.finish(driver.stop())
    r = ring.stats()
    assert r.dropped_newest > 0
    assert stats.dropped == r.dropped_newest
    assert stats.sequences_complete == len(seqs)
    for seq in seqs:
        np.testing.assert_array_equal(np.diff(seq.frame_ids), 1)
        assert [int(i) % K for i in seq.frame_ids] == list(range(K))


def test_unknown_driver_name_lists_the_valid_ones():
    with pytest.raises(ValueError, match="unknown driver 'dlpc900'; valid drivers: replay, twin"):
        open_driver("dlpc900")


# ---- content-only alignment ("sync"): the pattern index is not trusted ---------------------------------------
def expected_sync_sequences(exposures, k):
    """Runs of K contiguous delivered frames lit by patterns 0..K-1, confirmed by a delivered dark frame right after."""
    by_id = {fid: (n, ok) for fid, n, ok in exposures}
    emitted = []
    for fid, n, ok in exposures:
        run = [by_id.get(fid + j) for j in range(k + 1)]
        if any(r is None or not r[1] for r in run):
            continue
        if [r[0] - n for r in run] == list(range(k + 1)) and n % k == 0:
            emitted.append(list(range(fid, fid + k)))
    return emitted


@settings(max_examples=300, deadline=None)
@given(schedules())
def test_sync_alignment_never_shifts_a_sequence(schedule):
    n, k, dropped, duplicated, missed = schedule
    assume(k >= 2)
    exposures, delivered = simulate(n, k, dropped, duplicated, missed)
    asm = SequenceAssembler(k, align="sync", sync_max_dn=50.0)
    out = []
    for fid, p in delivered:
        frame = np.array([[0 if p == 0 else 1000, p, fid]], np.int64)  # mean <= 30 only under pattern 0
        # The driver's pattern index is a guess (frame id mod K): wrong after any missed trigger; it must not matter.
        seq = asm.push(frame, FrameInfo(fid, fid % k, fid * 0.01, 0.005))
        if seq is not None:
            out.append(seq)
    stats = asm.finish(StreamEnd(n - 1, -1) if n else None)
    assert [list(s.frame_ids) for s in out] == expected_sync_sequences(exposures, k)
    for seq in out:
        np.testing.assert_array_equal(seq.frames[:, 0, 1], np.arange(k))  # slot j lit by pattern j
        np.testing.assert_array_equal(np.diff(seq.frame_ids), 1)
    assert stats.dropped == len(dropped) and stats.duplicates == len(duplicated)
    assert stats.sequences_complete == len(out)
    assert stats.frames_unused == len(delivered) - len(duplicated) - k * len(out)


@settings(max_examples=20, deadline=None)
@given(n=st.integers(8, 60), data=st.data())
def test_sync_drill_through_twin_ring_and_assembler(drill_rig, n, data):
    ids = st.integers(0, n - 1)
    dropped = data.draw(st.frozensets(ids, max_size=n // 5))
    duplicated = data.draw(st.frozensets(ids, max_size=n // 5)) - dropped
    missed = data.draw(st.frozensets(st.integers(1, n - 1), max_size=n // 5))
    faults = FaultSchedule(dropped=dropped, duplicated=duplicated, missed_triggers=missed)
    driver = open_driver("twin", rig=drill_rig, faults=faults, n_frames=n)
    result = capture_sequences(driver, K, n_slots=3, align="sync", sync_max_dn=40.0)
    seqs, stats = result.sequences, result.assembly
    exposures, _ = simulate(n, K, dropped, duplicated, missed)
    assert [list(s.frame_ids) for s in seqs] == expected_sync_sequences(exposures, K)
    assert stats.dropped == len(dropped) and stats.duplicates == len(duplicated)
    means = np.array([drill_rig.expected_frame(j).mean() for j in range(K)])
    for seq in seqs:
        np.testing.assert_allclose(seq.frames.reshape(K, -1).mean(axis=1), means, atol=2.0)


def test_sync_mode_validation():
    with pytest.raises(ValueError, match="sync_max_dn is required with align='sync'"):
        SequenceAssembler(3, align="sync")
    with pytest.raises(ValueError, match="uses pattern 0 as the dark sync pattern"):
        SequenceAssembler(3, align="sync", sync_pattern=1, sync_max_dn=5.0)
    with pytest.raises(ValueError, match="needs n_patterns >= 2"):
        SequenceAssembler(1, align="sync", sync_max_dn=5.0)
    with pytest.raises(ValueError, match="align must be one of index, sync"):
        SequenceAssembler(3, align="content")
