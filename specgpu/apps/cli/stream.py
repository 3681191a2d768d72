"""``specgpu stream``: a plan's sequences streamed from the rig through the device to maps, with a live status
line, optionally recorded to zarr; Ctrl-C stops cleanly."""

from __future__ import annotations

import sys

import click
import numpy as np

from specgpu.apps.cli.group import kept
from specgpu.apps.cli.options import (
    ILLUMINANT,
    INTEGRATION,
    OBSERVER,
    PLAN,
    RESIZE,
    RIG,
    SCENE,
    WHITE_ROI_MOVES,
    Finite,
    command,
    experiment,
    lock,
    no_clash,
    one_interrupt,
    output_list,
    parse_reference,
)
from specgpu.apps.live_view import run_with_view
from specgpu.hardware.drivers import hardware_config, open_rig_driver
from specgpu.io.recording import refuse_existing
from specgpu.motion.methods import MOTION_METHODS
from specgpu.pipeline.accumulate import AccumulateSink
from specgpu.pipeline.decoder_outputs import STREAM_OUTPUTS
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS
from specgpu.pipeline.live import add_recording, behind_text, recording_slots, stream_summary
from specgpu.pipeline.motion_record import without_motion
from specgpu.pipeline.moving_decode import check_motion_options
from specgpu.pipeline.outputs import stream_metadata
from specgpu.pipeline.stream import Stream
from specgpu.pipeline.twin_capture import check_scene_covers
from specgpu.planning.uncertainty import constant_variance
from specgpu.rig.config import load_rig

#: the longest stream: a year (a longer one overflows the sequence count the free-space check works out)
MAX_STREAM_S = 366 * 86400


def status_line(s, tty):
    """The live status line (rewritten in place on a terminal)."""
    line = (f"frames in {s['frames_in']}, sequences out {s['sequences_out']}, drops {s['assembler_dropped']} "
            f"(ring {s['ring_dropped']}), discarded {s['discarded']}, latency {s['latency_ms']:.1f} ms"
            + (f", {behind_text(s['frame_rate_hz'], s['plan_frame_rate_hz'])}" if s.get("behind") else ""))
    click.echo(("\r" + line + "   ") if tty else line, err=True, nl=not tty)


def sink_stopped_line(message, tty):
    """An optional sink the stream stopped, said once on stderr (below the live status line on a terminal)."""
    click.echo(("\n" if tty else "") + f"Warning: {message}; the stream goes on", err=True)


