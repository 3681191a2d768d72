"""GenICam cameras (GigE Vision, USB3 Vision) through harvesters, as a :class:`~specgpu.capture.driver.CameraDriver`.

Two ways to wire camera and light (the capture path is the same):

- ``"strobe-master"`` (the paper's rig, Section 2.D): the camera free-runs at its frame rate and its exposure-active
  output (``strobe_line``, an output line) drives the DLPC900's TRIG_IN_1; every LUT entry waits for that trigger.
  The light starts first (it waits for the first strobe), then the camera: a strobe before the light's Start would
  be lost and shift every label.
- ``"hardware-trigger"``: the DLPC900 runs the sequence on its own clock and its TRIG_OUT_1 triggers each exposure
  on the camera's ``trigger_line`` (an input line). The camera is armed first, then the light started: a light
  started first runs patterns nobody sees, and frame 0 would not be pattern 0. Every LUT entry needs a non-zero
  dark time (:class:`~specgpu.hardware.dlpc900.DLPC900Light` ``dark_s``): TRIG_OUT_1 falls only there.

The strobe line's ``LineMode`` is read first and written only when it is not already ``Output``: on opto-isolated
lines (common USB3 and GigE cameras) it is read-only, and a line that cannot be an output is refused with the lines
that can.

Either way exposure ``n`` of the stream is lit by pattern ``n mod K``, and ``n`` comes from the camera's own frame
counter (GenTL frame id), which also counts frames lost on the link, so a lost frame shows as a gap and the frames
after it keep their true pattern. GigE Vision 1.x block ids are 16 bit and wrap from 65535 to 1 (0 is never used):
the ids are unwrapped, so a capture runs past 65535 frames. A buffer without a device timestamp (GenTL
NotAvailableException, e.g. the genicam package's virtual camera) is stamped with the host's clock at delivery.
Before a frame is handed over the light is checked (Main Status); a light that no longer runs its sequence, a camera
that stops delivering, or a USB failure ends the capture with a one-line error and the frame in hand is not
delivered: the sequence it belonged to stays incomplete, nothing is mislabelled.

harvesters is an optional dependency (``pip install harvesters``) imported only when a camera is opened without an
injected acquirer; a GenTL producer (``.cti`` file) from the camera vendor, or e.g. Aravis', is needed too.
"""

from __future__ import annotations

import time

import numpy as np

from specgpu.capture.driver import CameraDriver, FrameInfo, LightSource, StreamEnd
from specgpu.core.validate import check_number
from specgpu.hardware.errors import BackendMissing, DeviceNotFound, DeviceTimeout, HardwareError

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


#: GigE Vision 1.x block ids: 16 bit, 0 never used, so 65535 is followed by 1.
BLOCK_ID_WRAP = 0xFFFF


def _timestamp_ns(buffer) -> int | None:
    """The buffer's device timestamp, ns; ``None`` where the producer has none (GenTL NotAvailableException and
    the like: the property raises) or reports 0."""
    try:
        ts = buffer.timestamp_ns
    except Exception:  # genicam.gentl.NotAvailableException (and NotImplemented...) depending on the producer
        return None
    return int(ts) if ts else None


def _line_modes(nm) -> dict:
    """{line: (LineMode value, writable)} of every line the LineSelector offers (the selection is restored)."""
    selector = nm.LineSelector
    try:
        lines = list(selector.symbolics)
    except Exception:
        return {}
    keep, out = selector.value, {}
    try:
        for line in lines:
            try:
                selector.value = line
                node = nm.LineMode
                out[line] = (str(node.value), _writable(node))
            except Exception:
                continue
    finally:
        try:
            selector.value = keep
        except Exception:
            pass
    return out


