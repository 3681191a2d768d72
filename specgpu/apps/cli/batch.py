"""``specgpu batch``: the raw frames of a recording (or a sequence folder) re-processed with a plan on Dask."""

from __future__ import annotations

from pathlib import Path

import click

from specgpu.apps.cli.options import (
    ILLUMINANT,
    INTEGRATION,
    OBSERVER,
    PLAN,
    RESIZE,
    WHITE_ROI_MOVES,
    command,
    no_clash,
    output_list,
    parse_reference,
)
from specgpu.calibration.bundle import load_calibration
from specgpu.core.validate import validate_method
from specgpu.engine.colorimetry import DELTA_E_METHODS
from specgpu.motion.methods import MOTION_METHODS
from specgpu.pipeline.batch import BATCH_OUTPUTS, open_source, run_batch
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS
from specgpu.planning.plans import load_plan


def plan_calibration(plan, source, plan_path, calib):
    """The calibration ``plan`` was made from (default: SOURCE/calibration.npz); a stale pair is refused naming
    both files."""
    calib = Path(calib) if calib else Path(source) / "calibration.npz"
    if not calib.is_file():
        raise click.UsageError(f"{calib} not found; give --calib")
    bundle = load_calibration(calib)
    plan.check_calibration(bundle, name=str(plan_path), calibration_name=str(calib))  # names both files
    return bundle


@command("batch")
@click.argument("source", type=click.Path(exists=True, file_okay=False))
@PLAN
@click.option("--calib", default=None, type=click.Path(exists=True, dir_okay=False),
              help="Calibration the plan was made from (default: SOURCE/calibration.npz).")
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Output zarr (OUT.zarr); an existing one from the same batch is resumed.")
@click.option("--outputs", default="cube", show_default=True,
              help="Comma-separated: cube, XYZ, Lab, dE, sigma (each output's standard deviation and their RMS), "
                   "sigma_rms (that RMS alone), dE_sigma (first-order dE2000 standard deviation); the sigmas as "
                   "specgpu stream makes them, with --motion, --denoise and --white-roi, from the plan's noise model.")
@click.option("--delta-e-ref", "ref", default=None, help="dE reference: 'L,a,b' or a scene whose Lab per pixel is it.")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@ILLUMINANT
@OBSERVER
@INTEGRATION
@click.option("--scheduler", default=None,
              help="Address of a dask.distributed scheduler (default: Dask's scheduler-address setting, as "
                   "DASK_SCHEDULER_ADDRESS gives it, else a LocalCluster).")
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True,
              help="LocalCluster worker processes (one thread and one OpenCL context each).")
@click.option("--device", "device", default=None, help="OpenCL device selector (on every worker).")
@RESIZE
@click.option("--denoise", is_flag=True,
              help="Denoise the cube and XYZ (recover --denoise's guided filter), Lab, dE and dE_sigma computed "
                   "from the filtered XYZ; the sigmas carried through the filter.")
@click.option("--motion", type=click.Choice(list(MOTION_METHODS), case_sensitive=False), default="none",
              show_default=True, help="Compensate a scene that moved during each sequence, as recover --motion: a "
              "translation (global) or an affine map (affine) per frame, or a displacement per pixel (flow), "
              "estimated within the sequence; pixels seen "
              "outside the field or whose frames disagree are NaN.")
@click.option("--white-roi", default=None, metavar="X,Y,W,H",
              help="A reference white in the field: rescale each sequence's decoder for the light's drift (as "
                   "recover --white-roi).")
@click.option("--white-reflectance", default=None, metavar="VALUE|CSV",
              help="Reflectance of the --white-roi white: a number or a CSV (wavelength nm, value). [0.99]")
@WHITE_ROI_MOVES
def batch_command(source, plan_path, calib, out, outputs, ref, method, illuminant, observer, integration, scheduler,
                  workers, device, resize, denoise, motion, white_roi, white_reflectance, white_roi_moves):
    """Re-process the raw frames of a recording (specgpu stream --frames) or a sequence folder with a plan, on
    Dask: one task per sequence, resumable, equal to specgpu recover of each sequence."""
    no_clash([("--out", out)], [("SOURCE", source), ("--plan", plan_path), ("--calib", calib), ("--delta-e-ref", ref),
                                ("--white-reflectance", white_reflectance)])
    if white_reflectance is not None and white_roi is None:
        raise click.UsageError("--white-reflectance needs --white-roi")
    wanted = output_list(outputs, BATCH_OUTPUTS, "batch output")
    method = validate_method(method, DELTA_E_METHODS)
    if ("dE" in wanted) != (ref is not None):
        raise click.UsageError("the dE output and --delta-e-ref go together")
    plan = load_plan(plan_path)
    illuminant = plan.resolve_illuminant(illuminant, name=str(plan_path))
    observer = plan.resolve_observer(observer, name=str(plan_path))
    bundle = plan_calibration(plan, source, plan_path, calib)
    reference = None
    if ref is not None:
        src = open_source(source)
        reference = parse_reference(ref, src.height, src.width, illuminant, resize, observer=observer,
                                    integration=integration)
    report = run_batch(source, plan, bundle, out, outputs=wanted, illuminant=illuminant, observer=observer,
                       method=method, reference=reference, scheduler=scheduler, workers=workers, device=device,
                       denoise=(DENOISE_RADIUS, DENOISE_EPS) if denoise else None, motion=motion.lower(),
                       integration=integration,
                       white=None if white_roi is None else (white_roi, white_reflectance, white_roi_moves))
    click.echo(f"{plan.method}: {report.computed} sequences computed on {report.workers} worker(s) in "
               f"{report.seconds:.1f} s ({report.sequences_per_s:.1f} sequences/s), {report.skipped} already done; "
               f"OpenCL contexts built {report.contexts_built}; wrote {out}")
