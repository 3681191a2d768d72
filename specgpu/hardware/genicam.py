"""GenICam cameras (GigE Vision, USB3 Vision) through harvesters, as a :class:`~specgpu.capture.driver.CameraDriver`.

Two ways to wire camera and light (the capture path is the same):

- ``"strobe-master"`` (the paper's rig, Section 2.D): the camera free-runs at its frame rate and its exposure-active
  output (``strobe_line``) drives the DLPC900's TRIG_IN_1; every LUT entry waits for that trigger.
- ``"hardware-trigger"``: the DLPC900 runs the sequence on its own clock and its TRIG_OUT_1 triggers each exposure
  on the camera's ``trigger_line``.

Either way exposure ``n`` of the stream is lit by pattern ``n mod K``, and ``n`` comes from the camera's own frame
counter (GenTL frame id), which also counts frames lost on the link, so a lost frame shows as a gap and the frames
after it keep their true pattern. Before a frame is handed over the light is checked (Main Status); a light that no
longer runs its sequence, a camera that stops delivering, or a USB failure ends the capture with a one-line error
and the frame in hand is not delivered: the sequence it belonged to stays incomplete, nothing is mislabelled.

harvesters is an optional dependency (``pip install harvesters``) imported only when a camera is opened without an
injected acquirer; a GenTL producer (``.cti`` file) from the camera vendor, or e.g. Aravis', is needed too.
"""

from __future__ import annotations

import time

import numpy as np

from specgpu.capture.driver import CameraDriver, FrameInfo, LightSource, StreamEnd
from specgpu.hardware.errors import BackendMissing, DeviceNotFound, DeviceTimeout, HardwareError
from specgpu.rig._checks import check_number

__all__ = ["GenICamCamera", "MODES", "PIXEL_DTYPES", "open_acquirer"]

MODES = ("strobe-master", "hardware-trigger")
#: GenICam PixelFormat -> NumPy dtype of the frames.
PIXEL_DTYPES = {"Mono8": np.uint8, "Mono10": np.uint16, "Mono12": np.uint16, "Mono14": np.uint16,
                "Mono16": np.uint16}


def open_acquirer(cti, serial: str | None = None):
    """A harvesters ImageAcquirer for the camera with ``serial`` (the first one if ``None``) of GenTL producer
    ``cti``. Returns ``(harvester, acquirer)``; the harvester must be reset after use."""
    try:
        from harvesters.core import Harvester
    except ImportError:
        raise BackendMissing("GenICam cameras need the optional 'harvesters' package: pip install harvesters "
                             "(and a GenTL producer .cti from the camera vendor)") from None
    if cti is None:
        raise ValueError("a GenTL producer (.cti file) is needed to open a GenICam camera; pass cti=")
    h = Harvester()
    h.add_file(str(cti))
    h.update()
    infos = h.device_info_list
    if not infos:
        h.reset()
        raise DeviceNotFound(f"no GenICam camera found through {cti}: is it connected and powered?")
    try:
        ia = h.create({"serial_number": serial} if serial else 0)
    except Exception as exc:  # harvesters raises ValueError/IndexError/genicam errors depending on version
        h.reset()
        raise DeviceNotFound(f"GenICam camera {serial or '#0'} cannot be opened through {cti} ({exc})") from None
    return h, ia


def _set(node_map, name: str, value) -> None:
    node = getattr(node_map, name, None)
    if node is None:
        raise HardwareError(f"camera has no GenICam feature {name!r} (needed to set it to {value!r})")
    try:
        node.value = value
    except Exception as exc:
        raise HardwareError(f"camera refused {name} = {value!r} ({exc})") from None


def _frame_id(buffer) -> int:
    """The GenTL frame id of a fetched buffer (BUFFER_INFO_FRAMEID): the camera's count, gaps included."""
    fid = getattr(buffer, "frame_id", None)
    if fid is None:  # harvesters versions without Buffer.frame_id: ask the GenTL buffer it wraps
        fid = getattr(getattr(buffer, "_buffer", None), "frame_id", None)
    if fid is None:
        raise HardwareError("camera buffers carry no frame id: lost frames could not be told apart; use a GenTL "
                            "producer that reports BUFFER_INFO_FRAMEID")
    return int(fid)


