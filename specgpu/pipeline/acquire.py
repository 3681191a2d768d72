"""A capture of a plan's sequences on a rig (the twin or the real devices), each complete sequence handed to a
writer as it arrives: a sequence folder (:class:`~specgpu.pipeline.capture_folder.CaptureWriter`) or a zarr recording of
the raw frames (:class:`ZarrCapture`); and what a capture cut short keeps."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from specgpu.capture.motion_truth import truth_recorder
from specgpu.capture.session import capture_sequences
from specgpu.hardware.drivers import open_rig_driver
from specgpu.io.recording import ZarrRecorder, check_free_space
from specgpu.pipeline import twin_capture
from specgpu.pipeline.sinks import StreamResult

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan
    from specgpu.rig.config import RigDescription

__all__ = ["ZarrCapture", "capture_into", "keep_or_abort"]


class ZarrCapture:
    """``capture --out SEQ.zarr``: each complete sequence's raw frames committed to a zarr recording as it arrives
    (what was committed stays readable if the capture is cut short); the writer interface of CaptureWriter."""

    def __init__(self, out: str | os.PathLike[str], plan: Plan, plan_path: str | os.PathLike[str], calib, sequences,
                 sequence_bytes, metadata: dict):
        check_free_space(out, sequences * (sequence_bytes + 4096),
                         what=f"the recording ({sequences} sequences of {plan.K} raw frames)")
        self.recorder = ZarrRecorder(out, plan, outputs=(), frames=True, metadata=metadata)
        shutil.copyfile(plan_path, Path(out) / "plan.npz")
        shutil.copyfile(calib, Path(out) / "calibration.npz")

    @property
    def sequences(self) -> int:
        return self.recorder.committed

    def add(self, sequence) -> None:
        self.recorder.write(StreamResult(self.recorder.committed, sequence.cycle, sequence.frame_ids,
                                         sequence.timestamps_s, {}, 0.0, frames=sequence.frames))

    def close(self, assembly, metadata: dict | None = None) -> None:
        self.recorder.close()

    def abort(self, error=None) -> None:
        self.recorder.failed = self.recorder.failed or f"{type(error).__name__}: {error}"
        self.recorder.close()

    def keep(self, assembly, metadata: dict | None = None, *, reason: str, requested: int | None = None) -> None:
        """A capture cut short: the committed sequences stay (each was committed as it arrived)."""
        self.recorder.failed = self.recorder.failed or reason
        self.recorder.close()


def capture_into(writer, on_sequence, description: RigDescription, hardware, plan: Plan, bundle: CalibrationBundle,
                 truth, sequences, seed):
    """Capture on the twin (:func:`~specgpu.pipeline.twin_capture.capture_plan`) or the rig's devices, each complete
    sequence written as it arrives, then ``on_sequence()``; returns the capture's result."""
    # a moving twin: each sequence's truth at its reference time kept beside its frames (a sequence folder)
    record = truth_recorder(writer.directory, description, plan, truth) \
        if hardware is None and description.motion.any and hasattr(writer, "directory") else None

    def keep(sequence):
        if record is not None:
            record(writer.sequences, sequence)
        writer.add(sequence)
        on_sequence()

    if hardware is None:
        return twin_capture.capture_plan(description, plan, truth, sequences=sequences, noise_seed=seed,
                                     on_sequence=keep, calibration=bundle)
    # real devices: the same ring buffer and assembler, the plan uploaded to the light
    driver = open_rig_driver(description, plan, hardware=hardware, calibration=bundle, n_frames=plan.K * sequences)
    try:
        return capture_sequences(driver, plan.K, on_sequence=keep)
    finally:
        driver.close()


def keep_or_abort(writer, error, out, requested, meta) -> str | None:
    """A capture stopped by ``error``: keep the complete sequences already on disk (a folder is closed with them,
    marked interrupted; a zarr recording keeps what it committed); with none, remove what was written. Returns
    the line to say on stderr (None when nothing was kept)."""
    reason = "interrupted" if isinstance(error, KeyboardInterrupt) else f"{type(error).__name__}: {error}"
    kept = writer.sequences
    if not kept:
        writer.abort(error)
        return None
    try:
        writer.keep(None, meta, reason=reason, requested=requested)
    except Exception as failed:  # noqa: BLE001 (the first error is the one raised; this one is reported)
        return (f"specgpu: {kept} complete sequences are on disk in {out} but could not be indexed "
                f"({failed}); `specgpu salvage {out}` indexes them")
    return (f"specgpu: capture stopped ({reason.splitlines()[0] if reason else ''}); kept {kept} of {requested} "
            f"sequences in {out}")
