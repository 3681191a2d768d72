"""The capture loop: a driver fills ring-buffer slots on a producer thread; the assembler consumes them.

This is the one path every backend goes through (twin or hardware), used by the CLI's ``capture`` command, by
calibration and by the fault drills.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from specgpu.capture.assemble import AssemblyStats, SequenceAssembler, assemble_stream
from specgpu.capture.driver import CameraDriver, StreamEnd
from specgpu.capture.ringbuffer import RingBuffer, RingStats, run_producer

__all__ = ["CaptureResult", "capture_sequences"]


@dataclass(frozen=True)
class CaptureResult:
    """What :func:`capture_sequences` returns.

    Attributes
    ----------
    sequences : list of Sequence
        The complete, aligned sequences, in order.
    assembly : AssemblyStats
        The assembler's counters (drops, duplicates, missed triggers, discarded sequences ...).
    ring : RingStats
        The ring buffer's counters.
    end : StreamEnd
        The driver's account of its last exposure.
    """

    sequences: list
    assembly: AssemblyStats
    ring: RingStats
    end: StreamEnd


def capture_sequences(driver: CameraDriver, n_patterns: int, *, n_slots: int = 8, policy: str = "block",
                      align: str = "index", sync_pattern: int | None = None, sync_max_dn: float | None = None,
                      on_sequence=None) -> CaptureResult:
    """Run a bounded driver stream (e.g. ``TwinDriver(n_frames=...)``) through ring buffer and assembler.

    Parameters
    ----------
    driver
        A driver whose stream ends by itself (``fill`` returns ``None``).
    n_patterns
        Length K of the light's loaded sequence.
    n_slots, policy
        Ring buffer size and full policy (``"block"``, ``"drop_oldest"``, ``"drop_newest"``).
    align, sync_pattern, sync_max_dn
        Alignment by the driver's pattern index (``"index"``, optionally checking a dark sync pattern) or by content
        alone (``"sync"``), see :class:`SequenceAssembler`.
    on_sequence
        Optional callable given each sequence as it completes; when given, sequences are not kept in the result
        (for long runs).
    """
    ring = RingBuffer(n_slots, driver.frame_shape, driver.dtype, policy)
    assembler = SequenceAssembler(n_patterns, align=align, sync_pattern=sync_pattern, sync_max_dn=sync_max_dn)
    errors = []

    def produce():
        try:
            run_producer(driver, ring)
        except BaseException as exc:  # surfaced in the caller's thread below
            errors.append(exc)
            ring.close()

    driver.start()
    thread = threading.Thread(target=produce, name="specgpu-capture", daemon=True)
    thread.start()
    sequences = []
    try:
        for seq in assemble_stream(ring, assembler):
            if on_sequence is not None:
                on_sequence(seq)
            else:
                sequences.append(seq)
    finally:
        ring.close()
        thread.join()
        end = driver.stop()
    if errors:
        raise errors[0]
    stats = assembler.finish(end)
    return CaptureResult(sequences, stats, ring.stats(), end)