def stream_run(driver, description, plan, bundle, truth, wanted, reference, out, raw_frames, plan_path, calib,
               seconds, method, colours, pacing, policy, exr_every, half, seed, device, white=(None, None),
               disk_check=True, view=False, denoise=None, accumulate=None, motion="none", integration="rectangle"):
    """The stream of ``specgpu stream`` once its driver is open: the recording set up, run, summarised;
    ``colours``: the (illuminant, observer) of its XYZ, Lab and dE; ``integration``: of its XYZ and white."""
    illuminant, observer = colours
    white_roi, white_reflectance, white_moves = (*white, "scene")[:3]  # (ROI, reflectance[, where it moves])
    motion = check_motion_options(motion, plan, outputs=wanted)  # before any output: one line naming the option
    notice = without_motion(description, averaged=False) if motion == "none" else None
    if notice:
        click.echo(f"Warning: {notice}", err=True)
    accumulator = (None if accumulate is None else  # refused before any output
                   AccumulateSink(accumulate, wanted, motion=motion != "none",
                                  constant_variance=constant_variance(plan)))
    policy = policy or ("drop_newest" if pacing == "paced" else "block")
    stream = Stream(driver, plan, bundle, outputs=wanted, reference=reference, method=method,
                    illuminant=illuminant, observer=observer, cube_dtype=np.float16 if half else np.float32,
                    policy=policy, device=device, white_roi=white_roi, white_reflectance=white_reflectance,
                    white_moves=white_moves, n_slots=recording_slots(plan, description) if out else None,
                    denoise=denoise, motion=motion, integration=integration,
                    frame_rate_hz=plan.rig_description(description).camera.frame_rate_hz)
    writer = None
    if out:
        meta = stream_metadata(truth, illuminant=illuminant, observer=observer, method=method, seed=seed,
                               white_roi=white_roi, white_reflectance=white_reflectance, integration=integration)
        if denoise is not None:
            meta["denoise"] = f"guided filter, radius {denoise[0]}, eps {denoise[1]:g}, guide: the " \
                            f"{'warped ' if motion != 'none' else ''}frames' sum"
        if motion != "none":
            meta["motion"] = f"{motion} compensation of each frame, estimated within the sequence"
            if white_roi is not None:
                meta["white_roi_moves"] = white_moves
        if accumulate is not None:
            meta["accumulate"] = (f"running estimate over up to {accumulate} sequences, reset beyond 3 sigma"
                                  + (", moved with the scene between sequences" if motion != "none" else "")
                                  + "; the sigma maps are the running estimate's")
        writer = add_recording(stream, plan, description, out, wanted=wanted, raw_frames=raw_frames,
                               plan_path=plan_path, calib=calib, seconds=seconds, policy=policy, meta=meta,
                               exr_every=exr_every, method=method, colours=colours, disk_check=disk_check)
    if accumulator is not None:  # first in line: the recording and every other sink see the running estimate
        stream.sinks.insert(0, accumulator)
    tty = sys.stderr.isatty()
    stopped = lambda m: sink_stopped_line(m, tty and not view)  # noqa: E731
    try:
        with one_interrupt():
            report = (run_with_view(stream, seconds, wavelengths=plan.output_wavelengths if plan.output ==
                                    "reflectance" else None, illuminant=illuminant, on_sink_stopped=stopped) if view
                      else stream.run(seconds, on_status=lambda s: status_line(s, tty), on_sink_stopped=stopped))
    except BaseException as error:  # the recording says it failed (never "complete"), with the reason
        if writer is not None and not isinstance(error, KeyboardInterrupt):
            writer.mark_failed(f"{type(error).__name__}: {error}")
        elif writer is not None:
            kept(out, f"{writer.committed} complete sequences in {out}")
        raise
    if tty:
        click.echo("", err=True)
    click.echo(stream_summary(report, out, writer))
    if report.interrupted and not report.sink_errors:  # drained and summarised: still an interrupted run (130)
        if writer is not None:
            kept(out, f"{writer.committed} complete sequences in {out}")
        raise KeyboardInterrupt
    if report.sink_errors:
        saved = (f"; {writer.committed} sequences saved in {out}, {report.sequences_out - writer.committed} lost"
                 if writer is not None else "")
        raise click.ClickException(f"a sink failed: {report.sink_errors[0]}{saved}")


@command("stream")
@RIG
@PLAN
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False),
              help="The calibration the plan was made from.")
@SCENE
@click.option("--seconds", type=Finite(min=0, min_open=True, max=MAX_STREAM_S), required=True,
              help="Capture time (at most a year: 31622400 s).")
@click.option("--out", type=click.Path(file_okay=False), default=None,
              help="New zarr recording to write (REC.zarr: one chunk per sequence, xarray / dask readable), with "
                   "preview.png inside.")
@click.option("--frames", "raw_frames", is_flag=True, help="Also record the raw frames (for specgpu batch).")
@click.option("--outputs", default="coefficients,XYZ,dE", show_default=True,
              help="Comma-separated: coefficients, cube, XYZ, Lab, dE, sigma (each output's standard deviation and "
                   "their RMS), sigma_rms (that RMS alone), dE_sigma (first-order dE2000 standard deviation); the "
                   "sigmas use the noise model specgpu plan records (a plan of a custom rig needs plan --rig).")
@click.option("--delta-e-ref", "ref", default=None,
              help="dE reference: 'L,a,b' or a scene whose Lab per pixel is it (default: the streamed scene).")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@ILLUMINANT
@OBSERVER
@INTEGRATION
@click.option("--pacing", type=click.Choice(["paced", "free"]), default="paced", show_default=True,
              help="Twin pacing: at the camera's frame rate, or as fast as it renders.")
@click.option("--policy", type=click.Choice(["drop_newest", "drop_oldest", "block"]), default=None,
              help="Frame ring policy when the pipeline falls behind (default: drop_newest when paced, as a "
                   "camera never waits; block when free-running, where the simulated camera can).")
