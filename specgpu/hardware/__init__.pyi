"""Public names of :mod:`specgpu.hardware`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .drivers import hardware_config, open_rig_driver
from .errors import (
    BackendMissing,
    CommandRejected,
    DeviceDisconnected,
    DeviceNotFound,
    DeviceTimeout,
    HardwareError,
    LightFault,
    ProtocolError,
)
from .usb import UsbDevice, list_usb_devices

__all__ = [
    "BackendMissing",
    "CommandRejected",
    "DeviceDisconnected",
    "DeviceNotFound",
    "DeviceTimeout",
    "hardware_config",
    "HardwareError",
    "LightFault",
    "list_usb_devices",
    "open_rig_driver",
    "ProtocolError",
    "UsbDevice",
]
