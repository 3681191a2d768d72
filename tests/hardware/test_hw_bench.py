"""What would fail on a real bench, on the simulated controller and the bench camera of ``hw_fakes``:
trigger timing (dark time, start order), clear-after-exposure, read-only strobe lines, missing timestamps, 16-bit
GigE Vision block ids, and the controller's and spectrometer's quirks.

Every test here runs on the fakes (no GenICam producer); the tests against the genicam package's virtual GenTL
producer are in ``test_hw_gentl.py``.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from hw_fakes import FakeCamera, NodeMap, gev_block_id
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.capture import capture_sequences
from specgpu.hardware.dlpc900 import DLPC900, DLPC900Light, DMDGeometry, DMDLayout, LutEntry, SimulatedDLPC900
from specgpu.hardware.dlpc900.device import HardwareStatus
from specgpu.hardware.errors import CommandRejected, DeviceTimeout, HardwareError
from specgpu.hardware.genicam import GenICamCamera

DMD = DMDGeometry("test-dmd", 160, 48)
#: A camera whose strobe line is a GPIO (mode writable): the strobe set-up is not what the test is about.
GPIO = {"Line0": ("Input", False), "Line1": ("Output", True)}
COLUMNS, ROWS = 16, 40


def render(layout, light) -> np.ndarray:
    c0 = layout.column_offset
    counts = np.asarray(light, np.float64)[:, c0:c0 + layout.columns * layout.column_step].sum(axis=0)
    counts = counts.reshape(layout.columns, layout.column_step).sum(axis=1)
    return np.rint(counts[None, :] * 10 + np.arange(4)[:, None] + 1).astype(np.uint16)


def bench(k=6, *, mode="strobe-master", exposures=None, light_kw=None, camera_kw=None, **cam):
    """Controller, light (sequence loaded), bench camera and the GenICam driver over them."""
    sim = SimulatedDLPC900(DMD)
    layout = DMDLayout(DMD, COLUMNS, ROWS)
    light = DLPC900Light(DLPC900(sim, dmd=DMD), layout=layout, exposure_s=0.001,
                         wait_for_trigger=mode == "strobe-master", **(light_kw or {}))
    patterns = np.random.default_rng(k).integers(0, ROWS + 1, (k, COLUMNS))
    patterns[0] = 0
    light.load_sequence(patterns)
    n = exposures if exposures is not None else 3 * k
    acquirer = FakeCamera(sim, lambda m: render(layout, m), n, shape=(4, COLUMNS), **cam)
    camera = GenICamCamera(light, acquirer=acquirer, mode=mode, exposure_s=0.001, n_frames=n,
                           **(camera_kw or {}))
    want = np.stack([render(layout, layout.pattern_to_mask(p)) for p in patterns])
    return sim, light, camera, want


def assert_all_sequences_match(result, want, n_sequences):
    assert len(result.sequences) == n_sequences
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames, want)


# ---- hardware-trigger capture: dark time and start order ------------------------------------------------
def test_zero_dark_time_gives_one_trig_out_edge_for_the_whole_sequence():
    """The simulated controller: TRIG_OUT_1 rises per pattern only after a dark time (DLPU018)."""
    for dark, edges in ((0, [0]), (100, list(range(4)) * 2)):
        sim = SimulatedDLPC900(DMD)
        dev = DLPC900(sim, dmd=DMD)
        dev.upload_sequence(np.zeros((1, 48, 160), np.uint32),
                            [LutEntry(j, 1000, 0, j, wait_for_trigger=False, dark_us=dark) for j in range(4)])
        dev.start()
        seen, t = [], 0.0
        while (edge := sim.next_trigger_out1(t)) is not None and len(seen) < 8:
            t, j = edge
            seen.append(j)
            t += 1  # the next edge after this one
        assert seen == edges


def test_hardware_trigger_capture_gets_one_frame_per_pattern():
    k = 6
    sim, light, camera, want = bench(k, mode="hardware-trigger")
    assert all(sim.lut[j]["dark_us"] == 100 for j in range(k))  # the light's default dark time, 100 us
    result = capture_sequences(camera, k)
    assert_all_sequences_match(result, want, 3)
    assert result.assembly.dropped == 0 and result.end.last_frame_id == 3 * k - 1


def test_hardware_trigger_refuses_zero_dark_time():
    sim = SimulatedDLPC900(DMD)
    with pytest.raises(ValueError, match="dark_s must be at least 1 us when the controller triggers the camera"):
        DLPC900Light(DLPC900(sim, dmd=DMD), layout=DMDLayout(DMD, COLUMNS, ROWS), wait_for_trigger=False, dark_s=0)
    from specgpu.hardware.rig import HardwareConfig

    with pytest.raises(ValueError, match="hardware.dark_time_s must be at least 1e-6 s in hardware-trigger mode"):
        HardwareConfig(camera_mode="hardware-trigger", dark_time_s=0.0)


def test_light_started_before_the_armed_camera_runs_patterns_nobody_sees():
    """The bench: a light started first free-runs while the camera arms, so its first frame is not pattern 0."""
    k = 6
    sim, light, camera, want = bench(k, mode="hardware-trigger")
    camera.configure()
    light.start()  # the wrong order, by hand
    camera.acquirer.start()
    camera.acquirer.fetch()
    assert camera.acquirer.positions[0] != 0


@pytest.mark.parametrize("mode, first", [("hardware-trigger", "camera"), ("strobe-master", "light")])
def test_start_order_starts_the_waiting_device_first(mode, first):
    k = 6
    sim, light, camera, want = bench(k, mode=mode)
    order = []
    real_light, real_cam = light.start, camera.acquirer.start
    light.start = lambda: (order.append("light"), real_light())[1]
    camera.acquirer.start = lambda: (order.append("camera"), real_cam())[1]
    result = capture_sequences(camera, k)
    assert order[0] == first and sorted(order) == ["camera", "light"]
    assert camera.acquirer.positions[:k] == list(range(k))  # frame n lit by pattern n
    assert_all_sequences_match(result, want, 3)


@pytest.mark.parametrize("mode", ["strobe-master", "hardware-trigger"])
def test_a_camera_that_fails_to_start_leaves_the_light_stopped(mode):
    sim, light, camera, want = bench(6, mode=mode)

    def broken():
        raise RuntimeError("AcquisitionStart refused")

    camera.acquirer.start = broken
    with pytest.raises(RuntimeError, match="AcquisitionStart"):
        camera.start()
    assert not sim.running  # in strobe-master mode the light had started first: it is stopped again


def test_camera_started_before_a_triggered_light_loses_its_first_strobe():
    """The bench, strobe-master: a strobe before the light's Start is lost (frame dark, labels shifted)."""
    sim, light, camera, want = bench(4)
    camera.configure()
    camera.acquirer.start()
    light.start()
    camera.acquirer.fetch()
    assert camera.acquirer.positions[0] == -1


