"""``specgpu report``: the HTML report of a run folder (a capture and its recovery, or the demo's folder)."""

from __future__ import annotations

from pathlib import Path

import click

from specgpu.apps.cli.options import DEVICE, Busy, command, lock, no_clash
from specgpu.apps.report import find_captures, report_folder


@command()
@click.argument("run_folder", type=click.Path(exists=True, file_okay=False))
@click.option("--out", type=click.Path(dir_okay=False), default=None,
              help="The report (HTML) [default: RUN_FOLDER/report.html].")
@click.option("--truth", default=None,
              help="The true scene (colorchecker, white, natural[:image] or a cube file) [default: the scene the "
                   "capture records, when it can be rebuilt; none: no error figures].")
@DEVICE
def report(run_folder, out, truth, device):
    """Write the HTML report of a run folder (a capture folder, or folders of captures as the demo writes them):
    each capture recovered, scored against its truth, with tables, spectra, error maps and renderings."""
    out = out or Path(run_folder) / "report.html"
    no_clash([("--out", out)], [*((f"RUN_FOLDER's capture {name}", path)
                                   for name, path in find_captures(run_folder).items()), ("--truth", truth)])
    lock(out)
    notes = []  # said once the progress line has gone
    with Busy("reporting"):
        path = report_folder(run_folder, out=out, truth=truth, device=device, say=notes.append)
    for line in notes:
        click.echo(line, err=True)
    click.echo(f"wrote {path}")
