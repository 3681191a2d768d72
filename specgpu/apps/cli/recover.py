"""``specgpu recover``: a sequence folder recovered to a cube (or a tristimulus plan's map) and, when asked, XYZ,
Lab, dE and uncertainty maps, written all or nothing."""

from __future__ import annotations

import click
import numpy as np

from specgpu.apps.cli.options import (
    ILLUMINANT,
    INTEGRATION,
    OBSERVER,
    RESIZE,
    WHITE_ROI_MOVES,
    Busy,
    Finite,
    Staged,
    command,
    lock,
    no_clash,
    parse_reference,
)
from specgpu.core.validate import validate_method
from specgpu.engine.colorimetry import DELTA_E_METHODS
from specgpu.motion.methods import MOTION_METHODS
from specgpu.pipeline import recovery
from specgpu.pipeline.capture_folder import read_capture
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS, denoise_design_warning
from specgpu.pipeline.motion_record import without_motion
from specgpu.pipeline.moving_decode import check_motion_options
from specgpu.pipeline.outputs import recovery_metadata, recovery_writes


def recovered(folder, seq, *, sequence, device, white_roi, white_reflectance, colours, denoise=None,
              motion="none", integration="rectangle", white_moves="scene"):
    """The recovery of ``folder`` (a refusal is one line naming why), motion-compensated when ``motion`` is not
    "none", denoised when ``denoise`` gives (radius, eps), the metadata of its outputs and the warnings to say (a
    dark level not to be trusted; a capture that moved, recovered without ``--motion``)."""
    try:
        check_motion_options(motion, folder.plan)  # as the decoder checks
        y = recovery.recover(folder, sequence=sequence, device=device, white_roi=white_roi,
                             white_reflectance=white_reflectance, motion=motion, denoise=denoise,
                             white_moves=white_moves)
    except ValueError as error:
        raise click.ClickException(str(error)) from None
    untrusted = recovery.dark_warning(folder, sequence)  # said once the spinner has gone, recorded with every output
    notice = without_motion(folder, averaged=sequence is None) if motion == "none" else None
    meta = recovery_metadata(folder, seq, sequence=sequence, illuminant=colours[0], observer=colours[1],
                             white_roi=white_roi, white_reflectance=white_reflectance, untrusted=untrusted,
                             integration=integration)
    if denoise is not None:
        meta["denoise"] = f"guided filter, radius {denoise[0]}, eps {denoise[1]:g}, guide: the " \
                            f"{'warped ' if motion != 'none' else ''}frames' sum"
    if motion != "none":
        meta["motion"] = f"{motion} compensation of each frame, estimated within the sequence"
        if white_roi is not None:
            meta["white_roi_moves"] = white_moves
    elif notice:
        meta["motion"] = "none: the capture moved, decoded as if still"
    return y, meta, [w for w in (untrusted, notice) if w]


@command()
@click.argument("seq", type=click.Path(exists=True, file_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False),
              help="Recovered cube (.exr / .npz / .hdr ENVI); an XYZ map for a tristimulus plan.")
@click.option("--interleave", type=click.Choice(["bsq", "bil", "bip"]), default="bsq", show_default=True,
              help="ENVI (.hdr) cube layout: band sequential, interleaved by line or by pixel.")
@click.option("--xyz", "xyz_path", type=click.Path(dir_okay=False), default=None, help="Also write XYZ (EXR).")
@click.option("--lab", "lab_path", type=click.Path(dir_okay=False), default=None, help="Also write CIELAB (EXR).")
@click.option("--delta-e-ref", "ref", default=None,
              help="Reference: 'L,a,b', or a scene whose true colour per pixel (over all its bands) is it.")
@click.option("--delta-e", "de_path", type=click.Path(dir_okay=False), default=None,
              help="Colour-difference map to write (EXR; .png for a heat map).")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@ILLUMINANT
@OBSERVER
@INTEGRATION
@click.option("--sequence", type=int, default=None, help="Recover one sequence (default: the mean of all).")
@click.option("--half", is_flag=True, help="Write the cube in half precision.")
@click.option("--sigma", "sigma_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the per-pixel standard deviation of each output and their RMS (EXR).")
@click.option("--delta-e-sigma", "de_sigma_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the per-pixel dE2000 standard deviation (first-order, under --illuminant; EXR).")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@click.option("--white-roi", default=None, metavar="X,Y,W,H",
              help="A reference white in the field: rescale each sequence's decoder for the light's drift.")
