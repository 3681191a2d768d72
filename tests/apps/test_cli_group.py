"""The command group (specgpu.apps.cli): every command's help, the listing of the commands without loading them,
and each command's summary equal to its help."""

from __future__ import annotations

import subprocess
import sys

import pytest
from click.testing import CliRunner

from specgpu.apps.cli import COMMANDS, main


@pytest.mark.parametrize("command", [[], *([name] for name in COMMANDS)])
def test_help_of_every_command(command):
    result = CliRunner().invoke(main, [*command, "--help"])
    assert result.exit_code == 0 and "Usage:" in result.output


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_summary_is_the_first_paragraph_of_the_commands_help(name):
    command = main.get_command(None, name)
    assert command.help.split("\n\n")[0].split() == COMMANDS[name][1].split()


def test_the_listing_loads_no_command_module():
    code = ("import sys; from click.testing import CliRunner; from specgpu.apps.cli import main; "
            "r = CliRunner().invoke(main, ['--help']); assert r.exit_code == 0, r.output; "
            "print(sorted(m for m in sys.modules if m.startswith('specgpu.') and m.count('.') > 1))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['specgpu.apps.cli', 'specgpu.apps.cli.group']"


def test_every_command_is_listed():
    result = CliRunner().invoke(main, ["--help"])
    listed = [line.split()[0] for line in result.output.split("Commands:")[1].splitlines() if line.strip()]
    assert listed == sorted(COMMANDS)


def test_a_warning_from_a_commands_library_code_is_one_line_and_python_is_left_as_it_was():
    code = ("import warnings, click; from specgpu.apps.cli.group import LazyGroup\n"
            "group = LazyGroup(name='g')\n"
            "@group.command('warns')\n"
            "def warns():\n"
            "    warnings.warn('the motion is not steady:\\n  pixels flagged', RuntimeWarning, stacklevel=1)\n"
            "before = warnings.formatwarning\n"
            "group(['warns'], standalone_mode=False)\n"
            "assert warnings.formatwarning is before\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stderr.splitlines() == ["Warning: the motion is not steady: pixels flagged"]
