"""The command group of ``specgpu``: its commands loaded lazily (each from its own module, only when it runs or
its help is asked for), every usage error on one line, SIGTERM handled like Ctrl-C and an interrupt exiting 130.
Only click and the standard library are imported here, so ``specgpu --help`` stays fast."""

from __future__ import annotations

import importlib
import os
import signal
import sys
import threading
import warnings
from contextlib import contextmanager

import click

__all__ = ["LazyGroup", "one_line_usage", "terminate_as_interrupt", "watch_outputs", "kept", "interrupted_line",
           "one_line_warnings"]

_WATCHED = "specgpu.watched_outputs"  # click's context meta, shared by the group and its command
_KEPT = "specgpu.kept"


def _state(path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def watch_outputs(paths) -> None:
    """Note the state of these outputs now (before the command writes them), so that an interrupt can say which
    of them it leaves written (:func:`interrupted_line`)."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        watched = ctx.meta.setdefault(_WATCHED, {})
        for path in paths:
            watched.setdefault(str(path), _state(path))


def kept(path, what: str) -> None:
    """Say what an interrupted command keeps at output ``path`` (``what``: "3 of 5 sequences in seq"), in place of
    the plain path :func:`interrupted_line` would name."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.meta.setdefault(_KEPT, {})[str(path)] = what


def interrupted_line(ctx) -> str:
    """The one line of an interrupted command: ``specgpu: interrupted; kept ...`` naming every output it wrote
    or changed (a folder output without a word from its command is said to be incomplete), or ``...; nothing
    written``."""
    said = ctx.meta.get(_KEPT, {})
    parts = []
    for path, before in ctx.meta.get(_WATCHED, {}).items():
        if path in said:
            parts.append(said[path])
        elif _state(path) not in (None, before):
            parts.append(f"{path}, incomplete" if os.path.isdir(path) else path)
    parts += [what for path, what in said.items() if path not in ctx.meta.get(_WATCHED, {})]
    return "specgpu: interrupted; " + (f"kept {'; '.join(parts)}" if parts else "nothing written")


def one_line_usage(error: click.UsageError) -> click.UsageError:
    """A usage error as one ``Error: ...`` line (exit status 2): click prints a usage error with the command's
    synopsis and a "Try --help" line before it, three lines where every other error is one. The message keeps
    click's naming of the option or argument; the help pointer moves onto the same line."""
    if error.ctx is None or isinstance(error, getattr(click.exceptions, "NoArgsIsHelpError", ())):
        return error  # already one line (raised by a command), or the plain group's help (click >= 8.2)
    message = error.format_message().strip().splitlines()[0].rstrip().rstrip(".")
    hint = f"; see '{error.ctx.command_path} --help'" if error.ctx.command.get_help_option(error.ctx) else ""
    one = click.UsageError(message + hint)  # no context: click's show() then prints the Error: line alone
    one.__cause__ = error
    return one


class terminate_as_interrupt:
    """SIGTERM (``kill``, a service manager stopping us) is handled like Ctrl-C: a stream drains, a capture or
    recover removes what it half wrote (a capture keeps its complete sequences); only ``kill -9`` cannot be
    handled, and a killed capture is salvaged (see README, Reliability)."""

    def __enter__(self):
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            def interrupt(signum, frame):
                raise KeyboardInterrupt

            self._previous = signal.signal(signal.SIGTERM, interrupt)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGTERM, self._previous)


def _one_line(message, category, filename, lineno, line=None) -> str:
    return f"Warning: {' '.join(str(message).split())}\n"


@contextmanager
def one_line_warnings():
    """Within it, a warning a command's library code raises is printed as the commands print theirs: one line,
    ``Warning: <message>`` on stderr, without Python's file, line number and source line."""
    before = warnings.formatwarning
    warnings.formatwarning = _one_line
    try:
        yield
    finally:
        warnings.formatwarning = before


class LazyGroup(click.Group):
    """click's lazy-loading group: ``lazy_commands`` maps each name to ``(module:attribute, summary)``; the module is
    imported when the command runs or shows its help, and the group's help lists the summaries (each the first
    paragraph of the command's help) without importing any. The exit status follows one rule: 0 done, 2 a usage
    error (one line), 1 any other failure (one line), 130 interrupted (one line saying what was kept,
    :func:`interrupted_line`); a command's other errors are turned into one line by the command itself
    (:class:`specgpu.apps.cli.options.Command`, which names an output, never its temporary), any left over
    here too."""

    def __init__(self, *args, lazy_commands=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.lazy_commands = dict(lazy_commands or {})

    def list_commands(self, ctx):
        return sorted({*super().list_commands(ctx), *self.lazy_commands})

    def get_command(self, ctx, cmd_name):
        if cmd_name in self.lazy_commands and cmd_name not in self.commands:
            module, attribute = self.lazy_commands[cmd_name][0].split(":")
            self.add_command(getattr(importlib.import_module(module), attribute), cmd_name)
        return super().get_command(ctx, cmd_name)

    def format_commands(self, ctx, formatter):
        limit = formatter.width - 6 - max(len(name) for name in self.list_commands(ctx))
        rows = [(name, click.Command(name, help=self.lazy_commands[name][1]).get_short_help_str(limit))
                for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except click.UsageError as error:  # the group's own options: `specgpu --bogus`
            raise one_line_usage(error) from error

    def invoke(self, ctx):
        try:
            with terminate_as_interrupt(), one_line_warnings():
                return super().invoke(ctx)
        except click.UsageError as error:  # a command's options and arguments, an unknown command
            raise one_line_usage(error) from error
        except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort, SystemExit):
            raise
        except KeyboardInterrupt:  # exit 130 with what is kept, wherever the command was when stopped
            click.echo(interrupted_line(ctx), err=True)
            sys.exit(130)
        except Exception as error:  # outside a command's body (its options, its resources): still one line
            text = str(error).strip()
            raise click.ClickException(text.splitlines()[0] if text else type(error).__name__) from error
