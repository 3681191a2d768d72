"""``specgpu capture`` and ``specgpu salvage``: sequences of a plan captured on the rig into a sequence folder
(or a zarr recording of the raw frames), and the complete sequences of a killed capture indexed."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from tqdm import tqdm

from specgpu.apps.cli.group import kept
from specgpu.apps.cli.options import PLAN, RESIZE, RIG, SCENE, command, experiment, lock, no_clash
from specgpu.hardware.drivers import hardware_config
from specgpu.io import SEQUENCE_FILE
from specgpu.io.recording import refuse_existing
from specgpu.pipeline import acquire
from specgpu.pipeline.capture_folder import CaptureWriter, check_capture_folder
from specgpu.pipeline.salvage import salvage_capture
from specgpu.rig.config import load_rig


def open_writer(out, plan, plan_path, calib, sequences, description, meta):
    """The writer of ``--out``, its lock held: a zarr recording of the raw frames for a name ending in .zarr
    (one chunk per sequence), else a sequence folder; frames go to disk as they come, never all held in memory."""
    cam = description.camera
    if str(out).lower().rstrip("/").endswith(".zarr"):
        lock(out, folder=True)  # first: a killed capture's stale lock is cleared even when out is refused
        refuse_existing(out)
        return acquire.ZarrCapture(out, plan, plan_path, calib, sequences,
                                   plan.K * cam.roi_height * cam.roi_width * 2, meta)
    check_capture_folder(out)  # a folder holding a sequence or someone's files: refused before the capture
    lock(out, folder=True)
    return CaptureWriter(out, plan_path, calib)


def run_capture(writer, out, description, hardware, plan, bundle, truth, sequences, seed, meta):
    """Capture into ``writer`` with a progress bar; a capture cut short keeps its complete sequences (said on
    stderr) and re-raises."""
    try:
        with tqdm(total=sequences, desc="capturing", unit="seq", leave=False, file=sys.stderr) as bar:
            result = acquire.capture_into(writer, bar.update, description, hardware, plan, bundle, truth,
                                          sequences, seed)
        writer.close(result.assembly, metadata=meta)
    except BaseException as error:
        said = acquire.keep_or_abort(writer, error, out, sequences, meta)
        if said and isinstance(error, KeyboardInterrupt) and "; kept " in said:  # said in the interrupt's line
            kept(out, said.split("; kept ", 1)[1])
        elif said:
            click.echo(said, err=True)
        raise
    return result


@command()
@RIG
@PLAN
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False),
              help="The calibration the plan was made from (stored with the frames for recovery).")
@SCENE
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Sequence folder to write; a name ending in .zarr writes a zarr recording of the raw frames "
                   "instead (for specgpu batch).")
@click.option("--sequences", type=click.IntRange(min=1), default=1, show_default=True,
              help="Sequences of the plan to capture (K frames each).")
@click.option("--seed", type=click.IntRange(min=0, max=2**63 - 1), default=None,
              help="Seed of the frames' temporal noise.")
@RESIZE
def capture(rig_path, plan_path, calib, scene, out, sequences, seed, resize):
    """Capture sequences of a plan on the rig (the twin by default) into a sequence folder."""
    no_clash([("--out", out)], [("--rig", rig_path), ("--plan", plan_path), ("--calib", calib), ("--scene", scene)])
    description = load_rig(rig_path)
    hardware = hardware_config(description)  # a typo in [hardware] first, before any device or file work
    bundle, plan, truth = experiment(description, plan_path, calib, scene, resize)
    cam = description.camera
    meta = {"scene": truth.name, "rig": rig_path or "<paper defaults>",
            **({"scene_resampled": truth.resampled} if truth.resampled else {})}
    writer = open_writer(out, plan, plan_path, calib, sequences, description, meta)
    result = run_capture(writer, out, description, hardware, plan, bundle, truth, sequences, seed, meta)
    a = result.assembly
    click.echo(f"{writer.sequences} sequences of {plan.K} frames ({truth.name}, {cam.roi_width} x "
               f"{cam.roi_height}); dropped {a.dropped}, duplicated {a.duplicates}, missed triggers "
               f"{a.missed_triggers}, discarded {a.sequences_discarded}; wrote {out}")


@command()
@click.argument("seq", type=click.Path(exists=True, file_okay=False))
def salvage(seq):
    """Index the complete sequences of a capture folder whose capture was killed (kill -9, a crash, power loss).

    Each sequence a capture writes is journaled as it arrives; this checks every journal line and journaled frame
    against its checksum and writes sequence.json for every complete, intact sequence (marked salvaged, with the
    sequences left out and why). No frame is deleted, and the journal only once the index reads back: a refused
    salvage can be run again.
    """
    # salvage writes the folder's own index, by design; named as an output so an interrupt says if it was written
    no_clash([("SEQ's index", Path(seq) / SEQUENCE_FILE)])
    lock(seq, folder=True)  # not while a capture is still writing into it
    info = salvage_capture(seq)
    for gone in info["left_out"]:
        click.echo(f"specgpu: sequence {gone['sequence']} ({gone['first_file']} to {gone['last_file']}) left out: "
                   f"{gone['reason']}", err=True)
    rest = (f"; left out {len(info['left_out'])} of {info['sequences_journaled']} journaled sequences (listed "
            "above and in sequence.json)" if info["left_out"] else "")
    if info["frames_unindexed"]:
        rest += f"; {info['frames_unindexed']} frame file(s) outside the index left in place"
    click.echo(f"salvaged {info['sequences']} sequences ({info['frames_kept']} of {info['frames_journaled']} "
               f"journaled frames) in {seq}{rest}")

