"""``specgpu evaluate``: the accuracy of a recovered cube (or XYZ map) against the true scene."""

from __future__ import annotations

import json
from pathlib import Path

import click

from specgpu.apps.cli.options import RESIZE, Busy, command, integration_option, lock, no_clash, resampled
from specgpu.io.paths import atomic_path
from specgpu.pipeline.evaluate import PLAUSIBLE_RANGE
from specgpu.pipeline.evaluation_report import (
    colorimetry,
    evaluation_report,
    headline_line,
    patch_table,
    pixel_line,
    read_recovered,
    truth_file,
)
from specgpu.rig.scene import load_scene


@command()
@click.argument("cube", type=click.Path(exists=True, dir_okay=False))
@click.option("--truth", required=True,
              help="The true scene: colorchecker, white, natural[:image] or a .exr / .npz / .hdr (ENVI) cube; or "
                   "the sequence folder of a capture on a moving twin (its motion_truth/ at the sequence the cube "
                   "records). A truth that is not the capture (or sequence, or scene) the cube records is said on "
                   "stderr and in the report.")
@click.option("--illuminant", default=None,
              help="Illuminant of the colour differences [default: the one the file records (a tristimulus plan's "
                   "own), else D65]; another than an XYZ map records is refused.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None, help="Write the report here.")
@click.option("--exclude-invalid", is_flag=True,
              help=f"Score a cube holding infinite values or values outside the plausible range "
                   f"{PLAUSIBLE_RANGE[0]:g} to {PLAUSIBLE_RANGE[1]:g} without those pixels (counted in the report) "
                   "instead of refusing it. NaN pixels (flagged by the recovery) are always left out and counted.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@RESIZE
@integration_option(None, " [default: the one the file records, else rectangle]")
def evaluate(cube, truth, illuminant, json_path, exclude_invalid, device, resize, integration):
    """Accuracy of a recovered cube (.exr, .npz or ENVI .hdr; or an XYZ map) against the true scene: per pixel,
    and per patch for a chart, with the pixels left out counted by cause."""
    no_clash([("--json", json_path)], [("CUBE", cube), ("--truth", truth)])
    if json_path:
        lock(json_path)
    data, wavelengths, meta = read_recovered(cube)
    scene_source = truth_file(truth, meta)  # a moving capture's folder: the truth of the cube's sequence
    illuminant, cmfs = colorimetry(cube, meta, illuminant, colorimetric=wavelengths is None)
    height, width = data.shape[:2]
    scene = resampled(f"--truth {scene_source}", load_scene(scene_source, height, width, resize=resize))
    result = evaluation_report(cube, data, wavelengths, meta, scene, illuminant, cmfs, device=device,
                               progress=Busy, invalid="exclude" if exclude_invalid else "refuse", truth=truth,
                               integration=integration)
    report = result["report"]
    if "truth_mismatch" in report:
        click.echo(f"Warning: {report['truth_mismatch']}", err=True)
    if scene.masks:
        click.echo("\n".join(patch_table(report["patches"])))
    click.echo(headline_line(report, result["headline"], bool(scene.masks)))
    click.echo(pixel_line(report, result["pixel_statistics"], bool(scene.masks)))
    if json_path:
        with atomic_path(Path(json_path)) as tmp:
            tmp.write_text(json.dumps(report, indent=1, allow_nan=False))
