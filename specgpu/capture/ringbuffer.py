r"""A preallocated ring of frame slots between the acquisition thread and its consumer.

The producer ``acquire()``\ s a free slot, lets the driver fill it in place (zero copy), and ``finalize()``\ s it
with the frame's metadata; the consumer ``get()``\ s the oldest finalized slot, reads it, and ``release()``\ s it.
Slots are views into one (n_slots, H, W) array allocated once.

When no slot is free, the policy decides (explicitly chosen, never implicit):

- ``"block"``: the producer waits until the consumer releases a slot (no frame is ever lost here);
- ``"drop_oldest"``: the oldest finalized-but-unread frame is discarded and its slot reused (live view);
- ``"drop_newest"``: ``acquire`` returns ``None`` and the new frame is discarded (keeps a contiguous head).

Counters are exact under any interleaving: ``finalized == delivered + dropped_oldest + pending`` at all times,
and ``dropped_newest`` counts every refused acquire. Dropped frames also show as frame-id gaps downstream, which is
how the assembler keeps sequences aligned. All methods are thread-safe.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import DTypeLike

from specgpu.capture.driver import FrameInfo
from specgpu.core.validate import check_number

__all__ = ["RingBuffer", "Slot", "RingStats", "POLICIES", "run_producer"]

POLICIES = ("block", "drop_oldest", "drop_newest")

_FREE, _FILLING, _READY, _READING = range(4)


class Slot:
    """One slot of the ring: ``array`` is a view into the preallocated storage; ``info`` is set on finalize."""

    __slots__ = ("index", "array", "info", "_state", "_generation")

    def __init__(self, index: int, array: np.ndarray):
        self.index = index
        self.array = array
        self.info: FrameInfo | None = None
        self._state = _FREE
        self._generation = 0

    def __repr__(self):
        return f"Slot(index={self.index}, info={self.info})"


@dataclass(frozen=True)
class RingStats:
    """A consistent snapshot of the ring's counters.

    Attributes
    ----------
    acquired : int
        Slots handed to the producer.
    finalized : int
        Frames the producer completed.
    abandoned : int
        Slots the producer gave back unfilled.
    delivered : int
        Frames handed to the consumer.
    released : int
        Slots the consumer gave back.
    dropped_oldest : int
        Finalized frames discarded unread to make room (``"drop_oldest"``).
    dropped_newest : int
        Acquires refused because the ring was full (``"drop_newest"``).
    blocked_waits : int
        Times the producer had to wait for a free slot (``"block"``).
    pending : int
        Finalized frames not yet delivered.
    high_water : int
        Largest ``pending`` seen.
    """

    acquired: int
    finalized: int
    abandoned: int
    delivered: int
    released: int
    dropped_oldest: int
    dropped_newest: int
    blocked_waits: int
    pending: int
    high_water: int

    @property
    def dropped(self) -> int:
        return self.dropped_oldest + self.dropped_newest


def wait_for_items(cond: threading.Condition, items, closed, timeout: float | None) -> bool:
    """With ``cond`` held: wait until ``items()`` is non-empty (True), or until ``closed()`` with nothing left, or
    ``timeout`` seconds have passed (False). The one wait loop of the capture queues."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while not items():
        if closed():
            return False
        remaining = None if deadline is None else deadline - time.monotonic()
        if remaining is not None and remaining <= 0:
            return False
        cond.wait(remaining)
    return True


