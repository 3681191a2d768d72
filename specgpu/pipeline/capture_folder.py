"""The sequence folder on disk: written as a capture arrives (:class:`CaptureWriter`, :func:`write_capture`) and
read back checked (:func:`read_capture`, :func:`read_capture_header`).

A sequence folder (``specgpu capture``) holds the frames and ``sequence.json`` (:mod:`specgpu.io.sequence`), plus the
plan (``plan.npz``) and calibration bundle (``calibration.npz``) it was captured with, so ``specgpu recover``
needs nothing else; the hashes chain sequence -> plan -> calibration, and a mismatch is an error naming the
file, never a silent wrong answer.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from specgpu import io
from specgpu.calibration.bundle import CalibrationBundle, load_calibration, save_calibration
from specgpu.io.paths import atomic_path
from specgpu.planning.plans import Plan, load_plan, save_plan

__all__ = ["CALIBRATION_FILE", "INCOMPLETE_MARKER", "PLAN_FILE", "CaptureWriter", "SequenceFolder",
           "check_capture_folder", "read_capture", "read_capture_header", "save_plan_and_calibration",
           "write_capture"]

PLAN_FILE = "plan.npz"
CALIBRATION_FILE = "calibration.npz"

#: holding it is an interrupted capture that the next capture into it may replace.
INCOMPLETE_MARKER = ".specgpu-capture-incomplete"


class CaptureWriter:
    """Write a capture into a sequence folder as its sequences arrive (a long capture never holds its frames in
    memory): copies of the plan and calibration first, each frame as it comes, ``sequence.json`` last.

    The folder must be new, empty, or an interrupted capture (it holds :data:`INCOMPLETE_MARKER`); one that holds a
    sequence, or files specgpu did not put there (a user's own ``plan.npz``), is refused before anything is written
    unless ``overwrite``.

    Nothing captured is lost: each complete sequence is journaled as it is written (:meth:`add`), so a capture
    killed outright leaves a folder :func:`salvage_capture` indexes; one stopped by an error or an interrupt after
    at least one complete sequence is closed with those sequences by :meth:`keep` (its ``sequence.json`` says it was
    cut short); :meth:`abort` removes what this writer wrote, for a capture that has nothing to keep.
    ``compression``: the frames' TIFF compression (:class:`specgpu.io.sequence.SequenceWriter`'s).
    """

    def __init__(self, directory, plan_path, calibration_path, *, overwrite: bool = False, compression: str = "zip"):
        directory = self.directory = Path(directory)
        self.plan = load_plan(plan_path)
        check_capture_folder(directory, overwrite=overwrite)
        self._created = not directory.exists()
        directory.mkdir(parents=True, exist_ok=True)
        self.marker = directory / INCOMPLETE_MARKER
        (directory / "sequence.json").unlink(missing_ok=True)  # overwrite: never complete while rewritten
        self.marker.write_text(f"an interrupted specgpu capture (pid {os.getpid()}); `specgpu salvage` indexes "
                               "its complete sequences, a capture into this folder replaces it\n", encoding="utf-8")
        self._copies = []
        for source, name in ((plan_path, PLAN_FILE), (calibration_path, CALIBRATION_FILE)):
            with atomic_path(directory / name) as tmp:
                shutil.copyfile(source, tmp)
            self._copies.append(directory / name)
        self.frames = io.SequenceWriter(directory, self.plan.hash, overwrite=True,
                                        journal={"plan_method": self.plan.method, "K": self.plan.K},
                                        compression=compression)
        self.sequences = 0

    def add(self, sequence) -> None:
        """Write one complete sequence (a :class:`specgpu.capture.assemble.Sequence`) and journal it."""
        for frame, record in zip(sequence.frames, sequence.frame_records()):
            self.frames.add(frame, record)
        self.frames.commit()
        self.sequences += 1

    def keep(self, assembly, metadata=None, *, reason: str, requested: int | None = None) -> Path:
        """Close a capture cut short (``reason``: what stopped it) with the complete sequences written so far;
        the frames of a sequence it was writing are removed; ``assembly`` may be None (the counters died with
        the capture). ``sequence.json`` records ``interrupted`` (the reason) and ``sequences_requested``."""
        self.frames.truncate(self.sequences * self.plan.K)
        meta = {**(metadata or {}), "interrupted": reason}
        if requested is not None:
            meta["sequences_requested"] = int(requested)
        return self.close(assembly, meta)

    def close(self, assembly, metadata=None) -> Path:
        """Write ``sequence.json`` (with the assembler's counters) and remove the marker: the folder is complete."""
        if not self.sequences:
            raise ValueError(f"{self.directory}: no complete sequence was captured ({assembly.as_dict()})")
        meta = {"plan_method": self.plan.method, "K": self.plan.K, "sequences": self.sequences,
                "assembly": None if assembly is None else assembly.as_dict(), **(metadata or {})}
        self.frames.close(meta)
        self.marker.unlink(missing_ok=True)
        return self.directory

    def abort(self, error=None) -> None:
        """Remove the frames, copies and marker written (and the folder, when this writer created it); ``error``,
        what cut the capture short, is the caller's to report."""
        self.frames.abort()
        for path in (*self._copies, self.marker):
            path.unlink(missing_ok=True)
        if self._created:
            try:
                self.directory.rmdir()
            except OSError:
                pass



def check_capture_folder(directory, *, overwrite: bool = False) -> None:
    """Refuse, in one line, a capture folder that is not new, empty or an interrupted capture."""
    directory = Path(directory)
    if not directory.exists():
        return
    if not directory.is_dir():
        raise ValueError(f"{directory}: exists and is not a folder")
    if overwrite:
        return
    if (directory / "sequence.json").exists():
        raise FileExistsError(f"{directory} already holds a sequence (sequence.json); choose another --out")
    if (directory / INCOMPLETE_MARKER).exists():
        return  # an interrupted capture: replaced
    others = sorted(p.name for p in directory.iterdir() if not p.name.startswith("."))
    if others:
        shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
        raise FileExistsError(f"{directory} holds files a capture would overwrite or mix with ({shown}); "
                              "choose a new or empty folder")


def write_capture(directory, sequences, assembly, plan_path, calibration_path, *, metadata=None,
                  overwrite: bool = False, compression: str = "zip") -> Path:
    """Write complete sequences (from :func:`capture_plan`) into a sequence folder with copies of the plan and
    calibration; ``assembly`` is the assembler's counters, kept in ``sequence.json``; ``compression``: the frames'
    TIFF compression (:data:`specgpu.io.sequence.TIFF_COMPRESSIONS`).

    The plan and calibration are copied first and ``sequence.json`` is written last, so an interrupted write
    never leaves a folder that reads as complete (see :class:`CaptureWriter`, which this uses).
    """
    directory = Path(directory)
    if not sequences:
        raise ValueError(f"{directory}: no complete sequence was captured ({assembly.as_dict()})")
    writer = CaptureWriter(directory, plan_path, calibration_path, overwrite=overwrite, compression=compression)
    try:
        for sequence in sequences:
            writer.add(sequence)
        return writer.close(assembly, metadata)
    except BaseException:
        writer.abort()
        raise



@dataclass
class SequenceFolder:
    """A sequence folder read back and checked: frames (S, K, H, W), the plan and calibration, records, meta."""

    path: Path
    frames: np.ndarray
    plan: Plan
    calibration: CalibrationBundle
    records: list
    meta: dict

    @property
    def sequences(self) -> int:
        return self.frames.shape[0]


def _zarr_not_a_sequence(directory: Path) -> str:
    """The refusal of a zarr recording where a sequence folder is read: say what it is and what reads it."""
    try:
        attrs = json.loads((directory / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        attrs = {}
    if attrs.get("format") != "specgpu.recording":
        return f"{directory}: a zarr store, not a sequence folder (sequence.json); recover reads capture folders"
    if attrs.get("frames"):
        return (f"{directory}: a zarr recording, not a sequence folder; re-process its raw frames with "
                f"`specgpu batch {directory} --plan PLAN --out OUT.zarr` (recover reads capture folders)")
    return (f"{directory}: a zarr recording without raw frames, not a sequence folder; its results are in it "
            "(specgpu.io.recording.open_recording, or xarray.open_zarr), and recover reads capture folders")


def read_capture(directory) -> SequenceFolder:
    """Read a sequence folder; refuse it when the plan or calibration is missing or does not match its hashes,
    or when its frames are not whole sequences in pattern order.

    Parameters
    ----------
    directory : path
        A sequence folder written by ``specgpu capture`` (or :func:`write_capture`).

    Returns
    -------
    SequenceFolder
        Its frames (S, K, H, W), plan, calibration, frame records and metadata.

    Examples
    --------
    Two sequences of 7 Hadamard-coded frames, written as a capture folder and read back:

    >>> import tempfile
    >>> from pathlib import Path
    >>> from specgpu import calibration, pipeline, planning, rig
    >>> twin = rig.RigDescription(camera=rig.CameraParameters(roi_width=320, roi_height=240))
    >>> cal = calibration.oracle_calibration(twin)
    >>> root = Path(tempfile.mkdtemp())
    >>> codes = planning.make_plan("hadamard", cal, bands=7)
    >>> shot = pipeline.capture_plan(twin, codes, rig.natural_scene(240, 320), sequences=2, noise_seed=5,
    ...                              calibration=cal)
    >>> plan_file, cal_file = pipeline.save_plan_and_calibration(root, codes, cal)
    >>> folder = pipeline.write_capture(root / "capture", shot.sequences, shot.assembly, plan_file, cal_file)
    >>> pipeline.read_capture(folder).frames.shape
    (2, 7, 240, 320)
    """
    directory = Path(directory)
    _check_not_zarr(directory)
    _check_interrupted(directory)
    frames, records, meta = io.read_sequence(directory)
    plan, bundle = _capture_plan(directory, records, meta)
    return SequenceFolder(directory, frames.reshape(-1, plan.K, *frames.shape[1:]), plan, bundle, records, meta)


def read_capture_header(directory) -> tuple[list, dict, Plan, CalibrationBundle]:
    """What :func:`read_capture` checks, without reading a pixel: ``(records, meta, plan, calibration)`` of a
    sequence folder (``sequence.json`` validated, the plan and calibration matching it, whole sequences in pattern
    order). The frames are then read per sequence (:func:`specgpu.io.sequence.read_frames`), so a reader's memory does
    not grow with the capture."""
    directory = Path(directory)
    _check_not_zarr(directory)
    _check_interrupted(directory)
    records, meta = io.read_sequence_header(directory)
    plan, bundle = _capture_plan(directory, records, meta)
    return records, meta, plan, bundle


def _check_not_zarr(directory: Path) -> None:
    if (directory / "zarr.json").is_file() and not (directory / io.SEQUENCE_FILE).exists():
        raise ValueError(_zarr_not_a_sequence(directory))


def _check_interrupted(directory: Path) -> None:
    if (directory / INCOMPLETE_MARKER).exists() and not (directory / io.SEQUENCE_FILE).exists():
        salvage = (" `specgpu salvage DIR` indexes its complete sequences;"
                   if (directory / io.JOURNAL_FILE).exists() else "")
        raise ValueError(f"{directory}: an interrupted capture (no sequence.json);{salvage} capture again into it "
                         "to replace it, or delete it")


def _capture_plan(directory: Path, records, meta) -> tuple[Plan, CalibrationBundle]:
    """The plan and calibration stored in a sequence folder, checked against its ``sequence.json``."""
    for name in (PLAN_FILE, CALIBRATION_FILE):
        if not (directory / name).is_file():
            raise FileNotFoundError(f"{directory}: {name} is missing; capture with `specgpu capture` (it stores "
                                    "the plan and calibration beside the frames)")
    plan = load_plan(directory / PLAN_FILE)
    recorded = meta.get("plan_hash", "")
    if plan.hash != recorded:
        raise ValueError(f"{directory}: the frames were captured with plan {recorded[:12] or '(none)'} but "
                         f"{PLAN_FILE} is plan {plan.hash[:12]}")
    bundle = load_calibration(directory / CALIBRATION_FILE)
    plan.check_calibration(bundle, name=f"{directory / PLAN_FILE}")
    K = plan.K
    indices = np.array([r["pattern_index"] for r in records])
    if len(indices) % K or not np.array_equal(indices, np.tile(np.arange(K), len(indices) // K)):
        raise ValueError(f"{directory}: frames are not whole sequences of the plan's {K} patterns in order")
    return plan, bundle



def save_plan_and_calibration(directory, plan: Plan, bundle: CalibrationBundle) -> tuple[Path, Path]:
    """Save a plan and its calibration into ``directory`` (the demo's report folder)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    calibration_path = directory / CALIBRATION_FILE
    plan_path = directory / f"plan-{plan.method}.npz"
    save_calibration(calibration_path, bundle)
    save_plan(plan_path, plan)
    return plan_path, calibration_path
