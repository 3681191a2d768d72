"""The OL490 driver against the simulated SDK: the SDK calls, grey depth and frame rate, the light behind the
capture interfaces, the .NET adapter's call table, and the faults (an SDK call that fails, a unit that is not
connected or goes away, a missed trigger, pythonnet absent), each a one-line error with nothing recorded lost."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
from hw_fakes import Buffer, NodeMap

from specgpu.capture import capture_sequences
from specgpu.hardware.errors import BackendMissing, CommandRejected, DeviceDisconnected, DeviceNotFound, LightFault
from specgpu.hardware.genicam import GenICamCamera
from specgpu.hardware.ol490 import DOTNET_CALLS, DotNetSdk, OL490Light, OL490Unit, SimulatedOL490Sdk, load_dotnet_sdk
from specgpu.rig.light import LightParameters, ProgrammableLight

COLUMNS, ROWS = 16, 40


def model():
    return ProgrammableLight(LightParameters(columns=COLUMNS, rows=ROWS))


def light(sim=None, **kw):
    sim = sim or SimulatedOL490Sdk()
    return sim, OL490Light(OL490Unit(sim), model=model(), **kw)


def sequence(k=4, seed=0):
    p = np.random.default_rng(seed).integers(0, ROWS + 1, (k, COLUMNS))
    p[0] = 0
    return p


class OL490Camera:
    """A free-running camera whose strobe drives the unit's trigger input; the frame is the levels shown."""

    def __init__(self, sim, exposures, on_exposure=None):
        self.sim, self.exposures, self.on_exposure = sim, exposures, on_exposure
        self.remote_device = type("Remote", (), {"node_map": NodeMap(2, 1024)})()
        self.n, self.started = 0, False

    def start(self):
        self.started, self.n = True, 0

    def stop(self):
        self.started = False

    def fetch(self, timeout=None):
        if not self.started or self.n >= self.exposures:
            raise TimeoutError("no buffer")
        n, self.n = self.n, self.n + 1
        if self.on_exposure is not None and self.on_exposure(n) == "skip":
            pass  # the edge never reaches the unit
        else:
            self.sim.trigger()
        return Buffer(np.tile(self.sim.shown.astype(np.uint16), (2, 1)), n, n * 10_000_000)


def test_sdk_calls_calibration_grey_depth_and_frame_rate():
    sim, ol = light(slit=3, grey_bits=2)
    assert sim.calls[:4] == ["connect", "load_calibration", "set_grey_depth", "max_frame_rate"]
    assert (sim.calibration, sim.bits) == (3, 2)
    assert ol.max_frame_rate_hz == pytest.approx(16000 / 3)
    assert ol.minimum_exposure_s == pytest.approx(3 / 16000)
    _, deep = light(grey_bits=6)
    assert deep.max_frame_rate_hz == pytest.approx(16000 / 63)  # deeper grey, slower frames
    p = np.array([[0, 13, 14, 27, 40] + [40] * (COLUMNS - 5)])
    ol.load_sequence(p)
    levels = sim.sequence[0, ::1024 // COLUMNS]
    np.testing.assert_array_equal(levels[:5], [0, 1, 1, 2, 3])  # count / 40 * 3, rounded
    assert sim.sequence.shape == (1, 1024) and (sim.sequence[0, :64] == 0).all()  # a column spans 64 DMD columns
    np.testing.assert_array_equal(ol.sequence[0, :5], [0, 13, 13, 27, 40])  # what is shown, as mirror counts
    np.testing.assert_allclose(ol.emitted_spectrum(0), ol.model.pattern_to_spectrum(ol.sequence[0]))
    ol.show(p[0])
    np.testing.assert_array_equal(sim.shown, sim.sequence[0])
    with pytest.raises(ValueError, match="grey_bits must"):
        light(grey_bits=7)


def test_capture_steps_the_sequence_by_trigger():
    k = 4
    sim, ol = light(grey_bits=6)
    p = sequence(k)
    ol.load_sequence(p)
    camera = GenICamCamera(ol, acquirer=OL490Camera(sim, 3 * k), exposure_s=0.01, n_frames=3 * k, first_frame_id=0)
    result = capture_sequences(camera, k)
    assert len(result.sequences) == 3
    want = ol.to_levels(p)
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames[:, 0, :], want)
    assert not sim.running


def test_failed_sdk_call_is_one_line_naming_the_call_and_loads_nothing():
    sim, ol = light()
    sim.fail_calls["load_sequence"] = "Device memory write error.\n   at OL490.Memory.Write()"
    with pytest.raises(CommandRejected, match=r"^OL490: SDK call load_sequence failed: Device memory write error\.$"):
        ol.load_sequence(sequence())
    assert ol.requested.shape == (4, COLUMNS)
    with pytest.raises(RuntimeError, match="no sequence loaded"):
        ol.start()
    sim = SimulatedOL490Sdk()
    sim.fail_calls["load_calibration"] = "Calibration file for slit 2 is corrupt"
    with pytest.raises(CommandRejected, match="SDK call load_calibration failed: Calibration file for slit 2"):
        light(sim, slit=2)


