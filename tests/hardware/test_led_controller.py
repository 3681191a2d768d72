"""The LED controller's serial protocol against the simulated board: framing, commands, the light behind the capture
interfaces, and its faults (a board that does not answer, a checksum error either way, a wrong firmware, a missed or
lost trigger), each a one-line error naming the port with nothing recorded lost."""

from __future__ import annotations

import numpy as np
import pytest
from hw_fakes import Buffer, NodeMap

from specgpu.capture import capture_sequences
from specgpu.hardware.errors import (
    CommandRejected,
    DeviceNotFound,
    DeviceTimeout,
    HardwareError,
    LightFault,
    ProtocolError,
)
from specgpu.hardware.genicam import GenICamCamera
from specgpu.hardware.led import LedController, LedLight, SimulatedLedBoard, SimulatedSerial, serve
from specgpu.hardware.led.protocol import crc8, frame, unframe

CHANNELS = 5


def controller(board=None, **kw):
    return LedController(SimulatedSerial(board or SimulatedLedBoard(**kw)))


def patterns(k=4, seed=0):
    p = np.random.default_rng(seed).uniform(0.05, 1, (k, CHANNELS))
    p[0] = 0  # the all-off dark frame
    return p


class LedCamera:
    """A free-running camera whose exposure-active output is wired to the board's trigger input: exposure ``n``
    sends edge ``n`` at ``n * period_us`` and integrates the duties the board shows after it."""

    def __init__(self, board, exposures, period_us=10_000.0, on_exposure=None):
        self.board, self.exposures, self.period_us, self.on_exposure = board, exposures, period_us, on_exposure
        self.remote_device = type("Remote", (), {"node_map": NodeMap(3, CHANNELS)})()
        self.n, self.started = 0, False

    def start(self):
        self.started, self.n = True, 0

    def stop(self):
        self.started = False

    def fetch(self, timeout=None):
        if not self.started or self.n >= self.exposures:
            raise TimeoutError("no buffer")
        n, self.n = self.n, self.n + 1
        if self.on_exposure is not None:
            self.on_exposure(n)
        self.board.trigger(at_us=n * self.period_us)
        return Buffer(render(self.board.duty()), n, int(n * self.period_us * 1000))


def render(duty) -> np.ndarray:
    return np.rint(np.asarray(duty)[None, :] * 4000 + np.arange(3)[:, None] + 1).astype(np.uint16)


def led_rig(k=4, exposures=None, **board_kw):
    board = SimulatedLedBoard(**board_kw)
    light = LedLight(LedController(SimulatedSerial(board)), channels=CHANNELS)
    p = patterns(k)
    light.load_sequence(p)
    camera = GenICamCamera(light, acquirer=LedCamera(board, exposures or 3 * k), exposure_s=0.005,
                           n_frames=exposures, first_frame_id=0)
    return board, light, camera, p


# ---- framing ------------------------------------------------------------------------------------------------------
def test_crc8_and_framing_round_trip():
    assert crc8(b"123456789") == 0xF4  # the CRC-8/SMBUS check value
    line = frame("STEP", 3, 4095, 0)
    assert line == b"STEP 3 4095 0*%02X\n" % crc8(b"STEP 3 4095 0")
    assert unframe(line) == ["STEP", "3", "4095", "0"]
    with pytest.raises(ProtocolError, match="checksum mismatch"):
        unframe(line.replace(b"4095", b"4094"))
    with pytest.raises(ProtocolError, match="without a checksum"):
        unframe(b"OK 3\n")


