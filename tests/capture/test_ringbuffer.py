"""The ring buffer: zero-copy slots, explicit full policies, exact counters under threads."""

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.capture.driver import FrameInfo
from specgpu.capture.ringbuffer import RingBuffer


def info(i):
    return FrameInfo(i, 0, i * 1e-3, 1e-3)


def produce(ring, n, shape_value=True):
    """Producer: write frame id into the slot in place; returns ids that found no slot."""
    refused = []
    for i in range(n):
        slot = ring.acquire()
        if slot is None:
            refused.append(i)
            continue
        slot.array[...] = i % 65536
        ring.finalize(slot, info(i))
    ring.close()
    return refused


def test_slots_are_views_into_one_preallocated_array():
    ring = RingBuffer(3, (4, 5))
    slot = ring.acquire()
    assert np.shares_memory(slot.array, ring.storage)
    slot.array[...] = 7
    ring.finalize(slot, info(0))
    got = ring.get()
    assert got is slot and got.info == info(0) and np.all(ring.storage[slot.index] == 7)
    ring.release(got)
    s = ring.stats()
    assert (s.acquired, s.finalized, s.delivered, s.released, s.pending) == (1, 1, 1, 1, 0)


@pytest.mark.parametrize("n_slots", [2, 5])
def test_block_policy_loses_nothing_under_threads(n_slots):
    n = 20000
    ring = RingBuffer(n_slots, (8, 8), policy="block")
    seen = []

    def consume():
        while (slot := ring.get()) is not None:
            seen.append((slot.info.frame_id, int(slot.array[0, 0]), int(slot.array[-1, -1])))
            ring.release(slot)

    t = threading.Thread(target=consume)
    t.start()
    refused = produce(ring, n)
    t.join()
    assert refused == []
    assert [s[0] for s in seen] == list(range(n))  # no frame lost, duplicated or reordered
    assert all(a == b == fid % 65536 for fid, a, b in seen)  # content matches its metadata
    st_ = ring.stats()
    assert (st_.finalized, st_.delivered, st_.released, st_.dropped, st_.pending) == (n, n, n, 0, 0)
    assert st_.high_water <= n_slots


def test_drop_newest_counts_exactly_and_keeps_the_head():
    ring = RingBuffer(4, (2, 2), policy="drop_newest")
    refused = produce(ring, 10)  # nobody consumes: 4 fit, 6 refused
    assert refused == [4, 5, 6, 7, 8, 9]
    s = ring.stats()
    assert (s.finalized, s.dropped_newest, s.dropped_oldest, s.pending) == (4, 6, 0, 4)
    ids = []
    while (slot := ring.get()) is not None:
        ids.append(slot.info.frame_id)
        ring.release(slot)
    assert ids == [0, 1, 2, 3]


def test_drop_oldest_counts_exactly_and_keeps_the_tail():
    ring = RingBuffer(4, (2, 2), policy="drop_oldest")
    produce(ring, 10)
    s = ring.stats()
    assert (s.finalized, s.dropped_oldest, s.dropped_newest, s.pending) == (10, 6, 0, 4)
    ids = []
    while (slot := ring.get()) is not None:
        assert int(slot.array[0, 0]) == slot.info.frame_id  # the reused slot holds the new frame, not the old
        ids.append(slot.info.frame_id)
        ring.release(slot)
    assert ids == [6, 7, 8, 9]


@pytest.mark.parametrize("policy", ["drop_oldest", "drop_newest"])
def test_drop_policies_have_exact_counters_under_threads(policy):
    n = 20000
    ring = RingBuffer(3, (4, 4), policy=policy)
    seen = []

    def consume():
        while (slot := ring.get()) is not None:
            seen.append(slot.info.frame_id)
            if len(seen) % 7 == 0:
                threading.Event().wait(1e-5)  # a slow consumer, so the ring does fill up
            ring.release(slot)

    t = threading.Thread(target=consume)
    t.start()
    refused = produce(ring, n)
    t.join()
    s = ring.stats()
    assert seen == sorted(seen) and len(set(seen)) == len(seen)  # order kept, nothing twice
    assert s.delivered == len(seen)
    lost = n - len(seen)
    assert lost > 0
    if policy == "drop_newest":
        assert s.dropped_newest == len(refused) == lost and s.dropped_oldest == 0
        assert s.finalized == len(seen)
    else:
        assert refused == [] and s.dropped_oldest == lost and s.finalized == n
    # The lost ids are exactly the gaps a consumer sees in the id sequence.
    gaps = sum(b - a - 1 for a, b in zip([-1] + seen, seen + [n]))
    assert gaps == lost


@settings(max_examples=60, deadline=None)
@given(n_slots=st.integers(2, 6), ops=st.lists(st.sampled_from(["put", "get"]), max_size=60),
       policy=st.sampled_from(["drop_oldest", "drop_newest"]))
def test_counters_match_a_model_for_any_interleaving(n_slots, ops, policy):
    """Single-threaded interleavings against a reference deque model."""
    ring = RingBuffer(n_slots, (1,), policy=policy)
    model, next_id, dropped, got = [], 0, 0, []
    for op in ops:
        if op == "put":
            slot = ring.acquire()
            if len(model) == n_slots:
                dropped += 1
                if policy == "drop_newest":
                    assert slot is None
                    next_id += 1
                    continue
                model.pop(0)
            slot.array[0] = next_id
            ring.finalize(slot, info(next_id))
            model.append(next_id)
            next_id += 1
        elif model:
            slot = ring.get(timeout=0)
            got.append(slot.info.frame_id)
            assert got[-1] == model.pop(0) == int(slot.array[0])
            ring.release(slot)
        else:
            assert ring.get(timeout=0) is None
    s = ring.stats()
    assert s.dropped == dropped and s.pending == len(model) and s.delivered == len(got)
    assert s.finalized == s.delivered + s.dropped_oldest + s.pending


def test_block_policy_waits_and_times_out():
    ring = RingBuffer(2, (1,), policy="block")
    a, b = ring.acquire(), ring.acquire()
    assert ring.acquire(timeout=0.01) is None
    assert ring.stats().blocked_waits == 1
    ring.finalize(a, info(0))

    def later():
        threading.Event().wait(0.05)
        ring.release(ring.get())

    t = threading.Thread(target=later)
    t.start()
    c = ring.acquire(timeout=5)
    t.join()
    assert c is a
    ring.abandon(b)
    ring.abandon(c)
    ring.close()
    assert ring.get() is None and ring.acquire() is None


def test_misuse_is_refused():
    ring = RingBuffer(2, (1,))
    other = RingBuffer(2, (1,))
    slot = ring.acquire()
    with pytest.raises(ValueError, match="release: slot 0 is being filled, expected being read"):
        ring.release(slot)
    with pytest.raises(ValueError, match="slot does not belong to this ring buffer"):
        other.finalize(slot, info(0))
    ring.finalize(slot, info(0))
    with pytest.raises(ValueError, match="finalize: slot 0 is ready, expected being filled"):
        ring.finalize(slot, info(0))
    with pytest.raises(ValueError, match="unknown ring policy 'lossy'; valid policies: block, drop_oldest"):
        RingBuffer(2, (1,), policy="lossy")
    with pytest.raises(ValueError, match="n_slots must be >= 2"):
        RingBuffer(1, (1,))
