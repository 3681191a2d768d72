"""The info and selftest commands (specgpu.apps.cli.info) end to end: exit codes and one-line errors."""

from __future__ import annotations

from click.testing import CliRunner

from specgpu.apps.cli import main


def test_info_lists_devices_and_the_choice(queue):
    result = CliRunner().invoke(main, ["info"])
    assert result.exit_code == 0, result.output
    assert "platform 0:" in result.output and "chosen: " in result.output and "versions: " in result.output


def test_selftest_passes(queue):
    result = CliRunner().invoke(main, ["selftest", "--device", "0:0"])
    assert result.exit_code == 0, result.output
    assert "PASS: every kernel reproduces the golden set" in result.output


def test_unknown_device_is_one_line_and_nonzero():
    result = CliRunner().invoke(main, ["info", "--device", "99:99"])
    assert result.exit_code == 1
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines == ["Error: device='99:99' matches no OpenCL device (available: "
                     + lines[0].split("(available: ", 1)[1]]

