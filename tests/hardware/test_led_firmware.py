"""The LED controller firmware and the simulated board speak the same protocol: the firmware
(``tools/firmware/led_controller/led_controller.ino``) is compiled for this machine against a stand-in of the Arduino
core (``firmware_host/``) and given one script of protocol lines, trigger edges and output probes; its replies and
outputs must be the simulated board's, byte for byte. Skipped where no C++ compiler is installed."""

from __future__ import annotations

import select
import shutil
import subprocess
from pathlib import Path

import pytest

from specgpu.hardware.errors import LightFault
from specgpu.hardware.led import LedController, LedLight, SimulatedLedBoard
from specgpu.hardware.led.protocol import crc8, frame

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "tools" / "firmware" / "led_controller"
HOST = Path(__file__).resolve().parent / "firmware_host"
CXX = shutil.which("g++") or shutil.which("clang++")


@pytest.fixture(scope="module")
def firmware(tmp_path_factory):
    if CXX is None:
        pytest.skip("no C++ compiler to build the firmware for the host")
    exe = tmp_path_factory.mktemp("firmware") / "led_controller"
    subprocess.run([CXX, "-std=c++17", "-DTEENSYDUINO", "-I", str(HOST), "-I", str(FIRMWARE), "-o", str(exe),
                    str(HOST / "main.cpp")], check=True, capture_output=True, text=True, timeout=120)
    return exe


def script():
    """Protocol lines (bytes), trigger edges ("!TRIG us") and output probes ("!PWM"), good and bad."""
    good = [frame(*f).rstrip(b"\n") for f in (
        ("ID",), ("ARM",), ("STEP", 0, 1), ("CH", 0), ("CH", 3), ("SEQ", 0), ("SEQ", 3), ("STEP", 0, 1, 2),
        ("STEP", 0, 4096, 0, 0), ("DARK", 0), ("STEP", 1, 4095, 0, 7), ("END",), ("SHOW", 1),
        ("STEP", 2, 0, 2048, 4095), ("END",), ("HOLD", 2_000_000), ("HOLD", 500), ("SHOW", 1))]
    bad = [b"ID*00", b"ID", b"ID*3", frame("STEP", "x").rstrip(b"\n"), frame("FOO", 1).rstrip(b"\n"),
           b"ID 1*" + b"%02X" % crc8(b"ID 1"), b"X" * 200]
    run = [frame(*f).rstrip(b"\n") for f in (("ARM",), ("SEQ", 2), ("SHOW", 0), ("CH", 2))]
    edges = [b"!TRIG %d" % t for t in (1000, 2000, 2100, 3000, 4000, 4400, 5000)]
    probes = [b"!PWM"]
    after = [frame(*f).rstrip(b"\n") for f in (("STAT",), ("STOP",), ("STAT",), ("SHOW", 2))]
    return (good + probes + bad + run[:1] + probes + edges[:2] + probes + edges[2:] + probes
            + [frame("STAT").rstrip(b"\n")] + run[1:] + after + probes)


def simulate(lines) -> bytes:
    board = SimulatedLedBoard()
    out = b""
    for line in lines:
        if line.startswith(b"!TRIG "):
            board.trigger(at_us=float(line.split()[1]))
        elif line == b"!PWM":
            out += b"PWM " + b" ".join(b"%d" % v for v in board.outputs) + b"\n"
        else:
            out += board.handle(line + b"\n")
    return out


def test_firmware_answers_every_line_as_the_simulated_board_does(firmware):
    lines = script()
    got = subprocess.run([str(firmware)], input=b"\n".join(lines) + b"\n", capture_output=True, check=True,
                         timeout=30).stdout
    want = simulate(lines)
    assert got.splitlines() == want.splitlines()
    # the script does reach the interesting states: refusals of every code, a missed edge, steps shown
    text = want.decode()
    for code in (1, 2, 3, 4, 5, 6):
        assert f"ERR {code} " in text
    assert "OK 1 7 5 2 2 1*" in text  # armed, 7 pulses, 5 steps, 2 missed (first: pulse 2), step 1 shown
    assert "PWM 4095 0 7 " in text  # step 1's duties on the pins


def test_the_driver_runs_against_the_firmware_over_a_pipe(firmware):
    proc = subprocess.Popen([str(firmware)], stdin=subprocess.PIPE, stdout=subprocess.PIPE)

    class Pipe:  # the firmware's serial port, as the driver sees a serial port
        port = "pipe://firmware"

        def write(self, data):
            proc.stdin.write(data)
            proc.stdin.flush()
            return len(data)

        def readline(self):  # b"" after the driver's timeout, as pyserial's readline
            ready, _, _ = select.select([proc.stdout], [], [], 5.0)
            return proc.stdout.readline() if ready else b""

        def close(self):
            proc.stdin.close()

    try:
        light = LedLight(LedController(Pipe()), channels=2)
        light.load_sequence([[0, 0], [1, 0.5]])
        light.start()
        for t in (1000, 2000, 2005):
            proc.stdin.write(b"!TRIG %d\n" % t)
        status = light.controller.status()
        assert (status.pulses, status.steps, status.missed, status.first_missed, status.step) == (3, 2, 1, 2, 1)
        light.at_frame(1)
        light.check()
        light.at_frame(2)
        with pytest.raises(LightFault, match="^LED controller on pipe://firmware missed trigger pulse 2"):
            light.check()
        light.close()
    finally:
        if proc.poll() is None:
            proc.stdin.close()
        proc.wait(timeout=10)
