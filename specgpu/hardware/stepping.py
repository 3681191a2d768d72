"""The pattern a light shows when its controller steps through a loaded sequence on each camera trigger.

The DLPC900, the LED controller board and the OL490 all advance one pattern per trigger edge by themselves; the
host only follows: exposure ``n`` after a start was lit by pattern ``n mod K``.
"""

from __future__ import annotations


class TriggerStepped:
    """The host's view of a trigger-stepped sequence: the pattern now shown and the exposure last asked of
    :meth:`at_frame`. A subclass provides ``sequence`` (K, C) and calls :meth:`_restart` when it starts."""

    _index: int = 0
    _frame: int = -1

    def _restart(self) -> None:
        """Back to pattern 0, no exposure asked yet (a start, or a new sequence loaded)."""
        self._index, self._frame = 0, -1

    def trigger(self) -> int:
        """Count one hardware trigger (the controller advanced by itself); return the pattern now shown."""
        self._index = (self._index + 1) % self.sequence.shape[0]
        return self._index

    def at_frame(self, frame_id: int) -> int:
        """The pattern that lit exposure ``frame_id`` of the stream (0 is the first exposure after start)."""
        self._frame = int(frame_id)
        self._index = self._frame % self.sequence.shape[0]
        return self._index

    @property
    def pattern_index(self) -> int:
        """The pattern now shown."""
        return self._index
