"""The hardware capture path in CI: simulated DLPC900 (report level) + a GenICam-like camera + ring buffer + assembler.

The fake camera is wired to the simulated controller as on the rig (strobe-master: each exposure's strobe is a
TRIG_IN_1 edge), and each frame is rendered from the mirrors the controller is really displaying, decoded from the
uploaded images. So a frame whose label disagrees with the light that lit it is caught by comparing it with the
frame the labelled pattern gives.
"""

from __future__ import annotations

import numpy as np
import pytest
from hw_fakes import Buffer, FakeCamera

from specgpu.capture import SequenceAssembler, capture_sequences, open_driver
from specgpu.hardware.dlpc900 import DLPC900, DLPC900Light, DMDGeometry, DMDLayout, SimulatedDLPC900
from specgpu.hardware.errors import DeviceDisconnected, DeviceNotFound, DeviceTimeout, HardwareError, LightFault
from specgpu.hardware.genicam import GenICamCamera

DMD = DMDGeometry("test-dmd", 160, 48)
COLUMNS, ROWS = 16, 40


def FakeAcquirer(sim, layout, exposures, **kw):
    """The bench camera (:class:`hw_fakes.FakeCamera`) rendering through ``layout``."""
    return FakeCamera(sim, lambda light: render(layout, light), exposures, shape=(4, COLUMNS), **kw)


def render(layout, light) -> np.ndarray:
    """A (4, COLUMNS) uint16 frame: per pattern column, the light of its mirrors (plus a row offset so rows
    differ); ``light`` is a bool mask or the float light an exposure integrated."""
    c0 = layout.column_offset
    counts = np.asarray(light, np.float64)[:, c0:c0 + layout.columns * layout.column_step].sum(axis=0)
    counts = counts.reshape(layout.columns, layout.column_step).sum(axis=1)
    return np.rint(counts[None, :] * 10 + np.arange(4)[:, None] + 1).astype(np.uint16)


def rig(k=5, exposures=None, mode="strobe-master", dark_s=100e-6, **acq):
    sim = SimulatedDLPC900(DMD)
    layout = DMDLayout(DMD, COLUMNS, ROWS)
    light = DLPC900Light(DLPC900(sim, dmd=DMD), layout=layout, exposure_s=0.001,
                         wait_for_trigger=mode == "strobe-master", dark_s=dark_s)
    patterns = np.random.default_rng(k).integers(0, ROWS + 1, (k, COLUMNS))
    patterns[0] = 0  # a dark pattern, as a real sequence often has
    light.load_sequence(patterns)
    acquirer = FakeAcquirer(sim, layout, exposures if exposures is not None else 4 * k, **acq)
    camera = GenICamCamera(light, acquirer=acquirer, mode=mode, exposure_s=0.001, n_frames=exposures)
    return sim, light, camera, patterns


def expected_frames(light, patterns):
    return np.stack([render(light.layout, light.layout.pattern_to_mask(p)) for p in patterns])


def test_capture_path_complete_sequences_match_their_patterns():
    k = 30  # two 24-bit images: patterns 24..29 come from the second
    sim, light, camera, patterns = rig(k, exposures=3 * k + 4)
    result = capture_sequences(camera, k)
    want = expected_frames(light, patterns)
    assert len(result.sequences) == 3 and result.assembly.dropped == 0 and result.assembly.missed_triggers == 0
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames, want)
        np.testing.assert_array_equal(seq.frame_ids % k, np.arange(k))
    assert result.end.last_frame_id == 3 * k + 3
    assert camera.acquirer.remote_device.node_map.LineSource.value == "ExposureActive"  # strobe-master wiring
    assert camera.acquirer.remote_device.node_map.ExposureTime.value == pytest.approx(1000.0)
    assert not sim.running  # stop() stopped the controller's sequence


