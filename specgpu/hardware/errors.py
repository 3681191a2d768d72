"""Errors of the hardware backends: one class per thing a user must do something different about.

Every message is one line naming the device and the problem (and, where there is one, the fix).
"""

from __future__ import annotations

__all__ = ["HardwareError", "BackendMissing", "DeviceNotFound", "DeviceTimeout", "DeviceDisconnected",
           "CommandRejected", "ProtocolError", "LightFault"]


class HardwareError(RuntimeError):
    """Base class of every hardware backend error."""


class BackendMissing(HardwareError):
    """An optional dependency (pyusb's libusb backend, harvesters, seabreeze) is not installed."""


class DeviceNotFound(HardwareError):
    """The device is not connected (or not powered, or not visible to this user)."""


class DeviceTimeout(HardwareError):
    """The device did not answer in time."""


class DeviceDisconnected(HardwareError):
    """The device went away (unplugged, reset, powered off) while in use."""


class CommandRejected(HardwareError):
    """The device answered a command with its error flag set.

    Attributes
    ----------
    code : int
        The controller's error code (DLPC900: Read Error Code, 0x0100), -1 if it could not be read.
    description : str
        The controller's error text (DLPC900: Read Error Description, 0x0101), "" if none.
    """

    def __init__(self, message: str, code: int = -1, description: str = ""):
        super().__init__(message)
        self.code = code
        self.description = description


class ProtocolError(HardwareError):
    """A reply that does not follow the protocol (wrong sequence byte, short or truncated report)."""


class LightFault(HardwareError):
    """The light source stopped following the sequence (its sequencer is not running)."""
