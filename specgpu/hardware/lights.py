"""Opening the LED and OL490 lights a ``[hardware]`` table names (:class:`~specgpu.hardware.rig.HardwareConfig`):
the real device, or its simulated twin for a dry run (``"led-simulated"``, ``"ol490-simulated"``).

Which family of light a rig has is said twice at most: ``[light] kind`` (``"dmd"``, ``"led"``, ``"ol490"``; the
rig model's key, read here only when the rig description has it) and ``[hardware] light``. :func:`light_for_kind`
gives the hardware light a kind implies when the table does not name one, and refuses a table that names a light
of another kind.
"""

from __future__ import annotations

import numpy as np

from specgpu.hardware.led import LedController, LedLight, SimulatedLedBoard, SimulatedSerial
from specgpu.hardware.ol490 import OL490Light, OL490Unit, SimulatedOL490Sdk, load_dotnet_sdk

__all__ = ["KIND_LIGHTS", "light_for_kind", "read_channel_spectra", "open_led_light", "open_ol490_light"]

#: ``[light] kind`` -> the ``[hardware] light`` values of that kind (the first is the real device).
KIND_LIGHTS = {"dmd": ("dlpc900", "dlpc900-simulated"), "led": ("led", "led-simulated"),
               "ol490": ("ol490", "ol490-simulated")}


def light_for_kind(kind, light: str | None, *, source: str = "<dict>") -> str | None:
    """The ``[hardware] light`` for a rig whose ``[light] kind`` is ``kind``.

    Parameters
    ----------
    kind : str or None
        The rig's ``[light] kind`` (None: not said, ``light`` stands).
    light : str or None
        The table's ``light`` (None: not given).

    Raises
    ------
    ValueError
        ``kind`` is unknown, or ``light`` is of another kind (one line naming both and ``source``).
    """
    if kind is None:
        return light
    if kind not in KIND_LIGHTS:
        raise ValueError(f"{source}: light.kind must be one of {', '.join(repr(k) for k in KIND_LIGHTS)}, got {kind!r}")
    if light is None:
        return KIND_LIGHTS[kind][0]
    if light not in KIND_LIGHTS[kind]:
        raise ValueError(f"{source}: light.kind = {kind!r} but hardware.light = {light!r}; set hardware.light to "
                         f"{' or '.join(repr(v) for v in KIND_LIGHTS[kind])}")
    return light


def read_channel_spectra(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(wavelengths (B,), spectra (channels, B)) from a CSV: wavelength in nm, then one column per channel at full
    duty (W m^-2 nm^-1); a ``#`` line is a comment. ``ValueError`` naming the file if it is not that."""
    try:
        table = np.loadtxt(path, delimiter=",", comments="#", ndmin=2)
    except (OSError, ValueError) as exc:
        raise ValueError(f"hardware.light_spectra {path}: cannot be read as CSV ({str(exc).splitlines()[0]})") from None
    if table.shape[1] < 2 or table.shape[0] < 2 or not np.isfinite(table).all():
        raise ValueError(f"hardware.light_spectra {path}: expected finite rows 'wavelength nm, channel 1, channel 2 "
                         f"...', got a {table.shape[0]} x {table.shape[1]} table")
    if np.any(np.diff(table[:, 0]) <= 0):
        raise ValueError(f"hardware.light_spectra {path}: wavelengths must increase")
    return table[:, 0], table[:, 1:].T


def open_led_light(cfg, *, port=None) -> LedLight:
    """The LED light of ``cfg`` (``light`` ``"led"`` on ``cfg.light_port``, or ``"led-simulated"``); ``port``
    overrides the port (an open serial-port-like object or another name)."""
    if port is None:
        port = SimulatedSerial(SimulatedLedBoard()) if cfg.light == "led-simulated" else cfg.light_port
    wavelengths = spectra = None
    if cfg.light_spectra:
        wavelengths, spectra = read_channel_spectra(cfg.light_spectra)
    controller = LedController(port)
    try:
        channels = cfg.light_channels or (spectra.shape[0] if spectra is not None else None)
        return LedLight(controller, channels=channels, wavelengths=wavelengths, spectra=spectra,
                        holdoff_us=None if cfg.light_holdoff_us < 0 else cfg.light_holdoff_us)
    except BaseException:
        controller.close()
        raise


def open_ol490_light(cfg, *, model=None, calibration=None, sdk=None) -> OL490Light:
    """The OL490 light of ``cfg`` (``light`` ``"ol490"`` through the SDK assembly ``cfg.ol490_sdk``, or
    ``"ol490-simulated"``); ``sdk`` overrides the SDK (an :class:`~specgpu.hardware.ol490.OL490Sdk`)."""
    if sdk is None:
        sdk = SimulatedOL490Sdk() if cfg.light == "ol490-simulated" else load_dotnet_sdk(cfg.ol490_sdk,
                                                                                           cfg.ol490_sdk_type)
    unit = OL490Unit(sdk, cfg.light_serial)
    try:
        return OL490Light(unit, model=model, calibration=calibration, slit=cfg.ol490_slit,
                          grey_bits=cfg.ol490_grey_bits)
    except BaseException:
        unit.close()
        raise
