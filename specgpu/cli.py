"""The ``specgpu`` command.

Every command has --help, exits 0 on success and, on failure, prints one line saying why and exits non-zero.
"""

from __future__ import annotations

import sys

import click

from . import __version__


class _Group(click.Group):
    """Turns any error a command raises into one line on stderr and exit status 1 (2 for usage errors)."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort, SystemExit):
            raise
        except KeyboardInterrupt:
            click.echo("specgpu: interrupted", err=True)
            sys.exit(130)
        except Exception as error:  # noqa: BLE001: the CLI's contract is one line, not a traceback
            message = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise click.ClickException(message) from error


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="specgpu")
def main():
    """specgpu: active-illumination spectral imaging on OpenCL (Tominaga and Horiuchi, JOSA A 2012)."""


@main.command()
@click.option("--device", "device", default=None, help="Device selector: 'P:D' indices or a name substring.")
def info(device):
    """OpenCL platforms and devices, the one chosen, and versions."""
    from .runtime import describe

    click.echo(describe(device))


@main.command()
@click.option("--device", "device", default=None, help="Device selector: 'P:D' indices or a name substring.")
@click.option("--verbose", "-v", is_flag=True, help="Print the error figures of every case.")
def selftest(device, verbose):
    """Run the kernel regression suite (golden set) on this machine's device; exit 1 if any kernel fails."""
    from .selftest import run_selftest

    report = run_selftest(device=device)
    click.echo(report.format(verbose=verbose))
    if not report.passed:
        raise click.ClickException(f"selftest failed on {report.device}: {', '.join(report.failed_kernels())}")


@main.command()
@click.option("--device", "device", default=None, help="Device selector: 'P:D' indices or a name substring.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, writable=True), default=None,
              help="Also write the figures as JSON to this file.")
@click.option("--sizes", default="640x480,2048x2048", show_default=True,
              help="Comma-separated WxH image sizes.")
@click.option("--repeats", type=click.IntRange(min=1), default=None,
              help="Timed repetitions per case (default: by size).")
def bench(device, json_path, sizes, repeats):
    """Throughput of each kernel against NumPy / colour-science baselines measured in the same run."""
    from .bench import parse_sizes, run_bench

    try:
        parsed = parse_sizes(sizes)
    except ValueError as error:  # a usage error (exit 2) that names the bad token, before any device work
        raise click.BadParameter(str(error), param_hint="--sizes") from error
    run_bench(sizes=parsed, device=device, repeats=repeats, json_path=json_path, echo=click.echo)


if __name__ == "__main__":  # pragma: no cover
    main()
