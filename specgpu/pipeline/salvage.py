"""Salvage of a capture killed outright: the complete sequences its journal records indexed into a readable
sequence folder (``specgpu salvage``)."""

from __future__ import annotations

from pathlib import Path

from specgpu import io
from specgpu.calibration.bundle import load_calibration
from specgpu.io.journal import journal_header
from specgpu.pipeline.capture_folder import CALIBRATION_FILE, INCOMPLETE_MARKER, PLAN_FILE, read_capture
from specgpu.pipeline.motion_record import renumber_truth
from specgpu.planning.plans import load_plan

__all__ = ["salvage_capture"]


def salvage_capture(directory) -> dict:
    """Make a capture folder left by a killed capture (no ``sequence.json``, its journal present) readable: index
    every complete sequence whose journal lines and frames are intact (:func:`specgpu.io.journal.salvage_sequence`),
    keep
    the plan and calibration copies, remove the interrupted marker. Returns what was kept (``sequences``,
    ``frames_kept``, ``frames_journaled``, ``left_out``: each sequence not kept and why, ``kept_sequences``,
    ``stopped``). The motion truth of a capture on a moving twin is renumbered with the sequences
    (:func:`specgpu.pipeline.motion_record.renumber_truth`).

    Verify first, commit last: the plan copy must be the plan the journal names and match the calibration copy
    before anything is written; the index written must read back as a sequence folder before the journal is
    removed. A refusal leaves the folder as it was, to be salvaged again once fixed; no frame is deleted."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: capture folder not found")
    for name in (PLAN_FILE, CALIBRATION_FILE):
        if not (directory / name).is_file():
            raise FileNotFoundError(f"{directory}: {name} is missing; the capture was killed before it was copied, "
                                    "so its frames cannot be recovered with their plan")
    plan = load_plan(directory / PLAN_FILE)
    bundle = load_calibration(directory / CALIBRATION_FILE)

    def check(doc):
        if doc["plan_hash"] != plan.hash:
            raise ValueError(f"{directory / PLAN_FILE}: is plan {plan.hash[:12]} but the frames were captured with "
                             f"plan {str(doc['plan_hash'])[:12]} (the journal says so); put that plan's file back "
                             "and salvage again")
        plan.check_calibration(bundle, name=f"{directory / PLAN_FILE}")

    check(journal_header(directory))  # before the frames are grouped in sequences of the plan's length

    def confirm():  # the index reads back; then a moving capture's truth follows its sequences' new numbers
        salvaged = read_capture(directory).meta["metadata"]["salvaged"]
        renumber_truth(directory, salvaged["kept_sequences"])

    info = io.salvage_sequence(directory, plan.K, check=check, confirm=confirm)
    (directory / INCOMPLETE_MARKER).unlink(missing_ok=True)
    return info

