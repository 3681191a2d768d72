"""Frames -> complete illumination sequences, keyed by frame id and pattern index.

A sequence is K frames lit by patterns 0, 1, ..., K-1 of one pass (a *cycle*) of the light's loaded sequence,
with **consecutive frame ids**: nothing lost, nothing repeated, nothing shifted in between. Only such sequences
are emitted; every other frame is set aside and counted, so a missing frame is reported, never slid into the next
illuminant's slot.

Bookkeeping from (frame id, pattern index) alone, per received frame after the previous one:

- ids that do not advance are duplicates (same id again) or out of order (older id): ignored, counted;
- an id gap of ``g`` means ``g`` frames were lost (by the camera link, the driver or a full ring buffer);
- the light advanced once per exposure unless a trigger was missed, so
  ``missed = (p_prev + (id - id_prev) - p) mod K`` triggers were missed in between (exact while fewer than K are
  missed between two received frames; more cannot be told apart from the pattern index at all);
- the light's absolute pattern count ``n`` follows, and ``n // K`` is the cycle each frame belongs to.

A cycle with at least one received frame that does not yield a complete sequence is *discarded* and counted.
With a dark sync pattern in the sequence (``sync_pattern``), its frame is also checked to be dark: a belt-and-braces
guard for hardware whose pattern index cannot be trusted.

``align="sync"`` is for hardware that cannot say which pattern it showed (a light source that only counts
triggers, a camera whose "pattern index" is just ``frame_id mod K``): the pattern index is ignored and sequences
are found from the content alone. Pattern 0 must be dark (all mirrors off), every other pattern must give a mean
above ``sync_max_dn``. A sequence is a dark frame followed by K - 1 bright frames with consecutive ids, and it is
emitted only once the frame right after it (id + K) arrives dark as well: a missed trigger anywhere inside the
sequence delays the next dark frame, so a sequence is never emitted shifted. The price is one frame of latency and
the loss of the last sequence of a stream (never confirmed) and of any sequence whose successor's dark frame is
lost or late. Drops and duplicates are still counted exactly from the ids; missed triggers are not observable as
such, and show as ``sync_failures`` (dark frames early or late).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from specgpu.capture.driver import FrameInfo, StreamEnd
from specgpu.core.validate import check_number

__all__ = ["Sequence", "AssemblyStats", "SequenceAssembler", "assemble_stream"]


@dataclass(frozen=True)
class Sequence:
    """One complete, aligned illumination sequence.

    Attributes
    ----------
    frames : numpy.ndarray
        (K, H, W) frames; ``frames[j]`` was lit by pattern ``j``.
    frame_ids : numpy.ndarray
        (K,) int64 consecutive frame ids.
    timestamps_s : numpy.ndarray
        (K,) exposure start times, s.
    exposure_s : float
        Exposure of the frames, s.
    cycle : int
        Index mode: which pass through the loaded sequence this is (0 for the first since the start). Sync mode:
        the ordinal of the dark frame that opened it among all dark frames that opened a sequence.
    """

    frames: np.ndarray
    frame_ids: np.ndarray
    timestamps_s: np.ndarray
    exposure_s: float
    cycle: int

    def frame_records(self) -> list[dict]:
        """Per frame: frame id, pattern index (its slot), exposure and timestamp, as plain data (e.g. for the
        ``sequence.json`` of a saved capture)."""
        return [{"frame_id": int(fid), "pattern_index": j, "exposure_s": self.exposure_s, "timestamp_s": float(ts)}
                for j, (fid, ts) in enumerate(zip(self.frame_ids, self.timestamps_s))]


@dataclass
class AssemblyStats:
    """Exact counters of the assembler.

    Attributes
    ----------
    frames_received : int
        Frames pushed (duplicates included).
    duplicates : int
        Frames whose id equals the previous frame's.
    out_of_order : int
        Frames with an id older than the previous frame's.
    dropped : int
        Frames missing from the id sequence (gaps, and trailing ones known at :meth:`SequenceAssembler.finish`).
    missed_triggers : int
        Triggers the light missed, inferred from pattern indices.
    sync_failures : int
        Index mode: sync-pattern frames that were not dark. Sync mode: dark frames that came early or late.
    sequences_complete : int
        Sequences emitted.
    sequences_discarded : int
        Index mode: cycles with received frames that yielded no complete sequence. Sync mode: sequences opened by
        a dark frame that were not emitted.
    frames_unused : int
        Received, non-duplicate, in-order frames that are in no emitted sequence.
    """

    frames_received: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    dropped: int = 0
    missed_triggers: int = 0
    sync_failures: int = 0
    sequences_complete: int = 0
    sequences_discarded: int = 0
    frames_unused: int = 0

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class SequenceAssembler:
    """Assemble pushed frames into complete sequences of ``n_patterns`` frames.

    Parameters
    ----------
    n_patterns
        K, the length of the light's loaded sequence, >= 1.
    first_frame_id
        Id of the first exposure of the stream (frames before it are not counted as lost).
        The light shows pattern 0 at that exposure.
    align
        ``"index"`` (default): trust the driver's pattern index. ``"sync"``: ignore it and align on the dark
        pattern 0 (see the module docstring); needs ``sync_max_dn`` and K >= 2.
    sync_pattern
        Index mode: optional index of a dark pattern in the sequence whose frame must be dark.
    sync_max_dn
        Mean level (DN) at or below which a frame counts as dark; required with ``sync_pattern`` or ``"sync"``.
    """

    def __init__(self, n_patterns: int, *, first_frame_id: int = 0, align: str = "index",
                 sync_pattern: int | None = None, sync_max_dn: float | None = None):
        self.k = check_number("n_patterns", n_patterns, low=1, high=1 << 20, integer=True)
        self.first_frame_id = check_number("first_frame_id", first_frame_id, low=0, integer=True)
        if align not in ("index", "sync"):
            raise ValueError(f"align must be one of index, sync, got {align!r}")
        self.align = align
        if align == "sync":
            if self.k < 2:
                raise ValueError("align='sync' needs n_patterns >= 2 (a dark pattern 0 and at least one other)")
            if sync_pattern not in (None, 0):
                raise ValueError("align='sync' uses pattern 0 as the dark sync pattern, "
                                 f"got sync_pattern={sync_pattern}")
            if sync_max_dn is None:
                raise ValueError("sync_max_dn is required with align='sync' (the brightest mean a dark frame may have)")
            check_number("sync_max_dn", sync_max_dn)
            self._pending = None
            self._openings = 0
        elif sync_pattern is not None:
            check_number("sync_pattern", sync_pattern, low=0, high=self.k - 1, integer=True)
            if sync_max_dn is None:
                raise ValueError("sync_max_dn is required with sync_pattern (the darkest level a sync frame may have)")
            check_number("sync_max_dn", sync_max_dn)
        self.sync_pattern = sync_pattern
        self.sync_max_dn = sync_max_dn
        self.stats = AssemblyStats()
        self._last_id = self.first_frame_id - 1
        self._last_n = -1  # absolute pattern count: frame 0 is lit by pattern count 0
        self._cycle = None  # cycle of the latest frame
        self._cycle_emitted = False
        self._buf = None
        self._ids = np.zeros(self.k, np.int64)
        self._ts = np.zeros(self.k)
        self._next = -1  # next position expected in the partial sequence, -1 when none is open
        self._finished = False

    def push(self, frame: np.ndarray, info: FrameInfo) -> Sequence | None:
        """Add one frame (copied); return the sequence it completes, if any."""
        if self._finished:
            raise RuntimeError("push() after finish()")
        if self.align == "sync":
            return self._push_sync(frame, info)
        k = self.k
        fid, p = int(info.frame_id), int(info.pattern_index)
        if not 0 <= p < k:
            raise ValueError(f"frame {fid}: pattern_index {p} outside [0, {k - 1}] for a {k}-pattern sequence")
        st = self.stats
        st.frames_received += 1
        if fid <= self._last_id:
            if fid == self._last_id:
                st.duplicates += 1
            else:
                st.out_of_order += 1
            return None
        if fid < self.first_frame_id:
            st.out_of_order += 1
            return None
        steps = fid - self._last_id
        st.dropped += steps - 1
        missed = (self._last_n + steps - p) % k
        st.missed_triggers += missed
        n = self._last_n + steps - missed
        self._last_id, self._last_n = fid, n
        cycle, pos = divmod(n, k)
        if cycle != self._cycle:
            self._close_cycle()
            self._cycle, self._cycle_emitted = cycle, False
        st.frames_unused += 1
        if self._cycle_emitted:
            return None  # e.g. the last pattern shown again after a missed trigger: the sequence is already out
        if pos == 0:
            self._next = 0
            self._start_id = fid
        elif not (self._next == pos and fid == self._start_id + pos):
            self._next = -1
            return None
        if self.sync_pattern is not None and pos == self.sync_pattern:
            if float(np.mean(frame)) > self.sync_max_dn:
                st.sync_failures += 1
                self._next = -1
                return None
        self._store(frame, info, pos)
        self._next = pos + 1
        if self._next < k:
            return None
        seq = Sequence(self._buf, self._ids.copy(), self._ts.copy(), float(info.exposure_s), cycle)
        self._buf = None  # the emitted array now belongs to the consumer
        self._next = -1
        self._cycle_emitted = True
        st.sequences_complete += 1
        st.frames_unused -= k
        return seq

    def _store(self, frame: np.ndarray, info: FrameInfo, pos: int) -> None:
        if self._buf is None:
            self._buf = np.empty((self.k,) + frame.shape, frame.dtype)
        elif self._buf.shape[1:] != frame.shape:
            raise ValueError(f"frame {info.frame_id}: shape {frame.shape} differs from the stream's "
                             f"{self._buf.shape[1:]}")
        self._buf[pos] = frame
        self._ids[pos] = info.frame_id
        self._ts[pos] = info.timestamp_s

    def _push_sync(self, frame: np.ndarray, info: FrameInfo) -> Sequence | None:
        k, st = self.k, self.stats
        fid = int(info.frame_id)
        st.frames_received += 1
        if fid <= self._last_id or fid < self.first_frame_id:
            if fid == self._last_id:
                st.duplicates += 1
            else:
                st.out_of_order += 1
            return None
        st.dropped += fid - self._last_id - 1
        self._last_id = fid
        st.frames_unused += 1
        dark = float(np.mean(frame)) <= self.sync_max_dn
        out = None
        if self._pending is not None:
            seq = self._pending
            self._pending = None
            if dark and fid == int(seq.frame_ids[0]) + k:
                out = seq  # confirmed: exactly K advances of the light since the last dark frame
                st.sequences_complete += 1
                st.frames_unused -= k
            else:
                st.sequences_discarded += 1
                if fid == int(seq.frame_ids[0]) + k:
                    st.sync_failures += 1  # bright where the next dark frame belongs: late sync (missed trigger)
                # (a later id means the confirming frame was lost: counted as dropped, not as a sync failure)
        if dark:
            if self._next > 0:
                # A dark frame inside an open sequence. Contiguous: early sync (right after the opening dark frame it
                # is the light still dark, a missed trigger on pattern 1); after a gap: the drop broke the sequence.
                if fid == self._start_id + self._next:
                    st.sync_failures += 1
                st.sequences_discarded += 1
            self._next = 0
            self._start_id = fid
            self._openings += 1
        elif not (self._next > 0 and fid == self._start_id + self._next):
            if self._next > 0:
                st.sequences_discarded += 1
            self._next = -1
            return out
        self._store(frame, info, self._next)
        self._next += 1
        if self._next == k:
            self._pending = Sequence(self._buf, self._ids.copy(), self._ts.copy(), float(info.exposure_s),
                                     self._openings - 1)
            self._buf = None
            self._next = -1
        return out

    def _close_cycle(self) -> None:
        if self._cycle is not None and not self._cycle_emitted:
            self.stats.sequences_discarded += 1
        self._next = -1

    def finish(self, end: StreamEnd | None = None) -> AssemblyStats:
        """End of stream: account frames lost after the last received one (if the driver's ``end`` is given) and
        discard the unfinished cycle. Returns the final counters."""
        if not self._finished and self.align == "sync":
            if end is not None and end.last_frame_id > self._last_id:
                self.stats.dropped += end.last_frame_id - self._last_id
            if self._pending is not None or self._next > 0:
                self.stats.sequences_discarded += 1
            self._pending, self._next = None, -1
            self._finished = True
        if not self._finished:
            if end is not None and end.last_frame_id > self._last_id:
                steps = end.last_frame_id - self._last_id
                self.stats.dropped += steps
                if 0 <= end.last_pattern_index < self.k:
                    self.stats.missed_triggers += (self._last_n + steps - end.last_pattern_index) % self.k
            self._close_cycle()
            self._cycle = None
            self._finished = True
        return self.stats


def assemble_stream(ring, assembler: SequenceAssembler, *, timeout: float | None = None):
    """Consume a ring buffer until it is closed and drained, yielding complete sequences.

    Each slot is copied into the assembler and released at once, so the producer is never held up by a slow
    consumer of sequences.
    """
    while True:
        slot = ring.get(timeout)
        if slot is None:
            return
        try:
            seq = assembler.push(slot.array, slot.info)
        finally:
            ring.release(slot)
        if seq is not None:
            yield seq
