"""Public names of :mod:`specgpu.pipeline`, loaded lazily by its ``__init__`` (and read by type checkers)."""

from .accumulate import AccumulateSink
from .acquire import ZarrCapture, capture_into
from .batch import BATCH_FORMAT, BATCH_OUTPUTS, BatchJob, BatchReport, prepare_batch, run_batch
from .batch_output import BatchOutput, open_batch_output
from .capture_folder import SequenceFolder, read_capture, write_capture
from .decoder_outputs import STREAM_OUTPUTS
from .denoise import denoise_recovery
from .evaluate import PatchReport, PixelReport, evaluate_pixels, evaluate_reflectance, evaluate_XYZ
from .evaluation_report import evaluation_report
from .moving_layers import MovingRecovery, recover_moving
from .projector import PROJECTOR_TARGETS, ProjectionReport, metamer_map, project, render_scene
from .recovery import recover
from .sequence_decoder import SequenceDecoder, corrections_for
from .sinks import CallbackSink, ExrSequenceWriter, PreviewSink, Sink, StreamResult
from .stream import Stream
from .stream_report import StreamReport
from .twin_capture import capture_plan

__all__ = [
    "AccumulateSink",
    "BATCH_FORMAT",
    "BATCH_OUTPUTS",
    "BatchJob",
    "BatchOutput",
    "BatchReport",
    "corrections_for",
    "CallbackSink",
    "capture_into",
    "capture_plan",
    "denoise_recovery",
    "evaluate_pixels",
    "evaluate_reflectance",
    "evaluate_XYZ",
    "evaluation_report",
    "ExrSequenceWriter",
    "metamer_map",
    "MovingRecovery",
    "open_batch_output",
    "PatchReport",
    "PixelReport",
    "prepare_batch",
    "PreviewSink",
    "project",
    "ProjectionReport",
    "PROJECTOR_TARGETS",
    "read_capture",
    "recover",
    "recover_moving",
    "render_scene",
    "run_batch",
    "SequenceDecoder",
    "SequenceFolder",
    "Sink",
    "Stream",
    "STREAM_OUTPUTS",
    "StreamReport",
    "StreamResult",
    "write_capture",
    "ZarrCapture",
]
