"""Every command's --help, walked over the click command tree: each option says what it does, and the help as
printed never breaks a word across lines (a default too long for the column is cut mid-word by click)."""

from __future__ import annotations

import re

import click
import pytest
from click.testing import CliRunner

from specgpu.apps.cli import COMMANDS, main


def commands():
    """(path, command) of every command and subcommand under ``specgpu``."""
    found = []

    def walk(path, command):
        found.append((path, command))
        if isinstance(command, click.Group):
            ctx = click.Context(command)
            for name in command.list_commands(ctx):
                walk((*path, name), command.get_command(ctx, name))

    ctx = click.Context(main)
    for name in sorted(COMMANDS):
        walk((name,), main.get_command(ctx, name))
    return found


COMMAND_TREE = commands()
IDS = [" ".join(path) for path, _ in COMMAND_TREE]


@pytest.mark.parametrize("path, command", COMMAND_TREE, ids=IDS)
def test_every_option_has_help_text(path, command):
    bare = [p.opts[-1] for p in command.params
            if isinstance(p, click.Option) and not p.hidden and not (p.help or "").strip()]
    assert bare == [], f"specgpu {' '.join(path)}: options without help text: {', '.join(bare)}"


@pytest.mark.parametrize("path, command", COMMAND_TREE, ids=IDS)
@pytest.mark.parametrize("columns", ["80", "100"])
def test_no_help_line_breaks_a_word(path, command, columns):
    """Every word of each option's help and shown default appears whole in the printed help (a line may end at
    a word's own hyphen, as in print)."""
    result = CliRunner().invoke(main, [*path, "--help"], env={"COLUMNS": columns})
    assert result.exit_code == 0, result.output
    printed = set(re.sub(r"(?<=\w-)\n\s+", "", result.output).split())
    ctx = click.Context(command, info_name=path[-1])
    broken = []
    for param in command.params:
        record = param.get_help_record(ctx)
        if record is not None:
            broken += [f"{record[0]}: {word!r}" for word in record[1].split() if word not in printed]
    assert broken == [], f"specgpu {' '.join(path)} --help breaks: {'; '.join(broken)}"
