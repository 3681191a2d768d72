"""pyusb transport on a fake USB device, the USB device list, optional backends, spectrometer and rig config."""

from __future__ import annotations

import sys
from array import array
from collections import deque

import numpy as np
import pytest

usb_core = pytest.importorskip("usb.core")
import usb.util  # noqa: E402

from specgpu.hardware import list_usb_devices  # noqa: E402
from specgpu.hardware.dlpc900 import DLPC900, DLPC900Light, SimulatedDLPC900, UsbTransport  # noqa: E402
from specgpu.hardware.errors import BackendMissing, DeviceDisconnected, DeviceNotFound, DeviceTimeout, HardwareError  # noqa: E402
from specgpu.hardware.rig import HardwareConfig, HardwareRig, open_spectrometer  # noqa: E402


class Endpoint:
    def __init__(self, address):
        self.bEndpointAddress, self.bmAttributes = address, usb.util.ENDPOINT_TYPE_INTR
        self.written, self.replies, self.fail = [], deque(), None

    def write(self, data, timeout):
        if self.fail is not None:
            raise self.fail
        self.written.append(bytes(data))
        return len(data)

    def read(self, size, timeout):
        if self.fail is not None:
            raise self.fail
        return array("B", self.replies.popleft())


class Interface(list):
    bInterfaceClass, bInterfaceSubClass = 0x03, 0x00  # HID


class UsbDev:
    def __init__(self, vid=0x0451, pid=0xC900, bus=1, address=5, interface=None):
        self.idVendor, self.idProduct, self.bus, self.address = vid, pid, bus, address
        self.ep_out, self.ep_in = Endpoint(0x01), Endpoint(0x81)
        self.interface = interface if interface is not None else Interface([self.ep_out, self.ep_in])
        self.detached = False

    def is_kernel_driver_active(self, i):
        return not self.detached

    def detach_kernel_driver(self, i):
        self.detached = True

    def set_configuration(self):
        pass

    def get_active_configuration(self):
        return {(0, 0): self.interface}

    def __iter__(self):  # configurations -> interfaces, for list_usb_devices' class check
        return iter([[self.interface]])


@pytest.fixture
def fake_usb(monkeypatch):
    devices = []

    def find(find_all=False, idVendor=None, idProduct=None, custom_match=None):
        hits = [d for d in devices if (idVendor is None or d.idVendor == idVendor)
                and (idProduct is None or d.idProduct == idProduct) and (custom_match is None or custom_match(d))]
        return hits if find_all else (hits[0] if hits else None)

    monkeypatch.setattr(usb_core, "find", find)
    for name in ("claim_interface", "release_interface", "dispose_resources"):
        monkeypatch.setattr(usb.util, name, lambda *a, **k: None)
    return devices


def test_usb_transport_moves_reports_through_the_interrupt_endpoints(fake_usb):
    dev = UsbDev()
    fake_usb.append(dev)
    dev.ep_in.replies.append(bytes((0xC0, 0x01, 0x01, 0x00, 0x02)) + bytes(59))
    controller = DLPC900(UsbTransport())
    assert dev.detached  # the kernel's usbhid driver was detached from interface 0
    assert controller.main_status().sequencer_running
    # Main Status read: flags C0, sequence 01, length 02 00, command 0C 1A (Section 1.2.2), 64 bytes on the wire
    assert dev.ep_out.written == [bytes((0xC0, 0x01, 0x02, 0x00, 0x0C, 0x1A)) + bytes(58)]


def test_usb_device_absent_and_backend_missing(fake_usb, monkeypatch):
    with pytest.raises(DeviceNotFound, match=r"^DLPC900 \(USB 0451:c900\) not found: is the controller connected"):
        UsbTransport().open()
    fake_usb.append(UsbDev())
    with pytest.raises(DeviceNotFound, match="with serial XYZ not found"):
        UsbTransport(serial="XYZ").open()

    def no_backend(**kw):
        raise usb_core.NoBackendError("No backend available")

    monkeypatch.setattr(usb_core, "find", no_backend)
    with pytest.raises(BackendMissing, match="^pyusb found no libusb backend: install libusb-1.0"):
        UsbTransport().open()
    with pytest.raises(BackendMissing, match="no libusb backend"):
        list_usb_devices()


