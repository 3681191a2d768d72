"""The USB devices this machine sees, with the ones specgpu can drive named (for ``specgpu info --usb``).

LED controller boards are known by their USB serial identity: a Teensy's (VID 0x16C0, PID 0x0483) and any
Arduino's (VID 0x2341); either shows a board that may run the specgpu LED firmware (opening its port says whether
it does). The OL490's VID/PID is not published, so none is assumed: set ``SPECGPU_OL490_USB`` to its ``VID:PID`` in
hex (as ``lsusb`` shows it) and the unit is named too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from specgpu.hardware.dlpc900.transport import import_pyusb, no_backend_message
from specgpu.hardware.errors import BackendMissing

__all__ = ["UsbDevice", "list_usb_devices", "KNOWN_DEVICES", "OL490_USB_VARIABLE", "ol490_usb_id"]

#: (vendor, product or None for any) -> what it is and which specgpu backend drives it.
KNOWN_DEVICES = {
    (0x0451, 0xC900): ("TI DLPC900 (DLP LightCrafter 6500 / 9000)", "dlpc900"),
    (0x2457, None): ("Ocean Insight / Ocean Optics spectrometer", "seabreeze"),
    (0x16C0, 0x0483): ("Teensy USB serial (LED controller board)", "led"),
    (0x2341, None): ("Arduino (LED controller board)", "led"),
}
#: Environment variable holding the OL490's ``VID:PID`` (hex), which specgpu does not assume.
OL490_USB_VARIABLE = "SPECGPU_OL490_USB"
_USB3_VISION = (0xEF, 0x05)  # interface class (miscellaneous), subclass USB3 Vision


@dataclass(frozen=True)
class UsbDevice:
    """One USB device.

    Attributes
    ----------
    vendor_id, product_id : int
    bus, address : int
    description : str
        What specgpu knows it as ("" if not a device specgpu drives).
    backend : str
        The specgpu backend that drives it ("" if none).
    """

    vendor_id: int
    product_id: int
    bus: int
    address: int
    description: str = ""
    backend: str = ""

    def __str__(self) -> str:
        what = f"  {self.description} [{self.backend}]" if self.description else ""
        return f"bus {self.bus:03d} address {self.address:03d}  {self.vendor_id:04x}:{self.product_id:04x}{what}"


def ol490_usb_id() -> tuple[int, int] | None:
    """The OL490's (VID, PID) from ``SPECGPU_OL490_USB`` (``"VVVV:PPPP"`` in hex); None when unset.

    Raises
    ------
    ValueError
        The variable is set but not two hex numbers joined by a colon.
    """
    value = os.environ.get(OL490_USB_VARIABLE, "").strip()
    if not value:
        return None
    try:
        vid, pid = (int(part, 16) for part in value.split(":"))
        if not (0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF):
            raise ValueError
    except ValueError:
        raise ValueError(f"{OL490_USB_VARIABLE} must be the OL490's VID:PID in hex (e.g. 1234:abcd), got "
                         f"{value!r}") from None
    return vid, pid


def _classify(dev, known) -> tuple[str, str]:
    for (vid, pid), (text, backend) in known.items():
        if dev.idVendor == vid and (pid is None or dev.idProduct == pid):
            return text, backend
    try:
        for cfg in dev:
            for intf in cfg:
                if (intf.bInterfaceClass, intf.bInterfaceSubClass) == _USB3_VISION:
                    return "USB3 Vision camera (GenICam)", "genicam"
    except Exception:  # descriptors unreadable without permission: just not classified
        pass
    return "", ""


def list_usb_devices(*, known_only: bool = False, find=None) -> list[UsbDevice]:
    """USB devices present, those specgpu drives described.

    Parameters
    ----------
    known_only
        Only the devices a specgpu backend drives.
    find
        ``usb.core.find`` replacement (tests).

    Raises
    ------
    BackendMissing
        pyusb or its libusb backend is not installed (one line, with the fix).
    """
    if find is None:

        core, _ = import_pyusb()
        try:
            devices = list(core.find(find_all=True))
        except core.NoBackendError:
            raise BackendMissing(no_backend_message()) from None
    else:
        devices = list(find(find_all=True))
    known = dict(KNOWN_DEVICES)
    ol490 = ol490_usb_id()
    if ol490 is not None:  # before the generic entries: its VID/PID is the user's, it wins
        known = {ol490: (f"Optronic Laboratories OL490 (VID:PID from {OL490_USB_VARIABLE})", "ol490"), **known}
    out = []
    for d in devices:
        text, backend = _classify(d, known)
        if known_only and not backend:
            continue
        out.append(UsbDevice(int(d.idVendor), int(d.idProduct), int(getattr(d, "bus", 0) or 0),
                             int(getattr(d, "address", 0) or 0), text, backend))
    return sorted(out, key=lambda u: (u.bus, u.address))