# ---- strobe line set-up on read-only line modes ---------------------------------------------------------
def test_strobe_line_already_output_is_not_written():
    sim, light, camera, want = bench(4)  # Line1: opto-isolated output, LineMode read-only
    camera.configure()
    nm = camera.acquirer.remote_device.node_map
    assert ("Line1", "LineMode", "Output") not in nm.line_writes
    assert nm.LineSelector.value == "Line1" and nm.LineSource.value == "ExposureActive"
    assert_all_sequences_match(capture_sequences(camera, 4), want, 3)


def test_strobe_on_an_input_line_names_the_line_to_use():
    sim, light, camera, want = bench(4, camera_kw={"strobe_line": "Line0"})
    with pytest.raises(HardwareError) as err:
        camera.configure()
    msg = str(err.value)
    assert msg.startswith("camera line Line0 is an input and cannot be made the strobe output")
    assert "set strobe_line (hardware.camera_strobe_line) to Line1" in msg and "Line2, Line3" in msg
    assert "\n" not in msg


def test_strobe_on_a_writable_gpio_line_is_made_an_output():
    sim, light, camera, want = bench(4, camera_kw={"strobe_line": "Line2"})
    camera.configure()
    nm = camera.acquirer.remote_device.node_map
    assert ("Line2", "LineMode", "Output") in nm.line_writes and nm.lines["Line2"]["LineSource"] == "ExposureActive"


def test_camera_without_output_lines_says_so():
    nm = NodeMap(4, 16, lines={"Line0": ("Input", False)})
    sim, light, camera, want = bench(4, camera_kw={"strobe_line": "Line0"})
    camera.acquirer.remote_device.node_map = nm
    with pytest.raises(HardwareError, match="the camera offers no output line$"):
        camera.configure()


# ---- buffers without a device timestamp -----------------------------------------------------------------
def test_missing_timestamps_fall_back_to_the_host_clock():
    sim, light, camera, want = bench(4, timestamps=False, lines=GPIO)
    result = capture_sequences(camera, 4)
    assert_all_sequences_match(result, want, 3)
    ts = np.concatenate([s.timestamps_s for s in result.sequences])
    assert ts[0] == 0.0 and np.all(np.diff(ts) >= 0)
    assert camera.describe()["timestamps"] == "host"
    sim, light, camera, want = bench(4)
    capture_sequences(camera, 4)
    assert camera.describe()["timestamps"] == "device"


