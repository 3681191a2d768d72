"""Capture: the driver interface, the ring buffer, the sequence assembler and the capture loop.

Backends are chosen by name (:func:`open_driver`: the digital twin ``"twin"`` by default, ``"replay"`` for recorded
frames) and imported on demand.
"""

from specgpu.capture.assemble import AssemblyStats, Sequence, SequenceAssembler, assemble_stream
from specgpu.capture.driver import DRIVERS, CameraDriver, FrameInfo, LightSource, StreamEnd, open_driver
from specgpu.capture.ringbuffer import POLICIES, RingBuffer, RingStats, Slot, run_producer
from specgpu.capture.session import CaptureResult, capture_sequences

__all__ = [
    "AssemblyStats", "Sequence", "SequenceAssembler", "assemble_stream",
    "DRIVERS", "CameraDriver", "FrameInfo", "LightSource", "StreamEnd", "open_driver",
    "POLICIES", "RingBuffer", "RingStats", "Slot", "run_producer",
    "CaptureResult", "capture_sequences",
]