def test_identify_upload_arm_and_step_with_the_dark_frame():
    board = SimulatedLedBoard()
    ctl = controller(board)
    ident = ctl.identity
    assert (ident.protocol, ident.firmware, ident.max_channels, ident.pwm_bits) == (1, "1.0.0", 13, 12)
    light = LedLight(ctl, channels=CHANNELS)
    p = patterns(3)
    light.load_sequence(p)
    assert board.received[-5:] == ["SEQ", "DARK", "STEP", "STEP", "END"]  # row 0 is sent as the dark frame
    np.testing.assert_allclose(light.sequence, p, atol=0.5 / 4095)
    light.start()
    assert board.armed and not board.duty().any()  # outputs off until the first edge
    shown = []
    for n in range(7):
        assert board.trigger(at_us=1000.0 * n) == n % 3
        shown.append(board.duty().copy())
    np.testing.assert_allclose(shown[3], light.sequence[0])
    np.testing.assert_allclose(shown[4], light.sequence[1])
    assert not shown[0].any() and board.table[0] is None
    status = ctl.status()
    assert (status.armed, status.pulses, status.steps, status.missed, status.step) == (True, 7, 7, 0, 0)
    light.stop()
    assert light.counts == (7, 7, 0) and not board.duty().any()


def test_capture_through_the_light_gives_complete_sequences_that_match_their_patterns():
    k = 4
    board, light, camera, p = led_rig(k, exposures=3 * k)
    result = capture_sequences(camera, k)
    assert len(result.sequences) == 3 and result.assembly.dropped == 0
    want = np.stack([render(d) for d in light.sequence])
    for seq in result.sequences:
        np.testing.assert_array_equal(seq.frames, want)
    assert not board.armed  # the capture's stop disarmed the board


# ---- faults -------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fault", ["missed", "lost"])
def test_dropped_trigger_refuses_the_affected_sequence_and_keeps_the_earlier_ones(fault):
    k = 4
    board, light, camera, p = led_rig(k, exposures=5 * k)
    at = 2 * k + 1  # in the third cycle
    if fault == "missed":
        board.drop_pulses.add(at)  # the board saw the edge inside its hold-off and did not step
    else:
        board.lose_pulses.add(at)  # the edge never reached the board
    got = []
    match = (rf"^LED controller on sim://led missed trigger pulse {at} \(1 of {at + 1} pulses" if fault == "missed"
             else rf"^LED controller on sim://led saw {at} trigger pulses for {at + 1} camera exposures")
    with pytest.raises(LightFault, match=match) as err:
        capture_sequences(camera, k, on_sequence=got.append)
    assert "\n" not in str(err.value)
    assert len(got) == 2  # the two cycles before the fault, each complete and correct
    want = np.stack([render(d) for d in light.sequence])
    for seq in got:
        np.testing.assert_array_equal(seq.frames, want)


def test_a_missed_trigger_after_the_frame_in_hand_does_not_refuse_it():
    board = SimulatedLedBoard()
    light = LedLight(controller(board), channels=CHANNELS)
    light.load_sequence(patterns(4))
    light.start()
    board.drop_pulses.add(3)
    for n in range(5):
        board.trigger(at_us=1000.0 * n)
    light.at_frame(2)
    light.check()  # exposure 2 was lit by step 2: fine
    light.at_frame(3)
    with pytest.raises(LightFault, match="missed trigger pulse 3"):
        light.check()


def test_an_edge_inside_the_hold_off_is_counted_as_missed():
    board = SimulatedLedBoard()
    light = LedLight(controller(board), channels=CHANNELS, holdoff_us=500)
    light.load_sequence(patterns(2))
    light.start()
    assert [board.trigger(at_us=t) for t in (0.0, 200.0, 1000.0)] == [0, 0, 1]
    s = light.controller.status()
    assert (s.pulses, s.steps, s.missed, s.first_missed) == (3, 2, 1, 1)


def test_board_that_does_not_answer_times_out_naming_the_port():
    board = SimulatedLedBoard()
    board.mute = True
    with pytest.raises(DeviceTimeout, match=r"^LED controller on sim://led did not answer ID within 1 s: is the "
                                            r"board connected"):
        controller(board)
    board = SimulatedLedBoard()
    light = LedLight(controller(board), channels=CHANNELS)
    light.load_sequence(patterns(3))
    board.mute = True  # goes quiet during the next upload
    with pytest.raises(DeviceTimeout, match="did not answer SEQ"):
        light.load_sequence(patterns(3, seed=1))
    assert light.requested.shape == (3, CHANNELS)
    with pytest.raises(RuntimeError, match="no sequence loaded"):
        light.start()  # half an upload is never run


