"""``specgpu bound``: the lowest expected per-pixel error any K-frame linear design can reach on a rig within a
sequence-time budget, beside the best design found."""

from __future__ import annotations

import click

from specgpu.apps.cli.options import RIG, Busy, Finite, command
from specgpu.pipeline.denoise import DENOISE_RADIUS
from specgpu.planning.requests import requested_bound


@command("bound")
@click.option("--frames", type=click.IntRange(min=1, max=200), required=True, help="K, frames per sequence.")
@click.option("--sequence-ms", type=Finite(min=0.001, max=1e6), required=True, help="Time per sequence, ms.")
@click.option("--calib", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Calibration bundle (default: the rig's exact model).")
@click.option("--exclude-chart", default="ColorChecker N Ohta", show_default=True,
              help="Chart left out of the prior (the one you evaluate on).")
@click.option("--starts", type=click.IntRange(min=1, max=100), default=8, show_default=True,
              help="Starting points of the design search (the achievable side).")
@click.option("--denoise", is_flag=True,
              help="The limit where recover --denoise flattens the shot and read noise (plan --denoise designs).")
@click.option("--denoise-radius", type=click.IntRange(min=1, max=64), default=DENOISE_RADIUS, show_default=True,
              help="With --denoise: the filter's radius.")
@RIG
def bound(frames, sequence_ms, calib, exclude_chart, starts, rig_path, denoise, denoise_radius):
    """The lowest expected per-pixel RMSE any K-frame linear design can reach on the rig within a sequence time
    (shot and read noise, the training prior), beside the best design found: the limit lies between the two."""
    result = requested_bound(calib, rig_path, frames, sequence_ms, exclude_chart, starts, progress=Busy,
                             denoise_radius=denoise_radius if denoise else None)
    click.echo("\n".join(result.lines()))
