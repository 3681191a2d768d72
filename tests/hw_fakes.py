"""Fakes of a harvesters / GenICam camera shared by the hardware tests: feature nodes, the node map, the timeout
exception harvesters raises, and a fetched buffer."""

from __future__ import annotations


class Node:
    def __init__(self, value):
        self.value = value


class NodeMap:
    def __init__(self, height, width, pixel_format="Mono16"):
        self.PixelFormat, self.Height, self.Width = Node(pixel_format), Node(height), Node(width)
        for name in ("ExposureAuto", "ExposureTime", "TriggerSelector", "TriggerMode", "TriggerSource",
                     "TriggerActivation", "AcquisitionFrameRateEnable", "AcquisitionFrameRate", "LineSelector",
                     "LineMode", "LineSource"):
            setattr(self, name, Node(None))


class TimeoutException(Exception):
    """Named as genicam.gentl's, which harvesters raises when fetch() times out."""


class Buffer:
    def __init__(self, data, frame_id, timestamp_ns):
        self.payload = type("Payload", (), {"components": [type("Component", (), {"data": data.ravel()})()]})()
        self.frame_id, self.timestamp_ns = frame_id, timestamp_ns

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