def test_checksum_errors_in_either_direction():
    board = SimulatedLedBoard()
    ctl = controller(board)
    board.corrupt_replies = 1
    with pytest.raises(ProtocolError, match=r"^LED controller on sim://led: reply to STAT: checksum mismatch"):
        ctl.status()
    assert ctl.status().pulses == 0  # the next exchange is clean

    class Noisy(SimulatedSerial):
        def write(self, data):
            return super().write(data.replace(b"STAT", b"STAU"))  # a bit flipped on the line

    noisy = LedController(Noisy(SimulatedLedBoard()))
    with pytest.raises(CommandRejected, match=r"^LED controller on sim://led refused STAT: error 1 \(checksum "
                                              r"mismatch\)") as err:
        noisy.status()
    assert err.value.code == 1


def test_wrong_firmware_and_not_a_specgpu_board():
    with pytest.raises(HardwareError, match=r"^LED controller on sim://led runs firmware 2.1.0 speaking protocol 2; "
                                            r"this driver speaks protocol 1: flash tools/firmware/led_controller/"):
        controller(protocol=2, firmware="2.1.0")

    class Other(SimulatedSerial):
        def readline(self):
            line = super().readline()
            return frame("OK", "BLINKY", *unframe(line)[2:]) if line else line

    with pytest.raises(ProtocolError, match="does not identify a specgpu LED controller"):
        LedController(Other(SimulatedLedBoard()))


def test_refused_commands_and_bad_patterns_are_one_line():
    board = SimulatedLedBoard()
    ctl = controller(board)
    with pytest.raises(CommandRejected, match=r"refused ARM: error 5 \(upload a sequence first\)"):
        ctl.arm()
    with pytest.raises(CommandRejected, match=r"refused STEP: error 3 \(duty out of range 0 to 4095\)"):
        ctl.upload(np.array([[5000] * 13]))
    light = LedLight(ctl, channels=CHANNELS)
    with pytest.raises(ValueError, match=r"patterns must be \(K, 5\) duty fractions"):
        light.load_sequence(np.ones((2, 4)))
    with pytest.raises(ValueError, match=r"fractions in \[0, 1\]"):
        light.load_sequence(np.full((2, CHANNELS), 1.5))


def test_emitted_spectrum_is_the_duties_times_the_channel_spectra():
    wl = np.arange(400.0, 701.0, 100.0)
    spectra = np.eye(CHANNELS, wl.size) + 0.1
    light = LedLight(controller(), channels=CHANNELS, wavelengths=wl, spectra=spectra)
    p = patterns(2)
    light.load_sequence(p)
    np.testing.assert_allclose(light.emitted_spectrum(1), light.sequence[1] @ spectra)
    assert not light.emitted_spectrum(0).any()
    bare = LedLight(controller(), channels=CHANNELS)
    bare.load_sequence(p)
    with pytest.raises(HardwareError, match=r"no channel spectra given \(hardware.light_spectra\)"):
        bare.emitted_spectrum(1)


# ---- through pyserial ---------------------------------------------------------------------------------------------
def test_through_pyserial_over_a_socket_and_a_silent_one():
    pytest.importorskip("serial")
    board = SimulatedLedBoard()
    url, stop = serve(board)
    try:
        ctl = LedController(url)
        light = LedLight(ctl, channels=CHANNELS)
        light.load_sequence(patterns(3))
        light.start()
        board.trigger(at_us=0.0)
        light.at_frame(0)
        light.check()
        assert ctl.status().steps == 1
        light.close()
        board.mute = True
        with pytest.raises(DeviceTimeout, match=rf"^LED controller on {url} did not answer ID within 0.2 s"):
            LedController(url, timeout_s=0.2)
    finally:
        stop()


def test_pyserial_loop_echo_and_a_missing_port():
    pytest.importorskip("serial")
    with pytest.raises(ProtocolError, match=r"^LED controller on loop://: reply to ID is neither OK nor ERR"):
        LedController("loop://")  # a port that only echoes the host's own line
    with pytest.raises(DeviceNotFound, match=r"^LED controller port /dev/specgpu-no-such-tty cannot be opened"):
        LedController("/dev/specgpu-no-such-tty")