def test_usb_timeout_and_disconnect_then_reconnect(fake_usb):
    dev = UsbDev()
    fake_usb.append(dev)
    transport = UsbTransport(timeout_ms=250)
    controller = DLPC900(transport)
    dev.ep_in.fail = usb_core.USBTimeoutError("Operation timed out", errno=110)
    with pytest.raises(DeviceTimeout, match=r"DLPC900 \(USB 0451:c900\): read timed out after 250 ms"):
        controller.main_status()
    assert transport.is_open  # a timeout is not a disconnect
    dev.ep_out.fail = usb_core.USBError("No such device (it may have been disconnected)", errno=19)
    with pytest.raises(DeviceDisconnected, match=r"DLPC900 \(USB 0451:c900\) disconnected during write"):
        controller.stop()
    assert not transport.is_open
    with pytest.raises(DeviceDisconnected, match="is not open"):
        controller.stop()
    fake_usb.clear()
    with pytest.raises(DeviceNotFound):
        transport.reconnect(attempts=2, delay_s=0)
    replugged = UsbDev()
    fake_usb.append(replugged)
    transport.reconnect(attempts=1)
    next_seq = controller.protocol._sequence + 1  # failed transactions used up sequence bytes too
    replugged.ep_in.replies.append(bytes((0x40, next_seq, 0x00, 0x00)) + bytes(60))
    controller.stop()  # works again on the replugged device
    assert replugged.ep_out.written[0][4:7] == bytes((0x24, 0x1A, 0x00))


def test_list_usb_devices_names_what_specgpu_drives(fake_usb):
    u3v = Interface()
    u3v.bInterfaceClass, u3v.bInterfaceSubClass = 0xEF, 0x05
    fake_usb.extend([UsbDev(0x1D6B, 0x0002, 1, 1), UsbDev(0x2457, 0x1022, 2, 7), UsbDev(bus=1, address=9),
                     UsbDev(0x2676, 0xBA02, 2, 3, interface=u3v)])
    found = list_usb_devices()
    assert [(d.bus, d.address, d.backend) for d in found] == [(1, 1, ""), (1, 9, "dlpc900"), (2, 3, "genicam"),
                                                               (2, 7, "seabreeze")]
    assert str(found[1]) == "bus 001 address 009  0451:c900  TI DLPC900 (DLP LightCrafter 6500 / 9000) [dlpc900]"
    assert [d.backend for d in list_usb_devices(known_only=True)] == ["dlpc900", "genicam", "seabreeze"]


def test_list_usb_devices_names_led_boards_and_the_ol490_when_its_id_is_given(fake_usb, monkeypatch):
    monkeypatch.delenv("SPECGPU_OL490_USB", raising=False)
    fake_usb.extend([UsbDev(0x16C0, 0x0483, 1, 2), UsbDev(0x2341, 0x0043, 1, 3), UsbDev(0x16C0, 0x0478, 1, 4),
                     UsbDev(0x1234, 0xABCD, 1, 6)])
    found = list_usb_devices()
    assert [d.backend for d in found] == ["led", "led", "", ""]  # a Teensy in its bootloader (0478) is not serial
    assert str(found[0]) == "bus 001 address 002  16c0:0483  Teensy USB serial (LED controller board) [led]"
    assert found[1].description == "Arduino (LED controller board)"
    monkeypatch.setenv("SPECGPU_OL490_USB", "1234:abcd")
    ol490 = list_usb_devices()[3]
    assert (ol490.backend, ol490.description) == ("ol490", "Optronic Laboratories OL490 (VID:PID from "
                                                            "SPECGPU_OL490_USB)")
    monkeypatch.setenv("SPECGPU_OL490_USB", "OL490")
    with pytest.raises(ValueError, match=r"^SPECGPU_OL490_USB must be the OL490's VID:PID in hex \(e.g. 1234:abcd\), "
                                         r"got 'OL490'$"):
        list_usb_devices()


# ---- optional backends: a clear one-line error when absent ------------------------------------------------------
def test_missing_harvesters_and_seabreeze_are_clear(monkeypatch):
    from specgpu.hardware.genicam import open_acquirer
    from specgpu.hardware.ocean import open_seabreeze

    monkeypatch.setitem(sys.modules, "harvesters", None)
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    monkeypatch.setitem(sys.modules, "seabreeze", None)
    monkeypatch.setitem(sys.modules, "seabreeze.spectrometers", None)
    with pytest.raises(BackendMissing, match="^GenICam cameras need the optional 'harvesters' package"):
        open_acquirer("producer.cti")
    with pytest.raises(BackendMissing, match="^Ocean spectrometers need the optional 'seabreeze' package"):
        open_seabreeze()