def _writable(node) -> bool:
    """Whether a GenICam feature can be written now (genapi access mode RW or WO); True when it cannot be told."""
    try:
        from genicam.genapi import EAccessMode
        return node.node.get_access_mode() in (EAccessMode.RW, EAccessMode.WO)
    except Exception:
        writable = getattr(node, "writable", None)
        return True if writable is None else bool(writable)


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
        self._raw_last, self._wraps = None, 0
        self.timestamp_source = "device"  # "host" once a buffer came without a device timestamp
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
            self._configure_strobe(nm)
            _set(nm, "LineSource", "ExposureActive")
        else:
            _set(nm, "TriggerMode", "On")
            _set(nm, "TriggerSource", self.trigger_line)
            _set(nm, "TriggerActivation", "RisingEdge")

    def _configure_strobe(self, nm) -> None:
        """Select the strobe line and make it an output: nothing written when it already is one (its LineMode is
        read-only on opto-isolated lines); a one-line error naming the lines that can be when it cannot."""
        _set(nm, "LineSelector", self.strobe_line)
        mode = getattr(nm, "LineMode", None)
        if mode is None:
            raise HardwareError("camera has no GenICam feature 'LineMode': its strobe output cannot be set up")
        if str(mode.value) == "Output":
            return
        error = None
        if _writable(mode):
            try:
                mode.value = "Output"
                return
            except Exception as exc:
                error = exc
        modes = _line_modes(nm)
        usable = [line for line, (value, writable) in modes.items() if value == "Output" or writable]
        hint = (f"set strobe_line (hardware.camera_strobe_line) to {usable[0]}" + (f" (lines that can be outputs: "
                f"{', '.join(usable)})" if len(usable) > 1 else "")) if usable else "the camera offers no output line"
        why = f" ({error})" if error is not None else " (its LineMode is read-only)"
        raise HardwareError(f"camera line {self.strobe_line} is an {str(mode.value).lower()} and cannot be made the "
                            f"strobe output{why}; {hint}")

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
        """Configure the camera, then start first the device that waits for the other's trigger: in strobe-master
        mode the light (it waits for the first strobe), then the camera; in hardware-trigger mode the camera (armed,
        it waits for TRIG_OUT_1), then the light, whose clock starts the sequence at pattern 0."""
        self.configure()
        self._first_id = self.first_frame_id
        self._t0_ns = None
        self._last = (-1, -1)
        self._raw_last = None
        self._wraps = 0
        self.timestamp_source = "device"
        self.frames_delivered = 0
        self.fault = None
        if self.mode == "strobe-master":
            self._light.start()
            try:
                self.acquirer.start()
            except BaseException:  # the light must not stay on, waiting for strobes, behind the camera's error
                try:
                    self._light.stop()
                except Exception:  # noqa: BLE001 (the camera's error is the one to report)
                    pass
                raise
        else:
            self.acquirer.start()
            try:
                self._light.start()
            except BaseException:
                self.acquirer.stop()
                raise
        self._running = True

    def _unwrap(self, raw: int) -> int:
        """The frame id counted on from the first (GigE Vision 1.x 16-bit block ids wrap from 65535 to 1)."""
        last = self._raw_last
        if last is not None and raw < last and last <= BLOCK_ID_WRAP and last - raw > BLOCK_ID_WRAP // 2:
            self._wraps += 1
        self._raw_last = raw
        return raw + self._wraps * BLOCK_ID_WRAP

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
            raw = _frame_id(buffer)
            frame_id = self._unwrap(raw)
            if self._first_id is None:
                self._first_id = frame_id
            stamp = _timestamp_ns(buffer)
            if stamp is None:  # no device timestamp: the host's clock at delivery
                stamp, self.timestamp_source = time.monotonic_ns(), "host"
            if self._t0_ns is None:
                self._t0_ns = stamp
            n = frame_id - self._first_id
            if n < 0:
                raise HardwareError(f"camera frame id went backwards ({raw} after start at {self._first_id})")
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
            ts = (stamp - self._t0_ns) * 1e-9
        self.frames_delivered += 1
        return FrameInfo(n, pattern, ts, self.exposure_s)

    def describe(self) -> dict:
        """Metadata for a capture record."""
        return {"driver": "genicam", "mode": self.mode, "exposure_s": self.exposure_s,
                "frame_shape": list(self._shape), "dtype": str(self._dtype), "timestamps": self.timestamp_source,
                "time": time.time()}