# ---- chosen by the rig's [hardware] table ---------------------------------------------------------------------------
def test_rig_table_opens_the_led_light_behind_the_camera(tmp_path):
    from types import SimpleNamespace

    from specgpu.hardware.drivers import hardware_config
    from specgpu.hardware.rig import open_hardware

    wl = np.arange(400.0, 701.0, 10.0)
    spectra = np.exp(-0.5 * ((wl[None, :] - np.linspace(420, 680, CHANNELS)[:, None]) / 15) ** 2)
    (tmp_path / "leds.csv").write_text("# wavelength, channels\n" + "\n".join(
        ",".join(f"{v:.12g}" for v in (w, *col)) for w, col in zip(wl, spectra.T)))
    rig = SimpleNamespace(hardware={"light_port": "/dev/ttyACM0", "light_spectra": "leds.csv"}, source="rig.toml",
                          base_dir=str(tmp_path), light=SimpleNamespace(kind="led"))
    cfg = hardware_config(rig)  # [light] kind = "led" picks the LED board when [hardware] names no light
    assert (cfg.light, cfg.light_spectra) == ("led", str(tmp_path / "leds.csv"))
    board = SimulatedLedBoard()
    k = 3
    camera = open_hardware(hardware=cfg, patterns=patterns(k), transport=SimulatedSerial(board),
                           acquirer=LedCamera(board, 2 * k), n_frames=2 * k, exposure_s=0.005)
    light = camera.light
    assert isinstance(light, LedLight) and light.channels == CHANNELS  # as many as the spectra file has
    np.testing.assert_allclose(light.emitted_spectrum(2), light.sequence[2] @ spectra, rtol=1e-6)
    assert len(capture_sequences(camera, k).sequences) == 2
    rig.hardware = {"light": "dlpc900"}
    with pytest.raises(ValueError, match=r"^rig.toml: light.kind = 'led' but hardware.light = 'dlpc900'; set "
                                         r"hardware.light to 'led' or 'led-simulated'$"):
        hardware_config(rig)
    rig.hardware, rig.light = {"light": "led"}, SimpleNamespace()
    with pytest.raises(ValueError, match=r"^rig.toml: hardware.light_port names no serial port"):
        hardware_config(rig)
    rig.hardware = {"light": "led-simulated", "camera_mode": "hardware-trigger"}
    with pytest.raises(ValueError, match="camera_mode must be 'strobe-master' with hardware.light = 'led-simulated'"):
        hardware_config(rig)


def test_rig_table_names_a_port_pyserial_opens():
    pytest.importorskip("serial")
    from specgpu.hardware.rig import open_light

    board = SimulatedLedBoard()
    url, stop = serve(board)
    try:
        light = open_light({"light": "led", "light_port": url, "light_channels": 3, "light_holdoff_us": 250})
        assert light.channels == 3 and board.channels == 3 and board.holdoff_us == 250
        light.close()
    finally:
        stop()


def test_calibration_on_real_devices_refuses_a_light_it_cannot_calibrate():
    from specgpu.hardware.rig import open_calibration_rig
    from specgpu.rig.config import RigDescription

    for light in ("led-simulated", "ol490-simulated"):
        with pytest.raises(ValueError, match=rf"^calibration on real devices needs a DLPC900 light \(hardware.light "
                                             rf"= 'dlpc900'\), got hardware.light = '{light}'$"):
            open_calibration_rig(RigDescription(), hardware={"light": light, "spectrometer": "ocean"})


def test_channel_count_left_by_an_earlier_session_is_set_again():
    board = SimulatedLedBoard()
    board.channels = 3  # as an earlier session left it: the board keeps its state between connections
    light = LedLight(controller(board))
    assert board.channels == 13
    light.load_sequence(np.full((2, 13), 0.5))
    assert board.complete


def test_a_late_reply_to_a_timed_out_command_is_not_taken_for_the_next_ones():
    board = SimulatedLedBoard()
    port = SimulatedSerial(board)
    ctl = LedController(port)
    port._replies += frame("OK", 3)  # the board's answer to a command the host had given up on
    assert ctl.status().pulses == 0
