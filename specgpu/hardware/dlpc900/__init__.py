"""TI DLPC900 (DLP LightCrafter 6500 / 9000) over USB, in three layers as python-seabreeze does:

- :mod:`.transport`: 64-byte HID reports through pyusb (:class:`UsbTransport`) or the simulated controller
  (:class:`SimulatedDLPC900`);
- :mod:`.protocol`: the command table and the report framing of TI's DLPC900 Programmer's Guide (DLPU018);
- :mod:`.device`: :class:`DLPC900`, one method per TI command; :mod:`.images`: patterns <-> bit-planes <-> the
  controller's image format; :mod:`.light`: :class:`DLPC900Light`, the :class:`~specgpu.capture.driver.LightSource`.
"""

from specgpu.hardware.dlpc900.device import DLPC900, HardwareStatus, LutEntry, MainStatus
from specgpu.hardware.dlpc900.images import GEOMETRIES, DMDGeometry, DMDLayout, decode_image, encode_image
from specgpu.hardware.dlpc900.light import DLPC900Light
from specgpu.hardware.dlpc900.protocol import COMMANDS, ERROR_CODES, Protocol
from specgpu.hardware.dlpc900.simulated import SimulatedDLPC900
from specgpu.hardware.dlpc900.transport import PRODUCT_ID, VENDOR_ID, Transport, UsbTransport

__all__ = ["DLPC900", "HardwareStatus", "LutEntry", "MainStatus", "GEOMETRIES", "DMDGeometry", "DMDLayout",
           "decode_image", "encode_image", "DLPC900Light", "COMMANDS", "ERROR_CODES", "Protocol",
           "SimulatedDLPC900", "PRODUCT_ID", "VENDOR_ID", "Transport", "UsbTransport"]
