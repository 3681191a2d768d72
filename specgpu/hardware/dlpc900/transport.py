"""DLPC900 transport: 64-byte HID reports over the controller's USB interrupt endpoints, through pyusb.

The transport knows nothing of commands: it opens the device (vendor 0x0451, product 0xC900), moves reports and
turns every USB failure into one of three errors a caller can act on: :class:`DeviceNotFound` (absent, or no libusb
backend: :class:`BackendMissing`), :class:`DeviceTimeout` and :class:`DeviceDisconnected`. ``reconnect`` reopens
the device after a disconnect (e.g. the controller was reset).
"""

from __future__ import annotations

import abc
import errno
import sys
import time

from specgpu.hardware.dlpc900.protocol import REPORT_SIZE
from specgpu.hardware.errors import BackendMissing, DeviceDisconnected, DeviceNotFound, DeviceTimeout

__all__ = ["Transport", "UsbTransport", "VENDOR_ID", "PRODUCT_ID", "import_pyusb", "WINDOWS_DRIVER_HINT"]

VENDOR_ID = 0x0451  # Texas Instruments
PRODUCT_ID = 0xC900  # DLPC900

# errno values pyusb reports when the device is gone (libusb: NO_DEVICE -> ENODEV, IO -> EIO, PIPE -> EPIPE)
_GONE = {errno.ENODEV, errno.EIO, errno.EPIPE, errno.ENOENT, errno.ESHUTDOWN}


def import_pyusb():
    """``(usb.core, usb.util)``; :class:`BackendMissing` (one line, with the fix) if pyusb is not installed."""
    try:
        import usb.core
        import usb.util
    except ImportError:
        raise BackendMissing("USB devices need the 'pyusb' package: pip install pyusb") from None
    return usb.core, usb.util


#: Windows binds the DLPC900 to its HID driver, which libusb cannot claim.
WINDOWS_DRIVER_HINT = ("on Windows, replace the controller's HID driver by WinUSB (e.g. with Zadig: device "
                       "0451:C900) so libusb can open it")


def no_backend_message() -> str:
    return ("pyusb found no libusb backend: install libusb-1.0 (Debian/Ubuntu: apt install libusb-1.0-0; "
            "macOS: brew install libusb; Windows: libusb-1.0.dll next to Python, and " + WINDOWS_DRIVER_HINT + ")")



class Transport(abc.ABC):
    """Moves whole 64-byte HID reports to and from one device."""

    report_size = REPORT_SIZE

    @abc.abstractmethod
    def open(self) -> None:
        """Find and claim the device; :class:`DeviceNotFound` or :class:`BackendMissing` on failure."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device (idempotent)."""

    @property
    @abc.abstractmethod
    def is_open(self) -> bool:
        """Whether the device is claimed."""

    @abc.abstractmethod
    def write(self, report: bytes) -> None:
        """Send one 64-byte report."""

    @abc.abstractmethod
    def read(self, timeout_ms: int | None = None) -> bytes:
        """Receive one 64-byte report; :class:`DeviceTimeout` if none arrives in time."""

    def reconnect(self, attempts: int = 3, delay_s: float = 0.5) -> None:
        """Close and reopen, retrying ``attempts`` times ``delay_s`` apart; the last failure propagates."""
        for i in range(attempts):
            self.close()
            try:
                self.open()
                return
            except DeviceNotFound:
                if i == attempts - 1:
                    raise
                time.sleep(delay_s)

    def __enter__(self):
        if not self.is_open:
            self.open()
        return self

    def __exit__(self, *exc):
        self.close()