@click.option("--exr-every", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also write every N-th result as EXR maps into --out (0: none).")
@click.option("--half", is_flag=True, help="Keep the cube in half precision.")
@click.option("--seed", type=click.IntRange(min=0, max=2**63 - 1), default=None,
              help="Seed of the frames' temporal noise.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@click.option("--white-roi", default=None, metavar="X,Y,W,H",
              help="A reference white in the field: rescale each sequence's decoder for the light's drift (as "
                   "recover --white-roi; the gains are recorded).")
@click.option("--white-reflectance", default=None, metavar="VALUE|CSV",
              help="Reflectance of the --white-roi white: a number or a CSV (wavelength nm, value). [0.99]")
@WHITE_ROI_MOVES
@click.option("--denoise", is_flag=True,
              help="Denoise the coefficients, cube and XYZ outputs on the device (recover --denoise's guided filter), "
                   "Lab, dE and dE_sigma computed from the filtered XYZ; the sigmas carried through the filter.")
@click.option("--accumulate", type=click.IntRange(min=2), default=None, metavar="N",
              help="Each pixel's running estimate over up to N sequences, restarted where it changes beyond its "
                   "noise (needs the cube and sigma or sigma_rms outputs); with --motion it moves with the scene.")
@click.option("--motion", type=click.Choice(list(MOTION_METHODS), case_sensitive=False), default="none",
              show_default=True, help="Compensate a scene that moves during each sequence, as recover --motion: a "
              "translation (global) or an affine map (affine) per frame, or a displacement per pixel (flow), "
              "estimated within the sequence; the sigmas at the warped samples; with --denoise the "
              "guide is the warped frames' sum; --white-roi-moves says where a reference white is measured.")
@RESIZE
@click.option("--view", is_flag=True,
              help="Show the latest results in napari while streaming (the viewer extra): the sRGB of XYZ, dE and "
                   "the cube with the spectrum widget, as --outputs asks for them; the view never slows the stream.")
@click.option("--no-disk-check", is_flag=True,
              help="Record even when a write probe says the disk cannot keep up with --out (frames will be "
                   "dropped); also skips the probe that chooses each array's compression.")
def stream_command(rig_path, plan_path, calib, scene, seconds, out, raw_frames, outputs, ref, method, illuminant,
                   observer, integration, pacing, policy, exr_every, half, seed, device, white_roi, white_reflectance,
                   white_roi_moves, denoise, accumulate, motion, resize, view, no_disk_check):
    """Stream a plan's sequences from the rig through the device to maps, with a live status line; Ctrl-C
    stops cleanly (everything captured is processed or reported)."""
    wanted = output_list(outputs, STREAM_OUTPUTS, "stream output")  # before any loading: a typo names the valid
    if white_reflectance is not None and white_roi is None:
        raise click.UsageError("--white-reflectance needs --white-roi")
    no_clash([("--out", out)], [("--rig", rig_path), ("--plan", plan_path), ("--calib", calib), ("--scene", scene),
                                ("--delta-e-ref", ref), ("--white-reflectance", white_reflectance)])
    if out:
        lock(out, folder=True)  # one recorder per folder: a second stream into it refuses at once
        refuse_existing(out)  # before any work: a recording is never mixed with another run
    description = load_rig(rig_path)
    hardware = hardware_config(description)  # a typo in [hardware] first, before any device or file work
    bundle, plan, truth = experiment(description, plan_path, calib, scene, resize)
    colours = (plan.resolve_illuminant(illuminant, name=str(plan_path)),
               plan.resolve_observer(observer, name=str(plan_path)))
    cam = description.camera
    check_scene_covers(truth, plan, description.light.line_fwhm_nm, rig=description)
    reference = None
    if "dE" in wanted:  # default: the streamed scene itself, as fitted to the frame above
        reference = parse_reference(ref or truth, cam.roi_height, cam.roi_width, colours[0], resize,
                                    observer=colours[1], integration=integration)
    # real devices: the plan uploaded to the light, frames from the camera (a camera never waits: paced)
    driver = open_rig_driver(description, plan, hardware=hardware, scene=truth, calibration=bundle, seed=seed,
                         pacing=pacing)
    try:
        stream_run(driver, description, plan, bundle, truth, wanted, reference, out, raw_frames, plan_path, calib,
                   seconds, method, colours, pacing if hardware is None else "paced", policy, exr_every, half, seed,
                   device, white=(white_roi, white_reflectance, white_roi_moves), disk_check=not no_disk_check,
                   view=view,
                   denoise=(DENOISE_RADIUS, DENOISE_EPS) if denoise else None, accumulate=accumulate,
                   motion=motion.lower(), integration=integration)
    finally:
        if hardware is not None:
            driver.close()  # the light's USB link and the camera
