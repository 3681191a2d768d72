"""``specgpu demo``: the main job on the built-in twin, with the paper's tables beside ours."""

from __future__ import annotations

import click

from specgpu.apps.cli.options import RIG, command, lock, no_clash
from specgpu.apps.demo import format_tables, run_demo


@command()
@click.option("--out", default="specgpu-report", show_default=True, type=click.Path(file_okay=False),
              help="Report folder.")
@RIG
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the twin's noise (calibration and captures): a seed gives the same figures each run.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@click.option("--draws", type=click.IntRange(1, 50), default=None,
              help="Noise draws per method and profile (tables give mean +- std); 1 by default, 2 with --full.")
@click.option("--full", is_flag=True,
              help="Every row on both profiles (lab and ideal): the estimator rows and every method at equal "
                   "sequence time besides the paper's plans; minutes rather than one.")
def demo(out, rig_path, seed, device, draws, full):
    """The main job on the built-in twin: calibrate, plan, capture the chart, recover, evaluate; prints the
    paper's Tables 1-3 beside ours and writes a report folder with index.html.

    It says first what it runs and about how long that takes: by default the lab profile, the paper's plans, the
    design of each sequence-time budget (on the DMD and on a 12-LED rig) and a moving scene, one noise draw."""
    no_clash([("--out", out)], [("--rig", rig_path)])
    lock(out, folder=True)
    result = run_demo(out, rig=rig_path, seed=seed, echo=click.echo, device=device, draws=draws,
                      full=full)
    click.echo(format_tables(result))
    click.echo(f"\ndemo finished in {result.seconds:.1f} s; report: {result.out / 'index.html'}")
