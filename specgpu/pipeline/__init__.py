"""Offline recovery, the stream (decoder / runner / sinks / report), batch (Dask), evaluation and the spectral
projector."""

from __future__ import annotations

from specgpu.pipeline.capture_folder import (
    CaptureWriter,
    SequenceFolder,
    check_capture_folder,
    read_capture,
    save_plan_and_calibration,
    write_capture,
)
from specgpu.pipeline.recovery import dark_warning, default_basis, recover, to_Lab, to_XYZ
from specgpu.pipeline.twin_capture import capture_plan
from specgpu.pipeline.moving import (
    MASK_INCONSISTENT,
    MOTION_MODES,
    TRUTH_FOLDER,
    sequence_truth,
    MotionEstimate,
    check_motion_mode,
    consistency,
    estimate_global_motion,
    inconsistent_pixels,
    truth_recorder,
)
from specgpu.pipeline.moving_layers import (
    MASK_LAYER,
    MovingRecovery,
    ObjectLayer,
    decode_object_layers,
    recover_moving,
)
from specgpu.pipeline.evaluate import (
    PatchReport,
    PixelReport,
    delta_E_per_patch,
    evaluate_XYZ,
    evaluate_pixels,
    evaluate_reflectance,
    evaluation_illuminant,
    patch_means,
    rmse_per_patch,
    scene_XYZ,
    true_patch_spectra,
    truth_cube,
)
from specgpu.pipeline.projector import (
    PROJECTOR_TARGETS,
    ProjectionReport,
    metamer_map,
    project,
    render_scene,
    rgb_led_spectrum,
    spectrum_report,
    target_spectrum,
)
from specgpu.pipeline.decoder import STREAM_OUTPUTS, StreamDecoder
from specgpu.pipeline.sinks import (
    CallbackSink,
    ExrSequenceWriter,
    PreviewSink,
    ResultsRing,
    Sink,
    StreamResult,
)
from specgpu.pipeline.stream_report import (
    LatencyHistogram,
    StreamReport,
    current_rss_bytes,
    peak_rss_bytes,
    peak_rss_reset,
)
from specgpu.pipeline.stream import Stream
from specgpu.pipeline.batch import (
    BATCH_FORMAT,
    BATCH_OUTPUTS,
    BatchJob,
    BatchReport,
    prepare_batch,
    run_batch,
)
from specgpu.pipeline.batch_output import BatchOutput, open_batch_output

__all__ = [
    "BATCH_FORMAT",
    "BATCH_OUTPUTS",
    "BatchJob",
    "BatchOutput",
    "BatchReport",
    "CallbackSink",
    "CaptureWriter",
    "ExrSequenceWriter",
    "LatencyHistogram",
    "PROJECTOR_TARGETS",
    "PatchReport",
    "PixelReport",
    "PreviewSink",
    "ProjectionReport",
    "ResultsRing",
    "STREAM_OUTPUTS",
    "SequenceFolder",
    "Sink",
    "Stream",
    "StreamDecoder",
    "StreamReport",
    "StreamResult",
    "capture_plan",
    "check_capture_folder",
    "current_rss_bytes",
    "dark_warning",
    "default_basis",
    "delta_E_per_patch",
    "evaluate_XYZ",
    "evaluate_pixels",
    "evaluate_reflectance",
    "evaluation_illuminant",
    "metamer_map",
    "open_batch_output",
    "patch_means",
    "peak_rss_bytes",
    "peak_rss_reset",
    "prepare_batch",
    "project",
    "read_capture",
    "recover",
    "MASK_INCONSISTENT",
    "MOTION_MODES",
    "TRUTH_FOLDER",
    "sequence_truth",
    "MotionEstimate",
    "MovingRecovery",
    "check_motion_mode",
    "consistency",
    "MASK_LAYER",
    "ObjectLayer",
    "decode_object_layers",
    "estimate_global_motion",
    "inconsistent_pixels",
    "recover_moving",
    "truth_recorder",
    "render_scene",
    "rgb_led_spectrum",
    "rmse_per_patch",
    "save_plan_and_calibration",
    "run_batch",
    "scene_XYZ",
    "spectrum_report",
    "target_spectrum",
    "to_Lab",
    "to_XYZ",
    "true_patch_spectra",
    "truth_cube",
    "write_capture",
]

from specgpu.pipeline.outputs import DELTA_E_KINDS, delta_E_sigma_map, recovery_metadata, recovery_writes, sigma_with_rms, stream_metadata, white_metadata  # noqa: E402, E501
from specgpu.pipeline.live import RECORD_RING_S, add_recording, recording_slots, stream_summary  # noqa: E402
from specgpu.pipeline.acquire import ZarrCapture, capture_into, keep_or_abort  # noqa: E402
from specgpu.pipeline.evaluation_report import evaluation_report, headline_line, patch_table, read_recovered  # noqa: E402, E501

__all__ += ["DELTA_E_KINDS", "delta_E_sigma_map", "recovery_metadata", "recovery_writes", "sigma_with_rms", "stream_metadata", "white_metadata", "RECORD_RING_S", "add_recording", "recording_slots", "stream_summary", "ZarrCapture", "capture_into", "keep_or_abort", "evaluation_report", "headline_line", "patch_table", "read_recovered"]  # noqa: E501

from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS, denoise_design_warning, denoise_recovery, denoised_sigma, output_subspace, sequence_guide, stream_denoise  # noqa: E402, E501
from specgpu.pipeline.accumulate import ACCUMULATED_OUTPUTS, AccumulateSink, sequence_displacement, shift_image  # noqa: E402, E501

__all__ += ["DENOISE_EPS", "DENOISE_RADIUS", "denoise_design_warning", "denoise_recovery", "denoised_sigma", "output_subspace", "sequence_guide", "stream_denoise", "ACCUMULATED_OUTPUTS", "AccumulateSink", "sequence_displacement", "shift_image"]  # noqa: E501

from specgpu.pipeline.moving_scores import RECOVERIES, compare_motion, edge_band, motion_scores  # noqa: E402

__all__ += ["RECOVERIES", "compare_motion", "edge_band", "motion_scores"]

from specgpu.pipeline.moving_decode import MOTION_OUTPUTS, MovingDecoder, check_motion_options  # noqa: E402

__all__ += ["MOTION_OUTPUTS", "MovingDecoder", "check_motion_options"]
from specgpu.pipeline.registration import (  # noqa: E402
    correlation_surface, fit_peak, second_peak_ratio, sobel_magnitude, tile_displacements, whitened_half_spectrum)

__all__ += ["correlation_surface", "fit_peak", "second_peak_ratio", "sobel_magnitude", "tile_displacements",
            "whitened_half_spectrum"]

from specgpu.pipeline.moving_flow import TileMotion, choose_flow, flow_field, tile_motion  # noqa: E402

__all__ += ["TileMotion", "choose_flow", "flow_field", "tile_motion"]

from specgpu.pipeline.reference_motion import (  # noqa: E402
    check_reference_frames, estimate_reference_motion, interpolate_in_time)

__all__ += ["check_reference_frames", "estimate_reference_motion", "interpolate_in_time"]
from specgpu.pipeline.sequence_decoder import Corrections, SequenceDecoder, check_sequence, corrections_for  # noqa: E402

__all__ += ["Corrections", "SequenceDecoder", "check_sequence", "corrections_for"]