# ---- 16-bit GigE Vision block ids -----------------------------------------------------------------------
def test_gev_block_ids_wrap_to_one():
    assert [gev_block_id(65533, n, 16) for n in range(5)] == [65533, 65534, 65535, 1, 2]


def test_capture_runs_through_the_block_id_wrap_with_a_loss_across_it():
    k = 5
    # ids 65526 .. 65535, 1, ...: exposures 9 (id 65535) and 10 (id 1) lost on the link
    sim, light, camera, want = bench(k, exposures=6 * k, first_id=65526, id_bits=16, lost={9, 10},
                                     lines=GPIO)
    result = capture_sequences(camera, k)
    assert [s.cycle for s in result.sequences] == [0, 3, 4, 5]
    assert result.assembly.dropped == 2 and result.assembly.sequences_discarded == 2
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames, want)
    assert result.end.last_frame_id == 6 * k - 1


# ---- clear after exposure -------------------------------------------------------------------------------
def test_light_clears_each_pattern_after_its_exposure():
    sim, light, camera, want = bench(4)
    assert all(sim.lut[j]["options"] & 1 for j in range(4))
    assert LutEntry(0, 200).fields()["options"] & 1  # the LUT entry's default too


def test_without_clear_the_previous_pattern_leaks_into_each_exposure():
    """The bench: a pattern left up lights the next exposure during the Trigger In 1 delay."""
    sim = SimulatedDLPC900(DMD)
    dev = DLPC900(sim, dmd=DMD)
    img = np.zeros((1, 48, 160), np.uint32)
    img[0, :, :80] = 1  # bit 0: left half; bit 1: nothing
    for clear, leak in ((True, 0.0), (False, 105 / 1000)):
        dev.upload_sequence(img, [LutEntry(j, 1000, 0, j, clear_after_exposure=clear) for j in range(2)])
        dev.start()
        sim.trigger_in()
        sim.trigger_in()  # entry 1 (dark) after entry 0 (left half on)
        light = sim.exposure_light(1000.0)
        assert light[:, :80] == pytest.approx(leak) and not light[:, 80:].any()
        dev.stop()


# ---- controller and spectrometer quirks -----------------------------------------------------------------
def test_rejection_is_reported_when_the_error_description_times_out():
    sim = SimulatedDLPC900(DMD)
    dev = DLPC900(sim, dmd=DMD)
    sim.no_reply_to = {"Read Error Description"}
    with pytest.raises(CommandRejected, match=r"Pattern Display LUT Definition \(0x1A34\): error 14 \(pattern "
                                              r"exposure time is out of range\)$") as err:
        dev.define_pattern(LutEntry(0, 50))
    assert (err.value.code, err.value.description) == (14, "")
    sim.no_reply_to = {"Read Error Code", "Read Error Description"}
    with pytest.raises(CommandRejected, match=r"error -1 \(error status unreadable\)"):
        dev.define_pattern(LutEntry(0, 50))


def test_power_mode_reset_expects_no_reply():
    sim = SimulatedDLPC900(DMD)
    dev = DLPC900(sim, dmd=DMD)
    dev.upload_sequence(np.zeros((1, 48, 160), np.uint32), [LutEntry(0, 1000)])
    assert sim.lut_entries == 1
    dev.set_power_mode("reset")  # the rebooting controller answers nothing: no timeout
    assert sim.lut_entries == 0 and sim.log[-1][0] == "out"
    assert dev.display_mode() == "video"  # the link still works after the reset's silence


def test_trigger_in1_delay_at_least_104_us():
    sim = SimulatedDLPC900(DMD)
    dev = DLPC900(sim, dmd=DMD)
    with pytest.raises(ValueError, match=r"trigger in 1 delay must lie in \[104, 65535\] us"):
        dev.set_trigger_in1(103)
    dev.set_trigger_in1(104)
    assert sim.trigger_in1_delay == 104
    with pytest.raises(CommandRejected, match="error 13"):  # the controller refuses it too
        dev.protocol.write("Trigger In 1", delay_us=50, byte2=0)


class PartialSeabreeze:
    """A seabreeze-like device supporting dark correction only (non-linearity raises, as SeaBreezeError)."""

    def __init__(self):
        self.pixels = np.linspace(400.0, 700.0, 64)
        self.calls = []

    def wavelengths(self):
        return self.pixels

    def integration_time_micros(self, us):
        pass

    def intensities(self, correct_dark_counts=False, correct_nonlinearity=False):
        self.calls.append((correct_dark_counts, correct_nonlinearity))
        if correct_nonlinearity:
            raise RuntimeError("This device does not support non-linearity correction")
        return np.full(64, 1000.0) - (900.0 if correct_dark_counts else 0.0)

    def close(self):
        pass


