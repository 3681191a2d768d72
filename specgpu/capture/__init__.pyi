"""Public names of :mod:`specgpu.capture`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .assemble import Sequence, SequenceAssembler
from .driver import DRIVERS, CameraDriver, FrameInfo, LightSource, StreamEnd, open_driver
from .ringbuffer import POLICIES, RingBuffer
from .session import CaptureResult, capture_sequences

__all__ = [
    "CameraDriver",
    "capture_sequences",
    "CaptureResult",
    "DRIVERS",
    "FrameInfo",
    "LightSource",
    "open_driver",
    "POLICIES",
    "RingBuffer",
    "Sequence",
    "SequenceAssembler",
    "StreamEnd",
]
