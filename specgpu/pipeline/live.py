"""A recording stream's set-up and summary (``specgpu stream --out``): the frame ring sized to ride out a loaded
disk, the free-space and write-rate checks before any frame, the zarr recorder with the plan and calibration
copied beside it, the EXR maps and the preview; and the one-line summary of a run."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

from specgpu.io.recording import (
    ZarrRecorder,
    check_free_space,
    check_write_rate,
    expected_sequences,
    sequence_bytes,
)
from specgpu.pipeline.outputs import DELTA_E_KINDS
from specgpu.pipeline.sinks import ExrSequenceWriter, PreviewSink

__all__ = ["RECORD_RING_S", "add_recording", "behind_text", "recording_slots", "stream_summary"]

#: Seconds of frames the frame ring of a recording stream holds.
RECORD_RING_S = 2.0


def recording_slots(plan, description) -> int:
    """Frame-ring slots of a recording stream: a recording keeps every frame rather than the least latency, so a
    ring of 2 s of frames rides out the stalls of a loaded machine or disk (the default ring, 4 sequences, favours
    latency)."""
    rate = plan.rig_description(description).camera.frame_rate_hz
    return max(4 * plan.K, 16, math.ceil(RECORD_RING_S * rate))


def add_recording(stream, plan, description, out, *, wanted, raw_frames, plan_path, calib, seconds, policy, meta,
                  exr_every,
                  method, colours, disk_check=True):
    """Check the disk, open the zarr recorder of ``out`` and append it (and the EXR maps, the preview) to the
    stream's sinks; returns the recorder."""
    cam = description.camera
    illuminant, observer = colours
    frame_rate = plan.rig_description(description).camera.frame_rate_hz
    n_expected = expected_sequences(seconds, frame_rate, plan.K)
    per_sequence = sequence_bytes(stream.decoder.shapes(), frames_shape=(plan.K, cam.roi_height,
                                                                         cam.roi_width) if raw_frames else None)
    check_free_space(out, n_expected * per_sequence,
                     what=f"the recording ({n_expected} sequences x {per_sequence / 1e6:.1f} MB)")
    disk_rate = None
    if disk_check:
        # before any frame: a disk slower than the recording makes a camera that never waits drop frames
        # (a blocking ring only slows the run down, so there the probe only chooses the compression)
        # (large chunks bypass the system's write buffer: what can wait is the stream's frame ring)
        per_s = frame_rate / plan.K
        disk_rate = check_write_rate(
            out, per_sequence * per_s, seconds if policy != "block" else 0.0,
            what=f"the recording ({per_sequence / 1e6:.1f} MB a sequence x {per_s:.1f} sequences/s)",
            buffer_bytes=RECORD_RING_S * per_sequence * per_s)
    writer = ZarrRecorder(out, plan, frames=raw_frames, basis=stream.decoder.basis, metadata=meta,
                          disk_rate=disk_rate)
    shutil.copyfile(plan_path, Path(out) / "plan.npz")  # what batch re-processes the frames with
    shutil.copyfile(calib, Path(out) / "calibration.npz")
    stream.sinks.append(writer)
    if exr_every:
        stream.sinks.append(ExrSequenceWriter(Path(out) / "exr", wavelengths=plan.output_wavelengths,
                                              every=exr_every, dE_kind=DELTA_E_KINDS.get(method, "dE2000"),
                                              metadata=meta, output_labels=plan.output_labels))
    if "XYZ" in wanted:
        stream.sinks.append(PreviewSink(Path(out) / "preview.png", illuminant=illuminant, observer=observer,
                                        white=stream.decoder.white))
    return writer


def behind_text(rate_hz, plan_rate_hz) -> str:
    """How far a source that falls behind the plan is, both rates in frames/s."""
    return f"behind the plan: frames delivered at {rate_hz:.0f}/s, the plan's rate is {plan_rate_hz:.0f}/s"


def stream_summary(report, out=None, writer=None) -> str:
    """The one line a finished stream prints: frames in, sequences out, drops, latency, a source behind the plan's
    frame rate, the optional sinks stopped, what was written."""
    a = report.assembly
    return (f"{report.frames_in} frames in ({report.frames_per_s:.0f}/s), {report.sequences_out} sequences out "
            f"({report.sequences_per_s:.1f}/s); dropped {a.dropped} (ring {report.ring.dropped}), duplicated "
            f"{a.duplicates}, missed triggers {a.missed_triggers}, discarded {a.sequences_discarded}; latency "
            f"median {report.latency_ms(50):.1f} ms, p99 {report.latency_ms(99):.1f} ms"
            + (" (interrupted)" if report.interrupted else "")
            + (f"; {behind_text(report.frame_rate_hz, report.plan_frame_rate_hz)}" if report.behind else "")
            + "".join(f"; {line}" for line in report.sinks_stopped)
            + (f"; wrote {out} ({writer.committed} sequences)" if out and not report.sink_errors else ""))