def test_hardware_trigger_mode_controller_is_master():
    k = 6
    sim, light, camera, patterns = rig(k, exposures=2 * k, mode="hardware-trigger")
    assert all(sim.lut[j]["options"] >> 7 == 0 for j in range(k))  # no entry waits for a trigger
    # TRIG_OUT_1 configured after the upload: non-inverted, no delays
    assert sim.commands[-1] == ("Trigger Out 1", {"invert": 0, "rising_delay_us": 0, "falling_delay_us": 0})
    result = capture_sequences(camera, k)
    assert len(result.sequences) == 2
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames, expected_frames(light, patterns))
    nm = camera.acquirer.remote_device.node_map
    assert (nm.TriggerMode.value, nm.TriggerSource.value) == ("On", "Line0")


def test_lost_frame_leaves_a_gap_and_no_frame_slides():
    k = 5
    sim, light, camera, patterns = rig(k, exposures=4 * k, lost={7, 12})
    result = capture_sequences(camera, k)
    want = expected_frames(light, patterns)
    assert [s.cycle for s in result.sequences] == [0, 3]  # cycles 1 and 2 each lost a frame
    assert result.assembly.dropped == 2 and result.assembly.sequences_discarded == 2
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames, want)


def test_lost_first_frame_with_known_first_id_shifts_nothing():
    k = 4
    sim, light, camera, patterns = rig(k, exposures=3 * k, lost={0})
    camera.first_frame_id = 1  # GigE Vision: block ids start at 1 (the fake camera's first_id)
    result = capture_sequences(camera, k)
    assert [s.cycle for s in result.sequences] == [1, 2] and result.assembly.sequences_discarded == 1
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames, expected_frames(light, patterns))
    # Without it, the first delivered frame is taken as exposure 0 and every label would shift by one:
    sim, light, camera, patterns = rig(k, exposures=3 * k, lost={0})
    camera.n_frames = 3 * k - 1  # the last exposure is numbered 3k - 2 now
    result = capture_sequences(camera, k)
    want = expected_frames(light, patterns)
    assert len(result.sequences) == 2
    assert not any(np.array_equal(seq.frames, want) for seq in result.sequences)  # the guard matters


def test_open_driver_selects_the_hardware_backend():
    sim = SimulatedDLPC900("lightcrafter-6500")
    patterns = np.zeros((2, 1024), np.int32)
    patterns[1, 100:200] = 768
    driver = open_driver("vision-dlpc900", hardware={"light": "dlpc900-simulated", "exposure_s": 0.002,
                                                     "camera_first_frame_id": 1},
                         patterns=patterns, n_frames=4, transport=sim,
                         acquirer=FakeAcquirer(sim, None, 0))
    assert isinstance(driver, GenICamCamera) and driver.light.loaded and driver.first_frame_id == 1
    assert sim.lut_entries == 2 and sim.lut[0]["exposure_us"] == 2000
    layout = driver.light.layout
    np.testing.assert_array_equal(layout.images_to_patterns(sim.image(0)[None], 2), patterns)


# ---- USB faults ------------------------------------------------------------------------------------------------
def test_device_absent_is_a_clear_error():
    with pytest.raises(DeviceNotFound, match=r"^DLPC900 \(USB 0451:c900\) not found: is the controller connected"):
        DLPC900(SimulatedDLPC900(absent=True))


@pytest.mark.parametrize("mode, error", [("timeout", DeviceTimeout), ("disconnect", DeviceDisconnected)])
def test_fault_during_upload_leaves_no_sequence_loaded(mode, error):
    sim, light, camera, patterns = rig(3)
    sent = lambda: sum(1 for d, _ in sim.log if d == "out")  # noqa: E731
    before = sent()
    light.load_sequence(patterns)
    per_upload = sent() - before
    sim.fail_after, sim.fail_mode = sent() + per_upload - 2, mode  # fails inside the last image block
    with pytest.raises(error, match="DLPC900 \\(USB 0451:c900\\)"):
        light.load_sequence(patterns[::-1])
    assert not light.loaded
    with pytest.raises(RuntimeError, match="no sequence loaded"):
        camera.start()
    assert not camera.running


