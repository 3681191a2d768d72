"""``specgpu evaluate``: the accuracy of a recovered cube (or XYZ map) against the true scene."""

from __future__ import annotations

import json
from pathlib import Path

import click

from specgpu import io
from specgpu.apps.cli.options import RESIZE, Busy, command, integration_option, lock, no_clash, resampled
from specgpu.pipeline.evaluation_report import (
    colorimetry,
    evaluation_report,
    headline_line,
    patch_table,
    read_recovered,
)
from specgpu.pipeline.moving import sequence_truth
from specgpu.rig.scene import load_scene


@command()
@click.argument("cube", type=click.Path(exists=True, dir_okay=False))
@click.option("--truth", required=True,
              help="The true scene: colorchecker, white, natural[:image] or a .exr / .npz / .hdr (ENVI) cube; or "
                   "the sequence folder of a capture on a moving twin (its motion_truth/ at the sequence the cube "
                   "records).")
@click.option("--illuminant", default=None,
              help="Illuminant of the colour differences [default: the one the file records (a tristimulus plan's "
                   "own), else D65]; another than an XYZ map records is refused.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None, help="Write the report here.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@RESIZE
@integration_option(None, " [default: the one the file records, else rectangle]")
def evaluate(cube, truth, illuminant, json_path, device, resize, integration):
    """Accuracy of a recovered cube (.exr, .npz or ENVI .hdr; or an XYZ map) against the true scene: per pixel,
    and per patch for a chart."""
    if json_path:
        no_clash([("--json", json_path)], [("CUBE", cube), ("--truth", truth if Path(truth).exists() else None)])
        lock(json_path)
    data, wavelengths, meta = read_recovered(cube)
    if Path(truth).is_dir():  # a moving capture's folder: the truth of the sequence the cube was recovered from
        truth = str(sequence_truth(truth, meta.get("sequence")))
    illuminant, cmfs = colorimetry(cube, meta, illuminant, colorimetric=wavelengths is None)
    height, width = data.shape[:2]
    scene = resampled(f"--truth {truth}", load_scene(truth, height, width, resize=resize))
    result = evaluation_report(cube, data, wavelengths, meta, scene, illuminant, cmfs, device=device,
                               progress=Busy, integration=integration)
    report = result["report"]
    if scene.masks:
        click.echo("\n".join(patch_table(report["patches"])))
    click.echo(headline_line(report, result["headline"], bool(scene.masks)))
    if json_path:
        with io.atomic_path(Path(json_path)) as tmp:
            tmp.write_text(json.dumps(report, indent=1))
