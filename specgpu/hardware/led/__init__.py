"""LED arrays on a controller board over a documented serial protocol: the protocol (:mod:`.protocol`), the host's
driver (:class:`LedController`), the light (:class:`LedLight`) and a simulated board (:class:`SimulatedLedBoard`)
that follows the same protocol, for CI and dry runs."""

from specgpu.hardware.led.controller import FIRMWARE_PATH, LedController, open_serial
from specgpu.hardware.led.light import LedLight
from specgpu.hardware.led.protocol import PROTOCOL_VERSION, Identity, Status
from specgpu.hardware.led.simulated import SimulatedLedBoard, SimulatedSerial, serve

__all__ = ["FIRMWARE_PATH", "LedController", "open_serial", "LedLight", "PROTOCOL_VERSION", "Identity", "Status",
           "SimulatedLedBoard", "SimulatedSerial", "serve"]
