"""Fakes of a harvesters / GenICam camera shared by the hardware tests: feature nodes, the node map, the exceptions
harvesters and genicam raise, a fetched buffer, and :class:`FakeCamera`, an acquirer wired to a
:class:`~specgpu.hardware.dlpc900.SimulatedDLPC900` as a camera is on the bench; and the twin behind a simulated
bench for calibration (:class:`TwinCamera`, :class:`TwinSeaBreeze`, :func:`hardware_table`).

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

from specgpu.calibration.rigs import twin_at_exposure
from specgpu.hardware.dlpc900 import DMDLayout
from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription
from specgpu.rig.light import ProgrammableLight
from specgpu.rig.scene import white_plate_scene

#: The simulated bench of the hardware calibration tests: the twin at 320 x 240, a white plate of reflectance
#: ``WHITE``, a spectrometer with a dark offset of ``DARK_COUNTS``.
DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
WHITE = 0.99
DARK_COUNTS = 800.0


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


# ---- the twin behind the fakes: what the simulated bench's camera and spectrometer see ---------------------

class TwinCamera:
    """A free-running GenICam camera (strobe-master) whose frames are the twin's, lit by the controller's display.

    At start it reads the exposure from its ExposureTime feature and the controller's LUT (each entry's mirrors
    decoded back to mirror counts); each exposure's strobe is a TRIG_IN_1 edge, and the frame is the twin's
    rendering of the entry now on display. Frame ids start at 1 (GigE Vision); ``lost`` exposures are made but
    never delivered.
    """

    def __init__(self, sim, description=DESC, *, lost=()):
        cam = description.camera
        self.sim, self.description = sim, description
        self.layout = DMDLayout(sim.geometry, description.light.columns, description.light.rows)
        self.scene = white_plate_scene(cam.roi_height, cam.roi_width, reflectance=WHITE)
        self.remote_device = type("Remote", (), {"node_map": NodeMap(cam.roi_height, cam.roi_width,
                                                                     f"Mono{cam.bit_depth}")})()
        self.lost = set(lost)
        self.starts = 0
        self.started = False
        self._twins = {}
        self.exposures = []

    def start(self):
        nm = self.remote_device.node_map
        assert (nm.TriggerMode.value, nm.LineSource.value) == ("Off", "ExposureActive")  # strobe-master wiring
        t = float(nm.ExposureTime.value) * 1e-6
        if t not in self._twins:
            self._twins[t] = twin_at_exposure(self.description, self.scene, t)
        self.twin = self._twins[t]
        lut = [self.layout.mask_to_pattern(self.sim.entry_mask(j)) for j in range(self.sim.lut_entries)]
        assert all(self.sim.lut[j]["exposure_us"] == round(t * 1e6) for j in range(len(lut)))  # light follows
        self.twin.load_sequence(np.stack(lut))
        self.twin.seed = 1000 + self.starts  # fresh temporal noise for every capture, as a real sensor
        self.starts += 1
        self.exposures.append(t)
        self.n, self.started = 0, True
        self.out = np.empty(self.twin.camera.shape, np.uint16)

    def stop(self):
        self.started = False

    def fetch(self, timeout=None):
        while True:
            if not self.started:
                raise TimeoutException("no buffer")
            n = self.n
            self.n += 1
            position = self.sim.trigger_in()  # the exposure's strobe edge shows the next entry
            if position < 0:
                raise TimeoutException("sequencer stopped")
            self.twin.render(position, n, n * 0.011, self.out)
            if n not in self.lost:
                return Buffer(self.out.copy(), 1 + n, 1_000_000 + n * 11_000_000)


class TwinSeaBreeze:
    """A seabreeze-like spectrometer: the twin light's spectral irradiance of the mirrors the controller displays,
    sampled on the instrument's pixels, in counts (through the inverse of ``CAL``) plus a dark offset."""

    def __init__(self, sim, description=DESC, cal=1.0):
        self.sim = sim
        self.layout = DMDLayout(sim.geometry, description.light.columns, description.light.rows)
        self.model = ProgrammableLight(description.light, seed=description.seed)
        self.pixels = np.linspace(340.0, 830.0, 1961)
        self.cal = cal
        self.t = 0.1
        self.rng = np.random.default_rng(7)
        self.closed = False

    def wavelengths(self):
        return self.pixels

    def integration_time_micros(self, us):
        self.t = us * 1e-6

    def intensities(self, correct_dark_counts=True, correct_nonlinearity=True):
        mask = self.sim.displayed_mask()
        spd = (self.model.pattern_to_spectrum(self.layout.mask_to_pattern(mask)) if mask.any()
               else np.zeros(self.model.wavelengths.shape))
        irr = np.interp(self.pixels, self.model.wavelengths, spd, left=0.0, right=0.0)
        counts = irr * self.t / self.cal + DARK_COUNTS
        return counts + self.rng.normal(0.0, 0.5, counts.shape)

    def close(self):
        self.closed = True


def spectrometer_cal():
    """An irradiance calibration scale putting the all-on spectrum at about 30000 counts in 0.1 s."""
    return float(ProgrammableLight(DESC.light).max_spectrum.max()) * 0.1 / 30000.0


def hardware_table(tmp_path, **extra):
    """The [hardware] table of the simulated bench: the simulated controller, an Ocean spectrometer calibrated by
    :func:`spectrometer_cal` (a CSV under ``tmp_path``), the twin camera's exposure."""
    csv = tmp_path / "irradiance_cal.csv"
    csv.write_text("\n".join(f"{wl:g},{spectrometer_cal():.9g}" for wl in (330.0, 850.0)) + "\n")
    return {"light": "dlpc900-simulated", "spectrometer": "ocean", "spectrometer_calibration": str(csv),
            "camera_first_frame_id": 1, "exposure_s": DESC.camera.exposure_s, **extra}