def test_seabreeze_keeps_the_correction_it_supports():
    from specgpu.hardware.ocean import OceanSpectrometer

    dev = PartialSeabreeze()
    spec = OceanSpectrometer(dev, averages=2)
    np.testing.assert_allclose(spec.read_counts(), 100.0)  # dark corrected, not raw
    assert spec.corrections == (True, False)
    assert dev.calls == [(True, True), (True, False), (True, False)]  # found once, then kept


def test_lightcrafter_9000_needs_its_secondary_controller():
    assert HardwareStatus(0x11).secondary_present and not HardwareStatus(0x01).secondary_present
    sim = SimulatedDLPC900("lightcrafter-9000", secondary_present=False)
    light = DLPC900Light(DLPC900(sim, dmd="lightcrafter-9000"))
    with pytest.raises(HardwareError, match=r"^DLPC900 hardware status 0x01: secondary controller not present "
                                            r"\(a lightcrafter-9000 needs both controllers"):
        light.load_sequence(np.zeros((2, light.layout.columns), np.int32))
    assert not light.loaded and sim.lut_entries == 0  # nothing sent after the status read
    sim6500 = SimulatedDLPC900("lightcrafter-6500", secondary_present=False)
    DLPC900(sim6500).check_hardware()  # one controller: bit 4 not needed


def test_windows_hint_names_the_libusb_driver(monkeypatch):
    from specgpu.hardware.dlpc900 import transport

    assert "WinUSB" in transport.no_backend_message() and "Zadig" in transport.no_backend_message()
    monkeypatch.setattr(sys, "platform", "win32")
    monkeypatch.setattr(transport, "import_pyusb", lambda: (FakeCore, None))
    with pytest.raises(Exception, match=r"not found: is the controller connected and powered\? On Windows, "
                                        r"replace the controller's HID driver by WinUSB"):
        transport.UsbTransport().open()


class FakeCore:
    class NoBackendError(Exception):
        pass

    class USBError(Exception):
        pass

    @staticmethod
    def find(**kw):
        return None


def test_timeout_and_fault_accounting_unchanged_on_the_bench():
    """A camera that stops being triggered still times out with the one-line error."""
    sim, light, camera, want = bench(3, mode="hardware-trigger", exposures=9)
    camera.acquirer.exposures = 4
    with pytest.raises(DeviceTimeout, match=r"camera delivered no frame in 2 s: is it triggered \(hardware-trigger\)"):
        capture_sequences(camera, 3)


# ---- a long capture through the id wrap (tools/maintenance/hw_long_capture.py) ---------------------------------
def _long_capture():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "tools" / "maintenance" / "hw_long_capture.py"
    spec = importlib.util.spec_from_file_location("hw_long_capture", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.long_capture


@pytest.mark.parametrize("mode", ["strobe-master", "hardware-trigger"])
def test_capture_across_the_wrap_every_sequence_matches(mode):
    r = _long_capture()(3000, 30, first_id=64000, mode=mode)  # ids 64000 .. 65535, 1 .. 1464
    assert r["id_wraps"] == 1 and r["sequences"] == 100 and r["mismatched"] == [] and r["dropped"] == 0
    assert r["last_frame_id"] == 2999


@pytest.mark.slow
def test_capture_of_100000_frames_every_sequence_matches():
    r = _long_capture()(100_000, 30)  # ids 1 .. 65535, 1 .. 34465
    assert r["id_wraps"] == 1 and r["sequences"] == 3333 and r["mismatched"] == [] and r["dropped"] == 0
    assert r["discarded"] == 1 and r["last_frame_id"] == 99_999  # the last 10 frames: an incomplete sequence


# ---- property: block id unwrapping ------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(first=st.integers(1, 65535), steps=st.lists(st.integers(1, 30000), min_size=1, max_size=40))
def test_unwrapped_ids_count_every_exposure(first, steps):
    """Whatever the start and the gaps (frames lost on the link, fewer than half the id range at a time), the
    unwrapped 16-bit ids advance by the true number of exposures."""
    camera = GenICamCamera.__new__(GenICamCamera)
    camera._raw_last, camera._wraps = None, 0
    n = np.concatenate(([0], np.cumsum(steps)))
    got = np.array([camera._unwrap(gev_block_id(first, int(k), 16)) for k in n])
    np.testing.assert_array_equal(got - got[0], n)