class RingBuffer:
    """Fixed ring of ``n_slots`` preallocated frame slots with an explicit full policy.

    Parameters
    ----------
    n_slots
        Number of slots, >= 2.
    frame_shape
        (height, width) of a frame.
    dtype
        Frame dtype (uint16 for the twin).
    policy
        ``"block"``, ``"drop_oldest"`` or ``"drop_newest"`` (see the module docstring).
    """

    def __init__(self, n_slots: int, frame_shape, dtype: DTypeLike = np.uint16, policy: str = "block"):
        n = check_number("n_slots", n_slots, low=2, high=1 << 20, integer=True)
        if policy not in POLICIES:
            raise ValueError(f"unknown ring policy {policy!r}; valid policies: {', '.join(POLICIES)}")
        shape = tuple(int(s) for s in frame_shape)
        if len(shape) < 1 or any(s < 1 for s in shape):
            raise ValueError(f"frame_shape must be positive dimensions, got {frame_shape!r}")
        self.policy = policy
        self.storage = np.zeros((n,) + shape, dtype=dtype)
        self.slots = [Slot(i, self.storage[i]) for i in range(n)]
        self._free: deque[Slot] = deque(self.slots)
        self._ready: deque[Slot] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._c = dict(acquired=0, finalized=0, abandoned=0, delivered=0, released=0, dropped_oldest=0,
                       dropped_newest=0, blocked_waits=0, high_water=0)

    @property
    def n_slots(self) -> int:
        return len(self.slots)

    # ---- producer -----------------------------------------------------------------------------------------
    def acquire(self, timeout: float | None = None, *, count_drop: bool = True) -> Slot | None:
        """A free slot to fill in place, or ``None`` (policy ``drop_newest`` when full, closed ring, or timeout).

        Under ``drop_newest`` a refusal is counted as a dropped frame; a producer that only learns afterwards
        whether a frame was really there (the stream may have just ended) passes ``count_drop=False`` and calls
        :meth:`count_dropped_newest` once it has consumed the frame. Under ``drop_oldest`` a full ring discards its
        oldest unread frame; if every slot is held by the consumer (nothing to discard), it waits like ``block``.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            waited = False
            while True:
                if self._closed:
                    return None
                if self._free:
                    slot = self._free.popleft()
                    break
                if self.policy == "drop_newest":
                    if count_drop:
                        self._c["dropped_newest"] += 1
                    return None
                if self.policy == "drop_oldest" and self._ready:
                    slot = self._ready.popleft()
                    self._c["dropped_oldest"] += 1
                    break
                if not waited:
                    self._c["blocked_waits"] += 1
                    waited = True
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            slot._state = _FILLING
            slot._generation += 1
            slot.info = None
            self._c["acquired"] += 1
            return slot

    def count_dropped_newest(self) -> None:
        """Count one frame lost because the ring was full (see ``acquire(count_drop=False)``)."""
        with self._cond:
            self._c["dropped_newest"] += 1

    def finalize(self, slot: Slot, info: FrameInfo) -> None:
        """Publish a filled slot with its metadata to the consumer."""
        with self._cond:
            self._check(slot, _FILLING, "finalize")
            slot.info = info
            slot._state = _READY
            self._ready.append(slot)
            self._c["finalized"] += 1
            self._c["high_water"] = max(self._c["high_water"], len(self._ready))
            self._cond.notify_all()

    def abandon(self, slot: Slot) -> None:
        """Give back an acquired slot unfilled (e.g. the stream ended)."""
        with self._cond:
            self._check(slot, _FILLING, "abandon")
            slot._state = _FREE
            self._free.append(slot)
            self._c["abandoned"] += 1
            self._cond.notify_all()

    def close(self) -> None:
        """No more frames: consumers drain what is pending, then ``get`` returns ``None``; blocked calls wake."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # ---- consumer -----------------------------------------------------------------------------------------
    def get(self, timeout: float | None = None) -> Slot | None:
        """The oldest finalized slot (read it, then :meth:`release` it), or ``None`` when closed and drained or on
        timeout."""
        with self._cond:
            if not wait_for_items(self._cond, lambda: self._ready, lambda: self._closed, timeout):
                return None
            slot = self._ready.popleft()
            slot._state = _READING
            self._c["delivered"] += 1
            return slot

    def release(self, slot: Slot) -> None:
        """Return a slot the consumer has finished reading."""
        with self._cond:
            self._check(slot, _READING, "release")
            slot._state = _FREE
            self._free.append(slot)
            self._c["released"] += 1
            self._cond.notify_all()

    def _check(self, slot: Slot, state: int, what: str) -> None:
        if not isinstance(slot, Slot) or slot.index >= len(self.slots) or self.slots[slot.index] is not slot:
            raise ValueError(f"{what}: slot does not belong to this ring buffer")
        if slot._state != state:
            names = {_FREE: "free", _FILLING: "being filled", _READY: "ready", _READING: "being read"}
            raise ValueError(f"{what}: slot {slot.index} is {names[slot._state]}, expected {names[state]}")

    # ---- accounting ---------------------------------------------------------------------------------------
    def stats(self) -> RingStats:
        with self._cond:
            return RingStats(pending=len(self._ready), **self._c)

    @property
    def closed(self) -> bool:
        return self._closed


def run_producer(driver, ring: RingBuffer, *, stop_event: threading.Event | None = None) -> int:
    """Acquisition loop: fill ring slots from a started driver until its stream ends (or ``stop_event``).

    A frame the ring has no slot for (``drop_newest``) is still taken from the driver (``fill(None)``), because the
    camera does not wait. Closes the ring at the end. Returns the number of frames finalized.
    """
    count = 0
    try:
        while stop_event is None or not stop_event.is_set():
            slot = ring.acquire(count_drop=False)
            if slot is None:
                if ring.closed:
                    break
                if driver.fill(None) is None:
                    break  # the stream had ended: no frame was lost
                ring.count_dropped_newest()
                continue
            info = driver.fill(slot.array)
            if info is None:
                ring.abandon(slot)
                break
            ring.finalize(slot, info)
            count += 1
    finally:
        ring.close()
    return count