class GenICamCamera(CameraDriver):
    """Camera-master (or light-triggered) acquisition from a GenICam camera, lighting from a hardware light.

    Parameters
    ----------
    light
        The light source (e.g. :class:`~specgpu.hardware.dlpc900.DLPC900Light`) with its sequence loaded; it needs
        ``start``, ``stop``, ``at_frame`` and ``check`` besides the LightSource interface.
    acquirer
        A harvesters ImageAcquirer (or anything with its interface: ``remote_device.node_map``, ``start``, ``stop``,
        ``fetch(timeout=)`` returning a buffer with ``payload.components[0]``, ``frame_id`` and ``timestamp_ns``);
        default: opened from ``cti`` and ``serial``.
    mode
        ``"strobe-master"`` or ``"hardware-trigger"`` (module docstring).
    exposure_s
        Camera exposure, s.
    frame_rate_hz
        Frame rate in strobe-master mode (``None``: leave the camera's).
    n_frames
        Exposures after which the stream ends; ``None`` runs until stopped.
    timeout_s
        Longest wait for a frame before the capture fails.
    check_light
        Check the light's status before handing over each frame (one USB round trip per frame).
    trigger_line, strobe_line
        Camera I/O lines (GenICam ``LineSelector`` values).
    first_frame_id
        The frame id the camera gives its first exposure after acquisition start (GigE Vision block ids start at 1,
        USB3 Vision at 0). Given, a lost first frame cannot shift the labels; ``None`` takes the first frame
        delivered as exposure 0 (then also check a dark pattern with the assembler's ``sync_pattern``).
    """

    def __init__(self, light: LightSource, *, acquirer=None, cti=None, serial: str | None = None,
                 mode: str = "strobe-master", exposure_s: float = 0.010, frame_rate_hz: float | None = None,
                 n_frames: int | None = None, timeout_s: float = 2.0, check_light: bool = True,
                 trigger_line: str = "Line0", strobe_line: str = "Line1", first_frame_id: int | None = None):
        if mode not in MODES:
            raise ValueError(f"unknown camera mode {mode!r}; valid: {', '.join(MODES)}")
        self._light = light
        self.mode = mode
        self.exposure_s = check_number("exposure_s", exposure_s, low=light.minimum_exposure_s, high=60)
        self.frame_rate_hz = None if frame_rate_hz is None else check_number("frame_rate_hz", frame_rate_hz,
                                                                             low=0, low_open=True, high=1e5)
        self.n_frames = None if n_frames is None else check_number("n_frames", n_frames, low=0, integer=True)
        self.timeout_s = check_number("timeout_s", timeout_s, low=0, low_open=True)
        self.check_light = bool(check_light)
        self.trigger_line, self.strobe_line = trigger_line, strobe_line
        self.first_frame_id = None if first_frame_id is None else check_number("first_frame_id", first_frame_id,
                                                                                low=0, integer=True)
        self._harvester = None
        if acquirer is None:
            self._harvester, acquirer = open_acquirer(cti, serial)
        self.acquirer = acquirer
        nm = acquirer.remote_device.node_map
        fmt = str(nm.PixelFormat.value)
        if fmt not in PIXEL_DTYPES:
            raise HardwareError(f"camera pixel format {fmt} is not supported; set one of {', '.join(PIXEL_DTYPES)}")
        self._dtype = np.dtype(PIXEL_DTYPES[fmt])
        self._shape = (int(nm.Height.value), int(nm.Width.value))
        self._running = False
        self._first_id = None
        self._t0_ns = None
        self._last = (-1, -1)
        self.frames_delivered = 0
        self.fault: Exception | None = None

    def configure(self) -> None:
        """Write the trigger wiring and exposure to the camera's GenICam features."""
        nm = self.acquirer.remote_device.node_map
        if hasattr(nm, "ExposureAuto"):
            _set(nm, "ExposureAuto", "Off")
        _set(nm, "ExposureTime", self.exposure_s * 1e6)  # GenICam SFNC: microseconds
        _set(nm, "TriggerSelector", "FrameStart")
        if self.mode == "strobe-master":
            _set(nm, "TriggerMode", "Off")
            if self.frame_rate_hz is not None:
                if hasattr(nm, "AcquisitionFrameRateEnable"):
                    _set(nm, "AcquisitionFrameRateEnable", True)
                _set(nm, "AcquisitionFrameRate", self.frame_rate_hz)
            _set(nm, "LineSelector", self.strobe_line)
            _set(nm, "LineMode", "Output")
            _set(nm, "LineSource", "ExposureActive")
        else:
            _set(nm, "TriggerMode", "On")
            _set(nm, "TriggerSource", self.trigger_line)
            _set(nm, "TriggerActivation", "RisingEdge")

    # ---- CameraDriver -------------------------------------------------------------------------------------------
    @property
    def frame_shape(self) -> tuple[int, int]:
        return self._shape

    @property
    def dtype(self) -> np.dtype:
        return self._dtype

    @property
    def light(self) -> LightSource:
        return self._light

    @property
    def running(self) -> bool:
        return self._running

    def start(self) -> None:
        """Configure the camera, start the light's sequence, then the camera (the light must wait for the
        first exposure, not the other way round)."""
        self.configure()
        self._first_id = self.first_frame_id
        self._t0_ns = None
        self._last = (-1, -1)
        self.frames_delivered = 0
        self.fault = None
        self._light.start()
        self.acquirer.start()
        self._running = True

    def stop(self) -> StreamEnd:
        if self._running:
            self._running = False
            for stop in (self.acquirer.stop, self._light.stop):
                try:
                    stop()
                except Exception as exc:  # the device may be gone; the capture's own error is the one to report
                    self.fault = self.fault or exc
        return StreamEnd(*self._last)

    def close(self) -> None:
        """Release the camera (and the harvester that opened it) and the light it drives."""
        try:
            self.stop()
            if self._harvester is not None:
                self.acquirer.destroy()
                self._harvester.reset()
                self._harvester = None
        finally:
            close_light = getattr(self._light, "close", None)
            if close_light is not None:
                close_light()

    def fill(self, out: np.ndarray | None) -> FrameInfo | None:
        if not self._running:
            raise RuntimeError("GenICam camera: fill() called before start() or after stop()")
        if self.n_frames is not None and self._last[0] + 1 >= self.n_frames:
            return None
        try:
            buffer = self.acquirer.fetch(timeout=self.timeout_s)
        except Exception as exc:
            if type(exc).__name__ in ("TimeoutException", "TimeoutError", "DeviceTimeout"):
                self.fault = DeviceTimeout(f"camera delivered no frame in {self.timeout_s:g} s: is it triggered "
                                           f"({self.mode})?")
                raise self.fault from None
            raise
        with buffer:
            frame_id = _frame_id(buffer)
            if self._first_id is None:
                self._first_id = frame_id
            if self._t0_ns is None:
                self._t0_ns = int(buffer.timestamp_ns)
            n = frame_id - self._first_id
            if n < 0:
                raise HardwareError(f"camera frame id went backwards ({frame_id} after start at {self._first_id})")
            if self.n_frames is not None and n >= self.n_frames:
                return None  # exposures past the end: not part of this capture
            pattern = self._light.at_frame(n)
            if self.check_light:
                try:
                    self._light.check()  # before delivering: a frame the light may not have lit is never labelled
                except Exception as exc:
                    self.fault = exc
                    raise
            if out is not None:
                comp = buffer.payload.components[0]
                data = np.asarray(comp.data)
                if data.size != out.size:
                    raise HardwareError(f"camera frame has {data.size} pixels, expected {self._shape}")
                out[...] = data.reshape(out.shape)
            self._last = (n, pattern)
            ts = (int(buffer.timestamp_ns) - self._t0_ns) * 1e-9
        self.frames_delivered += 1
        return FrameInfo(n, pattern, ts, self.exposure_s)

    def describe(self) -> dict:
        """Metadata for a capture record."""
        return {"driver": "genicam", "mode": self.mode, "exposure_s": self.exposure_s,
                "frame_shape": list(self._shape), "dtype": str(self._dtype), "time": time.time()}