def test_recover_after_disconnect_reloads_the_sequence():
    sim, light, camera, patterns = rig(3)
    sim.fail_after = sum(1 for d, _ in sim.log if d == "out") + 5
    with pytest.raises(DeviceDisconnected):
        light.load_sequence(patterns[::-1])
    assert not light.loaded
    sim.fail_after = None
    sim.reset()  # the controller came back from a reset: nothing of the sequence is left in it
    light.recover(attempts=1)
    assert light.loaded and sim.lut_entries == 3
    imgs = sim.image(0)[None]
    np.testing.assert_array_equal(light.layout.images_to_patterns(imgs, 3), patterns[::-1])


def _drive(camera, k):
    """The capture loop with the assembler in hand, so its accounting after a fault can be checked."""
    asm = SequenceAssembler(k)
    out = np.empty(camera.frame_shape, camera.dtype)
    sequences, error = [], None
    camera.start()
    try:
        while (info := camera.fill(out)) is not None:
            if (seq := asm.push(out, info)) is not None:
                sequences.append(seq)
    except HardwareError as exc:
        error = exc
    return sequences, asm.finish(camera.stop()), error


@pytest.mark.parametrize("fault", ["disconnect", "controller-reset"])
def test_fault_mid_sequence_marks_it_incomplete_and_mislabels_nothing(fault):
    k = 4
    sim, light, camera, patterns = rig(k, exposures=5 * k)

    def on_exposure(n):
        if n == 2 * k + 1:  # during the third cycle
            if fault == "disconnect":
                sim.fail_after = len([d for d, _ in sim.log if d == "out"])
            else:
                sim.stop_after_triggers = sim.triggers

    camera.acquirer.on_exposure = on_exposure
    sequences, stats, error = _drive(camera, k)
    expected_error = DeviceDisconnected if fault == "disconnect" else LightFault
    assert isinstance(error, expected_error)
    assert str(error).startswith("DLPC900")
    assert len(sequences) == 2 and stats.sequences_complete == 2
    assert stats.sequences_discarded == 1  # the third cycle: one frame in, never completed
    assert stats.frames_received == 2 * k + 1  # the frame exposed at the fault was not delivered
    want = expected_frames(light, patterns)
    for seq in sequences:
        np.testing.assert_array_equal(seq.frames, want)


def test_fault_mid_capture_raises_through_capture_sequences():
    k = 4
    sim, light, camera, patterns = rig(k, exposures=5 * k)
    camera.acquirer.on_exposure = lambda n: setattr(sim, "stop_after_triggers", sim.triggers) if n == 6 else None
    got = []
    with pytest.raises(LightFault, match="sequencer stopped"):
        capture_sequences(camera, k, on_sequence=got.append)
    assert len(got) == 1
    np.testing.assert_array_equal(got[0].frames, expected_frames(light, patterns))


def test_camera_that_stops_delivering_times_out_clearly():
    k = 3
    sim, light, camera, patterns = rig(k, exposures=10)
    camera.acquirer.exposures = 5  # the camera stops being triggered after 5 of the 10 exposures asked for
    with pytest.raises(DeviceTimeout, match=r"camera delivered no frame in 2 s: is it triggered \(strobe-master\)"):
        capture_sequences(camera, k)


def test_frame_id_from_the_gentl_buffer_when_harvesters_does_not_expose_it():
    from specgpu.hardware.genicam import _frame_id

    class Old:
        _buffer = type("GenTLBuffer", (), {"frame_id": 42})()

    assert _frame_id(Buffer(np.zeros(1), 7, 0)) == 7 and _frame_id(Old()) == 42
    with pytest.raises(HardwareError, match="no frame id"):
        _frame_id(object())
