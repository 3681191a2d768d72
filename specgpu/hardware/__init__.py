"""Real devices behind the capture interfaces: the DLPC900 light (:mod:`.dlpc900`), LED arrays on a serial controller
board (:mod:`.led`), the OL490 through its vendor's SDK (:mod:`.ol490`), GenICam cameras through
harvesters (:mod:`.genicam`), Ocean spectrometers through python-seabreeze (:mod:`.ocean`) and the USB device list
(:func:`list_usb_devices`). Optional dependencies load only when a backend is used.
"""

from specgpu.hardware.errors import (BackendMissing, CommandRejected, DeviceDisconnected, DeviceNotFound,
                                     DeviceTimeout, HardwareError, LightFault, ProtocolError)
from specgpu.hardware.usb import UsbDevice, list_usb_devices

__all__ = ["BackendMissing", "CommandRejected", "DeviceDisconnected", "DeviceNotFound", "DeviceTimeout",
           "HardwareError", "LightFault", "ProtocolError", "UsbDevice", "list_usb_devices"]

from specgpu.hardware.drivers import hardware_config, open_driver  # noqa: E402

__all__ += ["hardware_config", "open_driver"]
