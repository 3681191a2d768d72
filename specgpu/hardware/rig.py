"""A real rig from a description: DLPC900 light + GenICam camera (+ Ocean spectrometer), chosen by name.

:func:`open_hardware` is registered in :data:`specgpu.capture.driver.DRIVERS` as ``"vision-dlpc900"``, so
``open_driver("vision-dlpc900", hardware={...}, patterns=..., n_frames=...)`` gives a camera driver that goes
through the same ring buffer and assembler as the twin. The ``hardware`` table (:class:`HardwareConfig`) is what
a rig TOML's ``[hardware]`` table would hold::

    [hardware]
    light = "dlpc900"                 # or "dlpc900-simulated" for a dry run of the upload
    dmd = "lightcrafter-6500"         # or "lightcrafter-9000"
    camera_cti = "/opt/vendor/lib/producer.cti"
    camera_serial = "12345678"
    camera_mode = "strobe-master"     # or "hardware-trigger"
    camera_first_frame_id = 1         # GigE Vision block ids start at 1 (USB3 Vision: 0)
    camera_strobe_line = "Line1"      # strobe-master: the camera output wired to the DLPC900's TRIG_IN_1
    camera_trigger_line = "Line0"     # hardware-trigger: the camera input wired to the DLPC900's TRIG_OUT_1
    exposure_s = 0.010
    dark_time_s = 0.0001              # dark time after each pattern (TRIG_OUT_1 falls only there)
    spectrometer = "ocean"            # for calibration loop (b); "" for none
    spectrometer_calibration = "irradiance_cal.csv"

An LED array on the specgpu LED controller board, or the OL490 (each stepped by the camera's strobe, so
``camera_mode`` stays ``"strobe-master"``)::

    [hardware]
    light = "led"                     # or "led-simulated"; "ol490" or "ol490-simulated"
    light_port = "/dev/ttyACM0"       # the board's serial port (COM3, or a pyserial URL)
    light_channels = 8                # channels used (0: all the board has)
    light_spectra = "leds.csv"        # wavelength nm, one column per channel at full duty
    ol490_sdk = "C:/Program Files/OL490/OL490_SDK_Dll.dll"
    ol490_slit = 2                    # the stored calibration of slit 1 to 4
    ol490_grey_bits = 6               # grey depth 1 to 6 bit (deeper: slower frames)

A rig whose ``[light]`` table says ``kind = "led"`` (or ``"ol490"``, ``"dmd"``) and whose ``[hardware]`` table
names no ``light`` gets that kind's device (:func:`~specgpu.hardware.lights.light_for_kind`).

:class:`HardwareRig` gives calibration loop (b) (:func:`specgpu.calibration.spectral_loop`) what it reads from a
twin rig: ``light``, ``spectroradiometer`` and ``measure_spectrum``; :class:`HardwareCalibrationRig`
(:func:`open_calibration_rig`) adds the camera, so :func:`specgpu.calibration.calibrate` runs its whole procedure
on real devices.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from specgpu.capture.session import capture_sequences
from specgpu.core.validate import check_number
from specgpu.hardware.dlpc900 import DLPC900, DLPC900Light, SimulatedDLPC900, UsbTransport
from specgpu.hardware.dlpc900.images import COMPRESSIONS, GEOMETRIES
from specgpu.hardware.genicam import MODES, GenICamCamera
from specgpu.hardware.lights import KIND_LIGHTS, light_for_kind, open_led_light, open_ol490_light
from specgpu.hardware.ocean import OceanSpectrometer
from specgpu.hardware.ol490.sdk import DEFAULT_SDK_TYPE
from specgpu.rig.config import RigDescription, load_rig
from specgpu.rig.light import ProgrammableLight

__all__ = ["HardwareConfig", "open_hardware", "open_light", "open_spectrometer", "HardwareRig",
           "HardwareCalibrationRig", "open_calibration_rig"]

LIGHTS = tuple(v for values in KIND_LIGHTS.values() for v in values)
SPECTROMETERS = ("", "ocean")
#: Keys naming files, resolved against the rig file's folder.
FILE_KEYS = ("camera_cti", "spectrometer_calibration", "light_spectra", "ol490_sdk")


@dataclass(frozen=True)
class HardwareConfig:
    """The devices of a real rig (every field a key of the ``[hardware]`` table).

    Attributes
    ----------
    light : str
        ``"dlpc900"`` (USB) or ``"dlpc900-simulated"`` (:class:`~specgpu.hardware.dlpc900.SimulatedDLPC900`);
        ``"led"`` (:class:`~specgpu.hardware.led.LedLight` on ``light_port``) or ``"led-simulated"``; ``"ol490"``
        (:class:`~specgpu.hardware.ol490.OL490Light` through ``ol490_sdk``) or ``"ol490-simulated"``.
    dmd : str
        ``"lightcrafter-6500"`` or ``"lightcrafter-9000"``.
    light_serial : str
        USB serial of the DLPC900 controller, or serial number of the OL490 ("" for the first).
    light_port : str
        Serial port of the LED controller board (``/dev/ttyACM0``, ``COM3`` or a pyserial URL).
    light_channels : int
        LED channels used (0: all the board has, or as many as ``light_spectra`` gives).
    light_spectra : str
        CSV of the LED channels' spectra: wavelength nm, then one column per channel at full duty (W m^-2 nm^-1).
    light_holdoff_us : int
        Shortest interval between two LED steps; an edge sooner is a missed trigger (-1: the board's own).
    ol490_sdk : str
        The OL490 SDK assembly (.dll), loaded through pythonnet.
    ol490_sdk_type : str
        The SDK's library class, ``Namespace.Type``.
    ol490_slit : int
        The OL490's stored calibration to load, slit 1 to 4.
    ol490_grey_bits : int
        The OL490's grey depth, 1 to 6 bit.
    compression : str
        Image upload encoding: ``"erle"``, ``"rle"`` or ``"none"``.
    camera_cti : str
        GenTL producer (.cti) of the camera.
    camera_serial : str
        Camera serial number ("" for the first).
    camera_mode : str
        ``"strobe-master"`` or ``"hardware-trigger"``.
    exposure_s : float
        Camera exposure and the time each pattern is shown, s.
    frame_rate_hz : float
        Camera frame rate in strobe-master mode (0: the camera's setting).
    camera_first_frame_id : int
        Frame id of the camera's first exposure (GigE Vision 1, USB3 Vision 0); -1: the first frame delivered.
    camera_strobe_line, camera_trigger_line : str
        Camera I/O lines (GenICam LineSelector): the output wired to TRIG_IN_1 (strobe-master) and the input wired
        to TRIG_OUT_1 (hardware-trigger).
    dark_time_s : float
        Dark time after each pattern, s (> 0 in hardware-trigger mode: TRIG_OUT_1 falls only in it).
    spectrometer : str
        ``"ocean"`` or "" (none).
    spectrometer_serial : str
    spectrometer_calibration : str
        Irradiance calibration CSV of the spectrometer (wavelength nm, W m^-2 nm^-1 per count/s).
    integration_time_s : float
        Spectrometer integration time, s.
    """

    light: str = "dlpc900"
    dmd: str = "lightcrafter-6500"
    light_serial: str = ""
    light_port: str = ""
    light_channels: int = 0
    light_spectra: str = ""
    light_holdoff_us: int = -1
    ol490_sdk: str = ""
    ol490_sdk_type: str = DEFAULT_SDK_TYPE
    ol490_slit: int = 1
    ol490_grey_bits: int = 6
    compression: str = "erle"
    camera_cti: str = ""
    camera_serial: str = ""
    camera_mode: str = "strobe-master"
    exposure_s: float = 0.010
    frame_rate_hz: float = 0.0
    camera_first_frame_id: int = -1
    camera_strobe_line: str = "Line1"
    camera_trigger_line: str = "Line0"
    dark_time_s: float = 0.0001
    spectrometer: str = ""
    spectrometer_serial: str = ""
    spectrometer_calibration: str = ""
    integration_time_s: float = 0.1

    def __post_init__(self):
        for key, value, valid in (("light", self.light, LIGHTS), ("dmd", self.dmd, tuple(GEOMETRIES)),
                                  ("compression", self.compression, tuple(COMPRESSIONS)),
                                  ("camera_mode", self.camera_mode, MODES),
                                  ("spectrometer", self.spectrometer, SPECTROMETERS)):
            if value not in valid:
                raise ValueError(f"hardware.{key} must be one of {', '.join(repr(v) for v in valid)}, got {value!r}")
        check_number("hardware.exposure_s", self.exposure_s, low=0, low_open=True, high=16.7)
        check_number("hardware.frame_rate_hz", self.frame_rate_hz, low=0, high=1e5)
        check_number("hardware.dark_time_s", self.dark_time_s, low=0, high=16.7)
        if self.camera_mode == "hardware-trigger" and self.dark_time_s < 1e-6:
            raise ValueError(f"hardware.dark_time_s must be at least 1e-6 s in hardware-trigger mode (TRIG_OUT_1 "
                             f"falls only in the dark time), got {self.dark_time_s!r}")
        check_number("hardware.camera_first_frame_id", self.camera_first_frame_id, low=-1, integer=True)
        check_number("hardware.integration_time_s", self.integration_time_s, low=0, low_open=True, high=600)
        check_number("hardware.light_channels", self.light_channels, low=0, high=64, integer=True)
        check_number("hardware.light_holdoff_us", self.light_holdoff_us, low=-1, high=1_000_000, integer=True)
        check_number("hardware.ol490_slit", self.ol490_slit, low=1, high=4, integer=True)
        check_number("hardware.ol490_grey_bits", self.ol490_grey_bits, low=1, high=6, integer=True)
        if self.light == "led" and not self.light_port:
            raise ValueError("hardware.light_port names no serial port: set it to the LED controller's port (e.g. "
                             "/dev/ttyACM0 or COM3)")
        if self.light.startswith(("led", "ol490")) and self.camera_mode != "strobe-master":
            raise ValueError(f"hardware.camera_mode must be 'strobe-master' with hardware.light = {self.light!r}: the "
                             f"camera's strobe steps the light")

    @classmethod
    def from_dict(cls, table: dict, *, source: str = "<dict>", base_dir=None,
                  kind: str | None = None) -> HardwareConfig:
        """From a ``[hardware]`` table; unknown keys and wrong types are errors naming ``source`` and the key.
        Relative file paths resolve against ``base_dir``. ``kind``, the rig's ``[light] kind``, gives the light
        when the table names none and must agree with the one it names."""
        valid = {f.name: f for f in fields(cls)}
        kwargs = {}
        light = light_for_kind(kind, table.get("light"), source=source)
        if light is not None:
            table = {**table, "light": light}
        for key, value in dict(table).items():
            if key not in valid:
                raise ValueError(f"{source}: unknown key hardware.{key}; valid keys: {', '.join(valid)}")
            default = valid[key].default
            if isinstance(default, str):
                if not isinstance(value, str):
                    raise ValueError(f"{source}: hardware.{key} must be a string, got {value!r}")
                if key in FILE_KEYS and value and base_dir is not None:
                    p = Path(value)
                    value = str(p if p.is_absolute() else Path(base_dir) / p)
            elif isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{source}: hardware.{key} must be a number, got {value!r}")
            kwargs[key] = value
        try:
            return cls(**kwargs)
        except ValueError as exc:
            raise ValueError(f"{source}: {exc}") from None


def _kind(rig):
    """The rig's ``[light] kind`` when its description has one (the rig model's key), else None."""
    if rig is None:
        return None
    desc = rig if isinstance(rig, RigDescription) else load_rig(rig)
    return getattr(desc.light, "kind", None)


def _config(hardware, rig=None) -> HardwareConfig:
    if hardware is None:
        hardware = {}
    if isinstance(hardware, HardwareConfig):
        light_for_kind(_kind(rig), hardware.light)  # a light of another kind than the rig's is refused
        return hardware
    if isinstance(hardware, dict):
        return HardwareConfig.from_dict(hardware, kind=_kind(rig))
    raise ValueError(f"hardware must be a HardwareConfig or a [hardware] table, got {type(hardware).__name__}")


def _model(rig):
    if rig is None:
        return ProgrammableLight()
    desc = rig if isinstance(rig, RigDescription) else load_rig(rig)
    return ProgrammableLight(desc.light, seed=desc.seed)


def open_light(hardware=None, *, rig=None, calibration=None, transport=None):
    """The light a :class:`HardwareConfig` names: a :class:`~specgpu.hardware.dlpc900.DLPC900Light`, an
    :class:`~specgpu.hardware.led.LedLight` or an :class:`~specgpu.hardware.ol490.OL490Light` (``transport``
    overrides the USB or simulated link: a DLPC900 transport, the LED board's serial port, the OL490's SDK)."""
    cfg = _config(hardware, rig)
    if cfg.light.startswith("led"):
        return open_led_light(cfg, port=transport)
    if cfg.light.startswith("ol490"):
        return open_ol490_light(cfg, model=_model(rig), calibration=calibration, sdk=transport)
    if transport is None:
        transport = (SimulatedDLPC900(cfg.dmd) if cfg.light == "dlpc900-simulated"
                     else UsbTransport(serial=cfg.light_serial or None))
    device = DLPC900(transport, dmd=cfg.dmd)
    return DLPC900Light(device, model=_model(rig), calibration=calibration, exposure_s=cfg.exposure_s,
                        wait_for_trigger=cfg.camera_mode == "strobe-master", compression=cfg.compression,
                        dark_s=cfg.dark_time_s)


def open_hardware(rig=None, *, hardware=None, patterns=None, calibration=None, n_frames: int | None = None,
                  acquirer=None, transport=None, check_light: bool = True, exposure_s: float | None = None):
    """The camera driver of a real rig (registered as ``"vision-dlpc900"``): a GenICam camera lit by the light the
    table names (a DLPC900, an LED array or an OL490).

    Parameters
    ----------
    rig
        Rig description (or TOML path) whose ``[light]`` gives the light model (columns, rows, grid).
    hardware
        :class:`HardwareConfig` or its table.
    patterns
        (K, C) sequence to upload now.
    calibration
        Optional calibration bundle (column map and forward model of the light).
    n_frames
        Exposures after which the stream ends.
    acquirer, transport
        Injected camera acquirer / light transport (default: opened from the configuration).
    exposure_s
        Exposure of the camera and of each pattern, s (a plan's: its dark frame and decoder are for it); default
        ``hardware.exposure_s``.
    """
    cfg = _config(hardware, rig)
    if exposure_s is not None:
        cfg = replace(cfg, exposure_s=float(exposure_s))  # checked as hardware.exposure_s is
    light = open_light(cfg, rig=rig, calibration=calibration, transport=transport)
    try:
        if patterns is not None:
            light.load_sequence(patterns)
        return GenICamCamera(light, acquirer=acquirer, cti=cfg.camera_cti or None, serial=cfg.camera_serial or None,
                             mode=cfg.camera_mode, exposure_s=cfg.exposure_s,
                             frame_rate_hz=cfg.frame_rate_hz or None, n_frames=n_frames, check_light=check_light,
                             trigger_line=cfg.camera_trigger_line, strobe_line=cfg.camera_strobe_line,
                             first_frame_id=None if cfg.camera_first_frame_id < 0 else cfg.camera_first_frame_id)
    except BaseException:
        light.close()  # the USB link must not stay open behind an error (e.g. harvesters missing)
        raise


def open_spectrometer(hardware=None, *, device=None):
    """The spectrometer a :class:`HardwareConfig` names; ``ValueError`` if it names none."""
    cfg = _config(hardware)
    if cfg.spectrometer != "ocean" and device is None:
        raise ValueError("hardware.spectrometer names no spectrometer; set it to 'ocean' for loop (b)")
    return OceanSpectrometer(device, serial=cfg.spectrometer_serial or None,
                             irradiance_calibration=cfg.spectrometer_calibration or None,
                             integration_time_s=cfg.integration_time_s)


class HardwareRig:
    """What calibration loop (b) reads from a rig, for real devices.

    Parameters
    ----------
    light
        A :class:`~specgpu.hardware.dlpc900.DLPC900Light`.
    spectroradiometer
        An :class:`~specgpu.hardware.ocean.OceanSpectrometer` (or anything with ``measure_spectrum()``,
        ``wavelengths`` and ``params``).
    """

    def __init__(self, light, spectroradiometer):
        self.light = light
        self.spectroradiometer = spectroradiometer

    def measure_spectrum(self, pattern_index: int | None = None, power: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Show loaded pattern ``pattern_index`` (the current one by default) steadily and measure it:
        (wavelengths nm, spectral irradiance W m^-2 nm^-1)."""
        if power != 1.0:
            raise ValueError("a real lamp's power cannot be scaled in software; power must be 1")
        k = self.light.pattern_index if pattern_index is None else int(pattern_index)
        # the sequence loaded, not the one pattern show() leaves in the controller
        self.light.show(self.light.requested[k])
        return self.spectroradiometer.measure_spectrum()


#: GenICam PixelFormat -> top ADC code of the frames.
_MAX_CODES = {"Mono8": 255, "Mono10": 1023, "Mono12": 4095, "Mono14": 16383, "Mono16": 65535}


class HardwareCalibrationRig(HardwareRig):
    """A real rig as a :class:`specgpu.calibration.CalibrationRig`: frames from the GenICam camera lit by the
    DLPC900 (:func:`open_hardware`, through :func:`~specgpu.capture.session.capture_sequences`: ring buffer and
    assembler), spectra from the Ocean spectrometer; the camera looks at the reference white.

    Parameters
    ----------
    description
        The rig description (its ``[light]`` is the light's model: columns, rows, grid, slit).
    camera
        The :class:`~specgpu.hardware.genicam.GenICamCamera` of :func:`open_hardware`; its light is the rig's.
    spectroradiometer
        An :class:`~specgpu.hardware.ocean.OceanSpectrometer` with its irradiance calibration.
    frame_rate_hz
        Camera frame rate at the calibration exposure (strobe-master); ``None``: the description's.

    Each capture sets the exposure on both devices (the camera's ExposureTime and the LUT's pattern exposure) and
    lowers the frame rate when a long exposure needs it; real frames carry fresh noise, so ``noise_seed`` is
    ignored. Sequences lost on the link are left out of the mean (a capture with none complete is an error).
    """

    max_spectrum = None  # a real lamp is known only through the spectrometer

    def __init__(self, description, camera, spectroradiometer, *, frame_rate_hz: float | None = None):
        super().__init__(camera.light, spectroradiometer)
        self.description = description
        self.camera = camera
        self.exposure_s = float(camera.exposure_s)
        self._rate = float(frame_rate_hz or camera.frame_rate_hz or description.camera.frame_rate_hz)
        fmt = str(camera.acquirer.remote_device.node_map.PixelFormat.value)
        self.max_code = _MAX_CODES[fmt]  # the camera refused any other format when it was opened
        self.sequences_lost = 0

    @property
    def frame_shape(self) -> tuple:
        return tuple(self.camera.frame_shape)

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self._rate

    def _set_exposure(self, exposure_s: float) -> None:
        t = float(exposure_s)
        light, cam = self.light, self.camera
        if t < light.minimum_exposure_s:
            raise ValueError(f"exposure {t:g} s is shorter than the light's minimum {light.minimum_exposure_s:g} s")
        light.exposure_s = t  # the LUT's pattern exposure, written with the next upload
        cam.exposure_s = t  # ExposureTime, written by the camera's configure() at start
        # the next strobe must find the pattern over: room for the light's trigger delay and switch, and the
        # pattern's dark time
        switch = max(light.params.switch_time_s, light.minimum_exposure_s)
        cam.frame_rate_hz = min(self._rate, 1.0 / (t + switch + getattr(light, "dark_s", 0.0) + 1e-4))
        cam.timeout_s = max(2.0, 4.0 / cam.frame_rate_hz)

    def capture_mean(self, patterns, repeats: int, *, exposure_s: float | None = None,
                     noise_seed: int | None = None) -> np.ndarray:
        """(K, H, W) float64 mean of ``repeats`` sequences of ``patterns`` captured at ``exposure_s`` (s)."""
        patterns = np.atleast_2d(np.asarray(patterns, np.int32))
        k = patterns.shape[0]
        self._set_exposure(self.exposure_s if exposure_s is None else exposure_s)
        self.light.load_sequence(patterns)
        self.camera.n_frames = k * int(repeats)
        acc = np.zeros((k, *self.frame_shape))
        count = 0

        def add(seq):
            nonlocal count
            acc[...] += seq.frames
            count += 1

        result = capture_sequences(self.camera, k, on_sequence=add)
        self.sequences_lost += result.assembly.sequences_discarded
        if count == 0:
            raise RuntimeError(f"calibration capture: none of the {repeats} sequences of {k} frames arrived complete "
                               f"(dropped {result.assembly.dropped} frames); check the camera link and trigger")
        return acc / count

    def zero_spectrometer(self) -> None:
        """The spectrometer's dark reading, with every mirror off."""
        if hasattr(self.spectroradiometer, "set_dark"):
            self.light.show(np.zeros((1, self.light.layout.columns), np.int32))
            self.spectroradiometer.set_dark()

    def close(self) -> None:
        """Stop the light and release the camera and the spectrometer."""
        try:
            try:
                self.light.stop()  # a pattern show() left up runs on the controller's own clock
            finally:
                self.camera.close()  # and the light's USB link with it
        finally:
            close = getattr(self.spectroradiometer, "close", None)
            if close is not None:
                close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def open_calibration_rig(rig=None, *, hardware=None, acquirer=None, transport=None,
                         spectrometer=None) -> HardwareCalibrationRig:
    """The real rig a ``[hardware]`` table names, opened for :func:`specgpu.calibration.calibrate` (``rig=``).

    Calibration needs the spectrometer (column-wavelength map, lamp power, loop (b)) with its irradiance
    calibration; a table without them is refused before any device is opened. ``acquirer``, ``transport`` and
    ``spectrometer`` (an :class:`~specgpu.hardware.ocean.OceanSpectrometer`, or a seabreeze-like device for it)
    replace the devices the table would open (tests, dry runs).
    """
    desc = rig if isinstance(rig, RigDescription) else load_rig(rig)
    cfg = _config(hardware, desc)
    if not cfg.light.startswith("dlpc900"):
        # the bundle's column map and forward model are a DMD column light's; an LED array's channel spectra come
        # from hardware.light_spectra, and the OL490's loop has not been run on a unit
        raise ValueError(f"calibration on real devices needs a DLPC900 light (hardware.light = 'dlpc900'), got "
                         f"hardware.light = {cfg.light!r}")
    if spectrometer is None or not isinstance(spectrometer, OceanSpectrometer):
        if cfg.spectrometer != "ocean" and spectrometer is None:
            raise ValueError("calibration needs a spectrometer: set hardware.spectrometer = 'ocean' (and "
                             "hardware.spectrometer_calibration)")
        if not cfg.spectrometer_calibration:
            raise ValueError("calibration needs the spectrometer's irradiance calibration: set "
                             "hardware.spectrometer_calibration to its CSV (wavelength nm, W m^-2 nm^-1 per count/s)")
    camera = open_hardware(desc, hardware=cfg, acquirer=acquirer, transport=transport)
    try:
        if not isinstance(spectrometer, OceanSpectrometer):
            spectrometer = open_spectrometer(cfg, device=spectrometer)
        return HardwareCalibrationRig(desc, camera, spectrometer, frame_rate_hz=cfg.frame_rate_hz or None)
    except BaseException:
        camera.close()
        raise