def test_unit_not_connected_or_gone():
    with pytest.raises(DeviceNotFound, match=r"^OL490 not connected: the SDK found no unit; is it powered"):
        light(SimulatedOL490Sdk(present=False))
    with pytest.raises(DeviceNotFound, match=r"^OL490 XYZ not connected: the SDK found no unit with that serial"):
        OL490Unit(SimulatedOL490Sdk(), serial="XYZ")
    k = 3
    sim, ol = light()
    ol.load_sequence(sequence(k))
    camera = GenICamCamera(ol, acquirer=OL490Camera(sim, 4 * k, on_exposure=lambda n: n == 2 * k and sim.unplug()),
                           exposure_s=0.01, n_frames=4 * k, first_frame_id=0)
    got = []
    with pytest.raises(DeviceDisconnected, match=r"^OL490 disconnected: SDK call sequence_running failed: OL490 is "
                                                 r"not connected$"):
        capture_sequences(camera, k, on_sequence=got.append)
    assert len(got) == 2  # the sequences before the unit went away are kept
    with pytest.raises(DeviceDisconnected, match=r"^OL490 is not connected \(SDK call send_pattern\)"):
        ol.show(sequence(1)[0])


def test_missed_trigger_refuses_the_affected_sequence():
    k = 4
    sim, ol = light()
    ol.load_sequence(sequence(k))
    camera = GenICamCamera(ol, acquirer=OL490Camera(sim, 4 * k, on_exposure=lambda n: "skip" if n == k + 2 else None),
                           exposure_s=0.01, n_frames=4 * k, first_frame_id=0)
    got = []
    with pytest.raises(LightFault, match=rf"^OL490 stepped {k + 2} times for {k + 3} camera exposures: a trigger "
                                         r"was missed"):
        capture_sequences(camera, k, on_sequence=got.append)
    assert len(got) == 1


def test_pythonnet_absent_or_no_assembly_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "clr", None)  # import clr -> ImportError, as without pythonnet
    with pytest.raises(BackendMissing, match=r"^OL490: the vendor SDK \(C:/OL490/sdk.dll, hardware.ol490_sdk\) is "
                                             r"loaded through pythonnet, which is not installed: pip install "
                                             r"'specgpu\[ol490\]'$"):
        load_dotnet_sdk("C:/OL490/sdk.dll")
    with pytest.raises(BackendMissing, match="set hardware.ol490_sdk to the vendor's OL490 SDK .dll"):
        load_dotnet_sdk("")
    clr = types.ModuleType("clr")
    clr.AddReference = lambda path: None
    monkeypatch.setitem(sys.modules, "clr", clr)
    with pytest.raises(DeviceNotFound, match=r"OL490 SDK assembly .*missing.dll \(hardware.ol490_sdk\) not found"):
        load_dotnet_sdk(str(tmp_path / "missing.dll"))
    dll = tmp_path / "sdk.dll"
    dll.write_bytes(b"MZ")
    with pytest.raises(Exception, match=r"cannot load NoSuchNamespace.Library \(hardware.ol490_sdk_type\)"):
        load_dotnet_sdk(str(dll), "NoSuchNamespace.Library")


def test_dotnet_adapter_calls_the_sdk_methods_its_table_names(monkeypatch):
    system = types.ModuleType("System")

    class Array:
        def __class_getitem__(cls, item):
            return list

    system.Array, system.Int32 = Array, int
    monkeypatch.setitem(sys.modules, "System", system)
    log = []

    class Library:  # the vendor's .NET object, as pythonnet exposes it
        def __getattr__(self, name):
            return lambda *args: log.append((name, args)) or True

    sdk = DotNetSdk(Library(), calls={"connect": "OpenDevice"})
    assert OL490Unit(sdk, serial="123").connected
    sdk.set_grey_depth(4)
    sdk.send_pattern(np.arange(3))
    sdk.load_sequence(np.ones((2, 2), int))
    assert log == [("OpenDevice", ("123",)), (DOTNET_CALLS["set_grey_depth"], (4,)),
                   (DOTNET_CALLS["send_pattern"], ([0, 1, 2],)), (DOTNET_CALLS["load_sequence"], ([[1, 1], [1, 1]],))]


def test_rig_table_opens_the_ol490_light_with_its_slit_and_grey_depth():
    from specgpu.hardware.rig import HardwareConfig, open_light

    sim = SimulatedOL490Sdk()
    ol = open_light({"light": "ol490", "ol490_slit": 4, "ol490_grey_bits": 3}, transport=sim)
    assert isinstance(ol, OL490Light) and (sim.calibration, sim.bits) == (4, 3)
    assert ol.max_frame_rate_hz == pytest.approx(16000 / 7)
    assert isinstance(open_light({"light": "ol490-simulated"}), OL490Light)
    with pytest.raises(ValueError, match="hardware.ol490_grey_bits must"):
        HardwareConfig.from_dict({"light": "ol490", "ol490_grey_bits": 8})
    with pytest.raises(BackendMissing, match="set hardware.ol490_sdk"):
        open_light({"light": "ol490"})  # a real unit, and no SDK assembly named
