"""Public names of :mod:`specgpu.capture`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .assemble import AssemblyStats, Sequence, SequenceAssembler, assemble_stream
from .driver import DRIVERS, CameraDriver, FrameInfo, LightSource, StreamEnd, open_driver
from .ringbuffer import POLICIES, RingBuffer, RingStats, Slot, run_producer
from .session import CaptureResult, capture_sequences

__all__ = [
    "assemble_stream",
    "AssemblyStats",
    "CameraDriver",
    "capture_sequences",
    "CaptureResult",
    "DRIVERS",
    "FrameInfo",
    "LightSource",
    "open_driver",
    "POLICIES",
    "RingBuffer",
    "RingStats",
    "run_producer",
    "Sequence",
    "SequenceAssembler",
    "Slot",
    "StreamEnd",
]