# ---- Ocean spectrometer and loop (b) ----------------------------------------------------------------------------
class Seabreeze:
    """A seabreeze-like spectrometer: counts = irradiance * t / cal + dark."""

    def __init__(self, irradiance_of, cal, dark=100.0):
        self.pixels = np.linspace(340.0, 1020.0, 2048)
        self.irradiance_of, self.cal, self.dark, self.t_us = irradiance_of, cal, dark, None

    def wavelengths(self):
        return self.pixels

    def integration_time_micros(self, us):
        self.t_us = us

    def intensities(self, correct_dark_counts=False, correct_nonlinearity=False):
        return self.irradiance_of(self.pixels) * (self.t_us * 1e-6) / self.cal + self.dark

    def close(self):
        pass


def test_ocean_spectrometer_counts_to_irradiance():
    cal = np.full(2048, 2e-6)
    truth = lambda wl: 0.01 * np.exp(-0.5 * ((wl - 550.0) / 40.0) ** 2)  # noqa: E731
    dev = Seabreeze(truth, cal)
    meter = open_spectrometer({"spectrometer": "ocean", "integration_time_s": 0.05}, device=dev)
    assert dev.t_us == 50000 and meter.wavelengths[[0, -1]].tolist() == [380.0, 780.0]
    with pytest.raises(HardwareError, match="no irradiance calibration"):
        meter.measure()
    meter.calibration = cal
    meter.set_dark(np.full(2048, 100.0))
    np.testing.assert_allclose(meter.measure(), truth(meter.wavelengths), atol=1e-6)
    with pytest.raises(TypeError, match="measures the light itself"):
        meter.measure(truth(meter.wavelengths), meter.wavelengths)
    assert meter.response_matrix(np.arange(370.0, 791.0)).shape == (401, 421)


def test_spectral_loop_b_runs_on_hardware_rig():
    # Loop (b) of the calibration against a HardwareRig: the DLPC900 light on the simulated controller, and a
    # spectrometer that sees what the controller displays (pattern decoded from the uploaded mirrors).
    from specgpu.calibration import spectral_loop
    from specgpu.rig.light import LightParameters, ProgrammableLight

    model = ProgrammableLight(LightParameters(columns=128, rows=64, fluctuation_rms=0.0))
    sim = SimulatedDLPC900("lightcrafter-6500")
    light = DLPC900Light(DLPC900(sim), model=model, exposure_s=0.005)

    def irradiance_of(wl):
        assert sim.running  # the spectrometer only ever reads a light that is on
        pattern = light.layout.mask_to_pattern(sim.displayed_mask())
        return np.interp(wl, model.wavelengths, model.pattern_to_spectrum(pattern))

    dev = Seabreeze(irradiance_of, np.full(2048, 1e-7), dark=0.0)
    meter = open_spectrometer({"spectrometer": "ocean"}, device=dev)
    meter.calibration = np.full(2048, 1e-7)
    target = 0.5 * model.pattern_to_spectrum(np.full(128, 64))
    result = spectral_loop(HardwareRig(light, meter), target, tolerance=0.02, max_iterations=8, averages=1)
    assert result.converged, result.history
    assert sim.lut_entries == 1 and sim.lut[0]["options"] >> 7 == 0  # shown on the controller's own clock


def test_hardware_config_validation():
    cfg = HardwareConfig.from_dict({"dmd": "lightcrafter-9000", "camera_cti": "p.cti", "exposure_s": 0.02},
                                   source="rig.toml", base_dir="/opt/rig")
    assert cfg.camera_cti == "/opt/rig/p.cti" and cfg.exposure_s == 0.02
    with pytest.raises(ValueError, match="^rig.toml: unknown key hardware.camera; valid keys: light, dmd"):
        HardwareConfig.from_dict({"camera": "x"}, source="rig.toml")
    with pytest.raises(ValueError, match="^rig.toml: hardware.dmd must be one of 'lightcrafter-6500'"):
        HardwareConfig.from_dict({"dmd": "dlp3000"}, source="rig.toml")
    with pytest.raises(ValueError, match="hardware.exposure_s must be a number"):
        HardwareConfig.from_dict({"exposure_s": "fast"}, source="rig.toml")
    with pytest.raises(ValueError, match="names no spectrometer"):
        open_spectrometer({})


def test_open_hardware_releases_the_light_when_the_camera_cannot_open():
    """A camera that fails to open (here: harvesters missing, or no camera) must not leave the USB link open."""
    from specgpu.hardware.dlpc900 import SimulatedDLPC900
    from specgpu.hardware.rig import open_hardware

    sim = SimulatedDLPC900("lightcrafter-6500")
    with pytest.raises(Exception) as error:
        open_hardware(hardware={"light": "dlpc900-simulated"}, transport=sim,
                      patterns=np.zeros((2, 1024), np.int32))
    assert "\n" not in str(error.value)
    assert not sim.is_open
