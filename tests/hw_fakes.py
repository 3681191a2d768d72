"""Fakes of a harvesters / GenICam camera shared by the hardware tests: feature nodes, the node map, the exceptions
harvesters and genicam raise, a fetched buffer, and :class:`FakeCamera`, an acquirer wired to a
:class:`~specgpu.hardware.dlpc900.SimulatedDLPC900` as a camera is on the bench.

They behave like real cameras where a capture depends on it:

- I/O lines are selected by ``LineSelector``; ``LineMode`` is read-only on the opto-isolated lines (as on common
  USB3 and GigE cameras: Line0 an input, Line1 an output) and writing it there raises ``AccessException``;
- a buffer may have no device timestamp: reading it raises ``NotAvailableException`` (as the genicam package's
  virtual camera does);
- GigE Vision 1.x block ids are 16 bit and wrap from 65535 to 1 (``id_bits=16``);
- strobe-master (TriggerMode Off): the camera free-runs from its arming, one exposure per frame period, and each
  exposure's strobe is a TRIG_IN_1 edge at that time (an edge before the light's Start is lost); the frame
  integrates what the controller shows during the exposure, a previous pattern left up by a missing
  clear-after-exposure included;
- hardware-trigger (TriggerMode On): the camera exposes on each TRIG_OUT_1 rising edge after it is armed (and after
  its previous exposure): edges the controller made before the camera was armed, or while it was exposing, are not
  seen; no edge in the timeout is a TimeoutException. Arming takes ``arm_us`` of the controller's clock.
"""

from __future__ import annotations

import numpy as np


class AccessException(Exception):
    """Named as genicam.genapi's, raised when a feature that is not writable is written."""


class NotAvailableException(Exception):
    """Named as genicam.gentl's, raised when a buffer has no such information (e.g. no timestamp)."""


class TimeoutException(Exception):
    """Named as genicam.gentl's, which harvesters raises when fetch() times out."""


class Node:
    """A GenICam feature: ``value``; ``writable`` False makes a write raise :class:`AccessException`."""

    def __init__(self, value, *, writable: bool = True, symbolics=None):
        self._value, self.writable = value, writable
        if symbolics is not None:
            self.symbolics = list(symbolics)
        self.writes = 0

    @property
    def value(self):
        return self._value

    @value.setter
    def value(self, v):
        if not self.writable:
            raise AccessException(f"Node is not writable (value {v!r})")
        if hasattr(self, "symbolics") and v not in self.symbolics:
            raise ValueError(f"{v!r} is not one of {self.symbolics}")
        self._value = v
        self.writes += 1


class LineNode:
    """A feature of the line ``LineSelector`` selects (LineMode, LineSource)."""

    def __init__(self, node_map, name):
        self._nm, self._name = node_map, name

    def _entry(self):
        return self._nm.lines[self._nm.LineSelector.value]

    @property
    def writable(self):
        return self._name != "LineMode" or self._entry()["mode_writable"]

    @property
    def value(self):
        return self._entry()[self._name]

    @value.setter
    def value(self, v):
        if not self.writable:
            raise AccessException(f"Node is not writable: {self._name} of {self._nm.LineSelector.value}")
        self._entry()[self._name] = v
        self._nm.line_writes.append((self._nm.LineSelector.value, self._name, v))


#: Lines of a common industrial camera: opto-isolated input and output (modes read-only), two GPIOs.
DEFAULT_LINES = {"Line0": ("Input", False), "Line1": ("Output", False), "Line2": ("Input", True),
                 "Line3": ("Input", True)}


class NodeMap:
    def __init__(self, height, width, pixel_format="Mono16", lines=None):
        self.PixelFormat, self.Height, self.Width = Node(pixel_format), Node(height), Node(width)
        for name in ("ExposureAuto", "ExposureTime", "TriggerSelector", "TriggerMode", "TriggerSource",
                     "TriggerActivation", "AcquisitionFrameRateEnable", "AcquisitionFrameRate"):
            setattr(self, name, Node(None))
        lines = DEFAULT_LINES if lines is None else lines
        self.lines = {name: {"LineMode": mode, "mode_writable": writable, "LineSource": "Off"}
                      for name, (mode, writable) in lines.items()}
        self.LineSelector = Node(next(iter(self.lines)), symbolics=self.lines)
        self.LineMode, self.LineSource = LineNode(self, "LineMode"), LineNode(self, "LineSource")
        self.line_writes = []