class UsbTransport(Transport):
    """The DLPC900's HID interface through pyusb (libusb).

    Parameters
    ----------
    timeout_ms
        Timeout of each report transfer.
    vendor_id, product_id
        USB ids (the DLPC900's by default).
    serial
        Optional USB serial number, to pick one of several controllers.
    """

    def __init__(self, *, timeout_ms: int = 1000, vendor_id: int = VENDOR_ID, product_id: int = PRODUCT_ID,
                 serial: str | None = None):
        self.timeout_ms = int(timeout_ms)
        self.vendor_id, self.product_id, self.serial = vendor_id, product_id, serial
        self._dev = self._ep_out = self._ep_in = None
        self._interface = 0

    @property
    def name(self) -> str:
        return f"DLPC900 (USB {self.vendor_id:04x}:{self.product_id:04x})"

    @property
    def is_open(self) -> bool:
        return self._dev is not None

    def open(self) -> None:
        core, util = import_pyusb()
        match = None if self.serial is None else (lambda d: _serial(util, d) == self.serial)
        try:
            dev = core.find(idVendor=self.vendor_id, idProduct=self.product_id, custom_match=match)
        except core.NoBackendError:
            raise BackendMissing(no_backend_message()) from None
        if dev is None:
            which = "" if self.serial is None else f" with serial {self.serial}"
            if sys.platform.startswith("win"):
                raise DeviceNotFound(f"{self.name}{which} not found: is the controller connected and powered? "
                                     f"{WINDOWS_DRIVER_HINT[0].upper() + WINDOWS_DRIVER_HINT[1:]}")
            raise DeviceNotFound(f"{self.name}{which} not found: is the controller connected, powered and "
                                 "readable by this user (udev rule)?")
        try:
            try:
                if dev.is_kernel_driver_active(self._interface):  # Linux binds usbhid to it
                    dev.detach_kernel_driver(self._interface)
            except NotImplementedError:  # not on this OS
                pass
            try:
                dev.set_configuration()
            except core.USBError as exc:
                if getattr(exc, "errno", None) != errno.EBUSY:  # already configured by another claim: fine
                    raise
            cfg = dev.get_active_configuration()
            intf = cfg[(self._interface, 0)]

            def endpoint(direction):
                return util.find_descriptor(intf, custom_match=lambda e: (
                    util.endpoint_direction(e.bEndpointAddress) == direction
                    and util.endpoint_type(e.bmAttributes) == util.ENDPOINT_TYPE_INTR))

            ep_out, ep_in = endpoint(util.ENDPOINT_OUT), endpoint(util.ENDPOINT_IN)
            if ep_out is None or ep_in is None:
                raise DeviceNotFound(f"{self.name}: no HID interrupt IN/OUT endpoints on interface 0 "
                                     "(is this really a DLPC900?)")
            util.claim_interface(dev, self._interface)
        except core.USBError as exc:
            extra = f"; {WINDOWS_DRIVER_HINT}" if sys.platform.startswith("win") else ""
            raise DeviceNotFound(f"{self.name}: cannot claim the USB interface ({exc}); is another program "
                                 f"(TI's GUI) using it?{extra}") from None
        self._dev, self._ep_out, self._ep_in = dev, ep_out, ep_in

    def close(self) -> None:
        dev, self._dev = self._dev, None
        if dev is None:
            return
        try:
            _, util = import_pyusb()
            util.release_interface(dev, self._interface)
            util.dispose_resources(dev)
        except Exception:  # the device may already be gone; closing must not fail
            pass

    def _fail(self, exc, what: str):
        core, _ = import_pyusb()
        if isinstance(exc, getattr(core, "USBTimeoutError", ())) or getattr(exc, "errno", None) == errno.ETIMEDOUT:
            return DeviceTimeout(f"{self.name}: {what} timed out after {self.timeout_ms} ms")
        self.close()
        if getattr(exc, "errno", None) in _GONE or getattr(exc, "backend_error_code", None) == -4:
            return DeviceDisconnected(f"{self.name} disconnected during {what} ({exc})")
        return DeviceDisconnected(f"{self.name}: USB error during {what} ({exc})")

    def write(self, report: bytes) -> None:
        if self._dev is None:
            raise DeviceDisconnected(f"{self.name} is not open")
        if len(report) != REPORT_SIZE:
            raise ValueError(f"a HID report is {REPORT_SIZE} bytes, got {len(report)}")
        core, _ = import_pyusb()
        try:
            n = self._ep_out.write(bytes(report), self.timeout_ms)
        except core.USBError as exc:
            raise self._fail(exc, "write") from None
        if n != REPORT_SIZE:
            raise DeviceDisconnected(f"{self.name}: short write ({n} of {REPORT_SIZE} bytes)")

    def read(self, timeout_ms: int | None = None) -> bytes:
        if self._dev is None:
            raise DeviceDisconnected(f"{self.name} is not open")
        core, _ = import_pyusb()
        try:
            data = self._ep_in.read(REPORT_SIZE, self.timeout_ms if timeout_ms is None else int(timeout_ms))
        except core.USBError as exc:
            raise self._fail(exc, "read") from None
        return bytes(data)


def _serial(util, dev) -> str | None:
    try:
        return util.get_string(dev, dev.iSerialNumber)
    except Exception:  # no permission to read strings, or no serial descriptor
        return None