@click.option("--white-reflectance", default=None, metavar="VALUE|CSV",
              help="Reflectance of the --white-roi white: a number or a CSV (wavelength nm, value). [0.99]")
@WHITE_ROI_MOVES
@click.option("--denoise", is_flag=True,
              help="Remove per-pixel noise without losing edges: a guided filter on the device, guided by the sum of "
                   "the frames; --sigma and --delta-e-sigma are carried through it.")
@click.option("--denoise-radius", type=click.IntRange(min=1, max=64), default=DENOISE_RADIUS, show_default=True,
              help="--denoise: window radius, px.")
@click.option("--denoise-eps", type=Finite(min=1e-12, max=1e3), default=DENOISE_EPS, show_default=True,
              help="--denoise: regularisation, in units of the frame sum's 99th percentile squared.")
@click.option("--motion", type=click.Choice(list(MOTION_METHODS), case_sensitive=False), default="none",
              show_default=True, help="Compensate a scene that moved: a translation (global) or an affine map "
              "(affine) per frame, or a displacement per pixel (flow: global, then a tile flow where it agrees "
              "better), one sequence at a time; pixels seen outside the field or whose frames disagree are NaN.")
@RESIZE
def recover(seq, out, interleave, xyz_path, lab_path, ref, de_path, method, illuminant, observer, integration,
            sequence, half,
            sigma_path, de_sigma_path, device, white_roi, white_reflectance, resize, denoise, denoise_radius,
            denoise_eps, motion, white_roi_moves):
    """Recover a sequence folder: the cube and, when asked, XYZ, Lab and dE maps (written only if all succeed)."""
    if (ref is None) != (de_path is None):
        raise click.UsageError("--delta-e-ref and --delta-e go together")
    method = validate_method(method, DELTA_E_METHODS)
    paths = {"out": out, "xyz_path": xyz_path, "lab_path": lab_path, "de_path": de_path, "sigma_path": sigma_path,
             "de_sigma_path": de_sigma_path}
    outputs = list(zip(("--out", "--xyz", "--lab", "--delta-e", "--sigma", "--delta-e-sigma"), paths.values()))
    no_clash(outputs, [("SEQ", seq), ("--delta-e-ref", ref), ("--white-reflectance", white_reflectance)])
    lock(*(p for _, p in outputs if p))  # before the work: a missing folder or a busy output is refused now
    folder = read_capture(seq)
    colours = (folder.plan.resolve_illuminant(illuminant, name=f"the plan of {seq}"),
               folder.plan.resolve_observer(observer, name=f"the plan of {seq}"))
    white = {"white_roi": white_roi, "white_reflectance": white_reflectance}
    with Busy("recovering"):
        if white_reflectance is not None and white_roi is None:
            raise click.UsageError("--white-reflectance needs --white-roi")
        y, meta, warnings = recovered(folder, seq, sequence=sequence, device=device, colours=colours, **white,
                                       denoise=(denoise_radius, denoise_eps) if denoise else None, motion=motion,
                                       integration=integration, white_moves=white_roi_moves)
        writes = recovery_writes(folder, y, meta, **paths, colours=colours, sequence=sequence, half=half,
                                 interleave=interleave, method=method, device=device, **white,
                                 denoise=(denoise_radius, denoise_eps) if denoise else None, integration=integration,
                                 motion=motion, white_moves=white_roi_moves,
                                 reference=lambda h, w, m: parse_reference(ref, h, w, colours[0], resize, m,
                                                                           colours[1], integration))
    for warning in warnings:
        click.echo(f"Warning: {warning}", err=True)
    mismatch = denoise_design_warning(folder.plan, denoise_radius if denoise else None)
    if mismatch:
        click.echo(f"Warning: {mismatch}", err=True)
    written = Staged().write_all(writes)  # all or nothing: no output replaced until every one is written
    saturated = int(np.isnan(y[..., 0]).sum())
    note = f"; {saturated} {'saturated or out-of-field' if motion != 'none' else 'saturated'} pixels left NaN" \
        if saturated else ""
    click.echo(f"{folder.plan.method}: {folder.plan.K} projections, {folder.sequences} sequences in {seq}; wrote "
               + ", ".join(str(p) for p in written) + note)