class Buffer:
    """A fetched buffer; ``timestamp_ns=None``: the producer has no timestamp (reading it raises)."""

    def __init__(self, data, frame_id, timestamp_ns=None):
        self.payload = type("Payload", (), {"components": [type("Component", (), {"data": data.ravel()})()]})()
        self.frame_id, self._timestamp_ns = frame_id, timestamp_ns

    @property
    def timestamp_ns(self):
        if self._timestamp_ns is None:
            raise NotAvailableException("GenTL exception: Resource or information is not available. (GetBufferInfo: "
                                        "timestamps not supported by the device) (ID: -1014)")
        return self._timestamp_ns

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def gev_block_id(first_id: int, n: int, id_bits: int | None) -> int:
    """The id of exposure ``n``: counted on from ``first_id``; 16 bit: 65535 is followed by 1 (GigE Vision 1.x)."""
    if id_bits is None:
        return first_id + n
    top = (1 << id_bits) - 1
    return (first_id - 1 + n) % top + 1


class FakeCamera:
    """A harvesters-like ImageAcquirer on the bench with a simulated controller (module docstring).

    Parameters
    ----------
    sim
        The :class:`SimulatedDLPC900` the camera is wired to.
    render
        ``render(light)`` -> frame: ``light`` is the (H, W) float light of the DMD's mirrors in the exposure.
    exposures
        Exposures the camera makes after arming (then it times out).
    shape, pixel_format, lines
        Node map.
    lost
        Exposures made but never delivered (lost on the link).
    first_id, id_bits
        Frame id of exposure 0 and the id width (16: GigE Vision 1.x, wraps to 1; None: 64 bit).
    timestamps
        Whether buffers carry a device timestamp.
    arm_us, readout_us, period_us
        Time arming takes; time after an exposure before the next trigger is accepted (overlapped readout); the
        free-running frame period (default: exposure + 500 us).
    on_exposure
        Called with the exposure number before it is made (fault drills).
    """

    def __init__(self, sim, render, exposures, *, shape=(4, 16), pixel_format="Mono16", lines=None, lost=(),
                 first_id=1, id_bits=None, timestamps=True, arm_us=5000.0, readout_us=50.0, period_us=None,
                 on_exposure=None):
        self.sim, self.render, self.exposures = sim, render, exposures
        self.remote_device = type("Remote", (), {"node_map": NodeMap(*shape, pixel_format, lines)})()
        self.lost, self.first_id, self.id_bits, self.timestamps = set(lost), first_id, id_bits, timestamps
        self.arm_us, self.readout_us, self.period_us, self.on_exposure = arm_us, readout_us, period_us, on_exposure
        self.n = 0
        self.started = False
        self.positions = []  # the LUT entry that lit each exposure (-1: none), for checks

    def start(self):
        self.sim.elapse(self.arm_us)  # AcquisitionStart goes over the link; the camera is armed after it
        nm = self.remote_device.node_map
        self.exposure_us = float(nm.ExposureTime.value)
        self.triggered = nm.TriggerMode.value == "On"
        rate = nm.AcquisitionFrameRate.value
        self.period = 1e6 / rate if rate else self.period_us or self.exposure_us + 500.0
        self.t_armed = self.t_ready = self.sim.clock_us
        self.started, self.n = True, 0

    def stop(self):
        self.started = False

    def _expose(self, n):
        sim = self.sim
        if not self.triggered:  # free-running: exposure n opens at its frame time, its strobe is TRIG_IN_1
            t = self.t_armed + n * self.period
            position = sim.trigger_in(at_us=t)
            light = sim.exposure_light(self.exposure_us) if position >= 0 else None
            sim.elapse(max(0.0, t + self.exposure_us - sim.clock_us))
        else:  # the next TRIG_OUT_1 rising edge the armed camera is ready for
            edge = sim.next_trigger_out1(self.t_ready)
            if edge is None:
                raise TimeoutException("no trigger: GenTL TimeoutException")
            t, position = edge
            sim.elapse(max(0.0, t - sim.clock_us))
            light = sim.displayed_mask().astype(np.float64)
            self.t_ready = t + self.exposure_us + self.readout_us
            sim.elapse(max(0.0, t + self.exposure_us - sim.clock_us))
        if light is None:
            light = np.zeros((sim.geometry.height, sim.geometry.width))
        return t, position, light

    def fetch(self, timeout=None):
        while True:
            if not self.started or self.n >= self.exposures:
                raise TimeoutException("no buffer")
            n = self.n
            self.n += 1
            if self.on_exposure is not None:
                self.on_exposure(n)
            t, position, light = self._expose(n)
            self.positions.append(position)
            if n not in self.lost:
                stamp = int(round(t * 1000)) if self.timestamps else None
                return Buffer(self.render(light), gev_block_id(self.first_id, n, self.id_bits), stamp)
