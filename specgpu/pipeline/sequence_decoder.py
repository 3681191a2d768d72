"""The decoding of one sequence, written once: the corrections a (calibration, plan) pair calls for, then the
linear or the warped pass, then the outputs.

:func:`corrections_for` decides, once, what a calibration and a plan ask of the frames before the decoder
(:class:`Corrections`): the level subtracted (the calibration's dark at the plan's exposure, or the plan's ambient
frame), the sensor's linearisation, the per-pattern flat field and a reference white.
:class:`SequenceDecoder` is the one decoder: it applies them and runs the pass, and every command decodes through
it. Without outputs named it makes the plan's outputs of a sequence folder (``pipeline.recover`` and
:func:`~specgpu.pipeline.recovery.uncertainty`, so the report and the viewer); given outputs
(:func:`specgpu.pipeline.decoder_outputs.outputs_for`, decided once for every mode) it is the stream's and the
batch's decoder: device-resident (the plan's composed matrices, dark, gain and noise maps on the device once, fused
launches per sequence: :class:`specgpu.pipeline.decoder_outputs.FusedLaunches`), or, for a scene that moves, the
warped pass with those outputs' rows stacked (:meth:`SequenceDecoder.maps`).

Frames corrected on the host are handed to the linear map as the signal above the level, with no dark: the level
is subtracted once. The motion estimate, the warped pass and the noise model read the corrected frames on the
sensor's scale (:meth:`Corrections.sensor`): they compare samples with the sensor's maximum code and model the
dark level's own noise. A plan's ambient frame is subtracted there in the warped pass, at the samples
(:meth:`Corrections.moving`), not from the frames' fixed pixels.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
from numpy.typing import ArrayLike

from specgpu import engine
from specgpu.core.mask import Mask
from specgpu.core.numerics import live_gain
from specgpu.core.validate import check_sequence, validate_method
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.runtime import get_allocator, get_queue
from specgpu.engine.warped_variance import PreparedWarpedVariance
from specgpu.motion.residual import residual_check
from specgpu.pipeline.decoder_outputs import ColourLaunch, FusedLaunches, lab_and_delta_E, outputs_for
from specgpu.pipeline.denoise import (
    PARTS_MADE_HERE,
    compensated_parts,
    denoise_compensated,
    warped_guide_row,
)
from specgpu.pipeline.moving_decode import check_motion_options, warped_uncertainty
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.planning.correction import (
    WhiteReference,
    ambient_index,
    corrected_decoder,
    subtracting_ambient,
    white_gains,
)
from specgpu.planning.noise import NoiseModel
from specgpu.planning.reference_frames import reference_indices
from specgpu.planning.uncertainty import delta_E_sigma

__all__ = ["Corrections", "SequenceDecoder", "WHITE_MOVES", "check_sequence", "corrections_for", "motion_model"]

#: Where a reference white is measured in a motion-compensated decoding (``--white-roi-moves``): on the warped
#: samples at the reference time (a white that moves with the scene) or on the fixed sensor pixels (a white fixed
#: in the field while the scene moves).
WHITE_MOVES = ("scene", "camera")


def motion_model(mode: str) -> str:
    """The estimator's model of a motion mode (``"global"``: one translation per frame)."""
    return "translation" if mode == "global" else mode


@dataclass(frozen=True, eq=False)
class Corrections:
    """What a (calibration, plan) pair asks of a sequence's frames before the decoder (:func:`corrections_for`).

    Attributes
    ----------
    calibration : specgpu.calibration.bundle.CalibrationBundle
    dark : ndarray, (H, W) float32
        The calibration's dark level at the plan's exposure.
    ambient : int or None
        The plan's ambient frame, subtracted instead of ``dark``.
    ratio : ndarray, (K, H, W) float32, or None
        The per-pattern flat-field ratio (:meth:`CalibrationBundle.flat_ratio`).
    linearize : bool
        The calibration measured the sensor's compression (:meth:`CalibrationBundle.linearize`).
    white_roi, white_reflectance
        A reference white in the field (each sequence's decoder rescaled for the light's drift), or None.
    """

    calibration: object
    dark: np.ndarray
    ambient: int | None
    ratio: np.ndarray | None
    linearize: bool
    white_roi: object = None
    white_reflectance: object = None

    @property
    def host(self) -> bool:
        """The frames need correcting on the host before the linear map (anything beyond a dark level and a
        per-pixel gain, which the kernels apply)."""
        return self.ratio is not None or self.ambient is not None or self.linearize

    @property
    def per_sequence(self) -> bool:
        """Each sequence is decoded on its own, then averaged: its level (an ambient frame) or its decoder (a
        reference white's gains) is its own."""
        return self.ambient is not None or self.white_roi is not None

    def level(self, raw) -> np.ndarray:
        """(H, W) float32 level subtracted from the sequence ``raw`` (K, H, W): its ambient frame, or the dark."""
        return np.asarray(raw[self.ambient], np.float32) if self.ambient is not None else self.dark

    def signal(self, raw, level=None) -> np.ndarray:
        """(K, H, W) float32 signal above ``level`` (default :meth:`level`), linearised and multiplied by the
        per-pattern flat ratio: what the decoder maps."""
        level = self.level(raw) if level is None else level
        f = np.asarray(raw, np.float32) - np.asarray(level, np.float32)[None]
        if self.linearize:
            f = np.asarray(self.calibration.linearize(f), np.float32)
        if self.ratio is not None:
            f *= self.ratio
        return f

    def sensor(self, raw, level=None) -> np.ndarray:
        """The corrected frames on the sensor's scale (:meth:`signal` above ``level``, the level kept), for the
        passes that compare samples with the sensor's maximum code or model the level's own noise; ``raw`` itself
        when nothing is corrected on the host."""
        if not self.host and level is None:
            return np.asarray(raw)
        level = self.level(raw) if level is None else level
        f = self.signal(raw, level)
        f += np.asarray(level, np.float32)[None]
        return f

    def moving(self, raw) -> np.ndarray:
        """The corrected frames on the sensor's scale as the warped pass reads them (:meth:`sensor`): with an
        ambient frame, above the calibration's dark rather than above the ambient frame, which the scene moves
        across: the pass samples the ambient frame where it saw each pixel and subtracts it there
        (:func:`specgpu.planning.correction.subtracting_ambient`)."""
        return self.sensor(raw, None if self.ambient is None else self.dark)


def corrections_for(calibration, plan, *, white_roi=None, white_reflectance=None) -> Corrections:
    """The corrections ``calibration`` and ``plan`` call for (the one place that decides them).

    Parameters
    ----------
    calibration : specgpu.calibration.bundle.CalibrationBundle
    plan : specgpu.planning.plans.Plan
    white_roi, white_reflectance : optional
        A reference white in the field (``--white-roi``, ``--white-reflectance``).

    Returns
    -------
    Corrections
    """
    if white_reflectance is not None and white_roi is None:
        raise ValueError("--white-reflectance needs --white-roi")
    return Corrections(calibration=calibration, dark=np.asarray(calibration.dark_at(plan.exposure_s), np.float32),
                       ambient=ambient_index(plan), ratio=calibration.flat_ratio(plan.patterns),
                       linearize=calibration.reports.get("linearity_c_per_dn2", 0.0) > 0,
                       white_roi=white_roi, white_reflectance=white_reflectance)


class SequenceDecoder:
    """The decoding of a plan's sequences: the corrections (:func:`corrections_for`), then the linear map or,
    for a scene that moved, the warped pass with the motion estimated within the sequence, then the outputs.

    Three modes, one object: without ``outputs``, :meth:`decode` gives the plan's outputs of a sequence folder
    (``recover``); with ``outputs`` and no motion, the device-resident decoder of the stream and the batch
    (:meth:`enqueue` on a sequence's device frames, :meth:`maps` for host frames); with ``outputs`` and a motion
    mode, :meth:`maps` decodes each sequence through the warped pass.

    Parameters
    ----------
    plan : specgpu.planning.plans.Plan
    calibration : specgpu.calibration.bundle.CalibrationBundle
    outputs : sequence of str, optional
        The maps made of each sequence (:func:`specgpu.pipeline.decoder_outputs.outputs_for`; with a motion mode,
        of :data:`specgpu.pipeline.moving_decode.MOTION_OUTPUTS`).
    white_roi, white_reflectance : optional
        A reference white in the field (as :func:`specgpu.pipeline.recovery.recover`): with ``outputs`` each
        sequence's decoder is rescaled for the light's drift (:class:`specgpu.planning.correction.WhiteReference`)
        and every launch gets its matrix from the corrected decoder (:meth:`matrices`). With a motion mode the
        warped pass samples every frame, the white is measured as ``white_moves`` says
        (:meth:`motion_white_gains`) and the sequence's corrected decoder applied to the samples.
    white_moves : {"scene", "camera"}
        With a motion mode and ``white_roi``: the white moves with the scene (measured on the warped samples at
        the reference time, the ROI in the reference frame's coordinates) or is fixed in the field (measured on
        the raw pixels).
    motion : {"none", "global", "affine", "flow"}
        How the scene's motion within a sequence is compensated (:data:`specgpu.motion.methods.MOTION_METHODS`).
    device : optional
        OpenCL device selector or queue.
    frame_shape : (int, int), optional
        (H, W) of the frames; default the calibration's.
    reference, method, illuminant, observer, integration, cube_dtype, denoise
        Of the outputs (:func:`specgpu.pipeline.decoder_outputs.outputs_for`).
    """

    def __init__(self, plan, calibration, outputs=(), *, white_roi=None, white_reflectance=None, white_moves="scene",
                 motion: str = "none",
                 device=None, frame_shape=None, reference=None, method: str = "CIE 2000", illuminant=None,
                 observer=None, integration: str = "rectangle", cube_dtype=np.float32, denoise=None):
        self.plan, self.calibration, self.device = plan, calibration, device
        self._variance = None  # the motion mode's sigma set-up on the device, made on first use (variance_launch)
        self.corrections = corrections_for(calibration, plan, white_roi=white_roi,
                                           white_reflectance=white_reflectance)
        # every option that cannot be motion-compensated refused before any work, alike in every mode
        self.motion = check_motion_options(motion, plan, outputs=outputs)
        #: (radius, eps) of the guided filter, or None; in the motion mode its guide is the warped frames' sum
        self.denoise = None if denoise is None else (int(denoise[0]), float(denoise[1]))
        self.gain = calibration.flat_field
        if self.motion != "none":
            self.model = motion_model(self.motion)
            self.reference_frames = reference_indices(plan)  # the motion from them where the plan has them
            self.residual = residual_check(plan, calibration)  # samples judged against the plan's model
        self.white_moves = validate_method(white_moves, {m: m for m in WHITE_MOVES}, "--white-roi-moves")
        #: the reference white of the motion mode (parsed and checked now), or None
        self.white_motion = (None if self.motion == "none" or white_roi is None else
                             WhiteReference(plan, calibration, white_roi, white_reflectance,
                                            frame_shape=np.shape(self.corrections.dark) if frame_shape is None
                                            else frame_shape))
        self._white_base = None  # the white's pass rows for the plan's decoder, made on first use (white_rows)
        self.spec = self.fused = None
        if not outputs:
            return
        shape = np.shape(self.corrections.dark) if frame_shape is None else frame_shape
        self.height, self.width = (int(v) for v in shape)
        self.n, self.K = self.height * self.width, plan.K
        self.spec = outputs_for(plan, outputs, frame_shape=(self.height, self.width), reference=reference,
                                method=method, illuminant=illuminant, observer=observer, integration=integration,
                                cube_dtype=cube_dtype, denoise=denoise)
        self.outputs = self.spec.names
        self.queue = get_queue(device)
        if self.motion == "none":
            # the white reference: parsed and checked now (an ROI outside the frame is refused before any work)
            white = (None if white_roi is None else
                     WhiteReference(plan, calibration, white_roi, white_reflectance, frame_shape=shape))
            self.fused = FusedLaunches(plan, self.spec, calibration, self.corrections, frame_shape=shape,
                                       queue=self.queue, white_reference=white)
            return
        # the motion mode: the outputs' linear rows decoded in one warped pass, Lab and dE from its XYZ
        self.rows, self.slices = self.pass_rows(), self.spec.rows()[1]
        if self.denoise is not None:  # the guide: one more row of the same warped pass
            self.slices["guide"] = slice(len(self.rows) - 1, len(self.rows))
        self._reference = (None if self.spec.reference is None else
                           engine.to_device(self.queue, self.spec.reference.reshape(-1)))
        self._colour_launch = None  # Lab and dE of the warped (filtered) XYZ: one launch, made on first use
        #: host seconds spent so far in each step (estimate, warped pass, consistency check with the object
        #: layers, colour), and the sequences decoded: where a moving stream's time goes
        self.seconds = dict.fromkeys(("estimate", "warp", "check", "colour"), 0.0)
        self.sequences = 0
        self._lock = threading.Lock()  # maps may run on several threads at once (the stream's)

    # ------------------------------------------------------------------------------ what the outputs look like
    @property
    def basis(self):
        """The plan's output basis U (B, m) of the ``coefficients`` output, or None."""
        return None if self.spec is None else self.spec.basis

    @property
    def white(self):
        """The white XYZ of Lab and dE, or None without a colour output."""
        return None if self.spec is None else self.spec.white

    @property
    def white_reference(self):
        """The reference white's per-sequence correction of the device-resident mode, or None."""
        return None if self.fused is None else self.fused.white_reference

    @property
    def precorrect(self) -> bool:
        """The frames are corrected on the host (:meth:`prepare_frames`) before the device launches."""
        return self.fused is not None and self.fused.precorrect

    @property
    def frames_dtype(self):
        """What the launches read: float32 when :meth:`prepare_frames` corrects the frames first, else None (the
        raw frames)."""
        return None if self.fused is None else self.fused.frames_dtype

    def shapes(self) -> dict[str, tuple[tuple, np.dtype]]:
        """Per output: its (H, W, C) or (H, W) shape and dtype; plus ``mask`` (H, W) uint8, bit 1 = saturated."""
        return self.spec.shapes(self.height, self.width)

    def device_shapes(self) -> dict[str, tuple[tuple, np.dtype]]:
        """The maps read back from the device (:meth:`shapes`); :meth:`enqueue` may return more buffers (those
        ``dE_sigma`` is computed from), which stay on the device."""
        return self.shapes()

    # -------------------------------------------------------------------------- the device-resident launches
    def _device(self) -> FusedLaunches:
        if self.fused is None:
            raise ValueError("the device launches need outputs and no motion mode (a moving scene is decoded "
                             "by maps)")
        return self.fused

    def prepare_frames(self, raw: ArrayLike) -> np.ndarray:
        """(K, H, W) float32 frames for the launches when they need host-side corrections (:attr:`precorrect`;
        :meth:`specgpu.pipeline.decoder_outputs.FusedLaunches.prepare_frames`)."""
        return self._device().prepare_frames(raw)

    def matrices(self, A: ArrayLike) -> list[np.ndarray]:
        """The float32 matrix of each launch for the decoder ``A`` (B x K): what a per-sequence decoder (the
        white reference's) writes into the launches' matrix buffers."""
        return self._device().matrices(A)

    def white_matrices(self, raw, host=None) -> list | None:
        """With a reference white in the device-resident mode: this sequence's corrected decoder's matrix of each
        launch (:meth:`matrices`), from the white's gains on its frames ``raw`` (``host``: them as
        :meth:`prepare_frames` made them, when it corrects them); None without a white."""
        ref = self.white_reference
        if ref is None:
            return None
        if self.precorrect:
            host = self.prepare_frames(raw) if host is None else host
            gains = ref.gains(host, dark=np.zeros(host.shape[1:], np.float32))
        else:
            gains = ref.gains(raw)
        return self.matrices(ref.decoder(gains))

    def warm_up(self, dtype=np.uint16) -> None:
        """Build every kernel and prime the memory pool on a blank sequence (nothing to build in the motion
        mode, whose passes are made per sequence)."""
        if self.fused is not None:
            self.fused.warm_up(dtype)

    def enqueue(self, frames, matrices=None) -> dict:
        """Enqueue every launch on the K frames (flat device array); returns the flat device output buffers by
        output name and ``mask`` (bit 1: a frame at the saturation level). ``matrices``: a device buffer per launch
        holding :meth:`matrices` of this sequence's decoder, used instead of the plan's."""
        return self._device().enqueue(frames, matrices)

    # ---------------------------------------------------------------------------------------- one sequence
    def maps(self, raw: ArrayLike) -> dict:
        """The maps of one sequence ``raw`` (K, H, W) by output name, plus ``mask`` (H, W) uint8 (1 saturated, 4
        outside the field, 8 inconsistent, 16 decoded with an object's own motion), NaN where masked. In the
        motion mode also ``estimate`` (the sequence's :class:`specgpu.motion.estimate.MotionEstimate`) and
        ``layers`` (its :class:`specgpu.pipeline.moving_layers.ObjectLayer` list)."""
        if self.spec is None:
            raise ValueError("maps needs the outputs named (SequenceDecoder(plan, calibration, outputs))")
        if self.motion != "none":
            return self._moving_maps(raw)
        dev, q = self._device(), self.queue
        host = dev.prepare_frames(raw) if dev.precorrect else np.asarray(raw)
        out = dev.enqueue(engine.to_device(q, np.ascontiguousarray(host).reshape(-1)))
        maps = {}
        for name, (shape, dtype) in self.shapes().items():
            maps[name] = np.empty(shape, dtype)
            cl.enqueue_copy(q, maps[name], out[name])
        q.finish()
        saturated = (maps["mask"] & np.uint8(Mask.SATURATED)).astype(bool)
        if saturated.any():  # no valid measurement: NaN, as recover makes it
            for name in self.outputs:
                maps[name][saturated] = np.nan
        return maps

    def pass_rows(self, A=None) -> np.ndarray:
        """(rows, K) the warped pass's rows for the decoder ``A`` (the plan's by default): every linear output
        asked for (:meth:`specgpu.pipeline.decoder_outputs.Outputs.rows`) and, with ``denoise``, the guide's."""
        rows = self.spec.rows(A)[0] if self.spec is not None else np.asarray(self.plan.A if A is None else A)
        return rows if self.denoise is None else np.vstack([rows, warped_guide_row(self.plan)])

    def warped_outputs(self, sensor, seconds=None):
        """The warped pass of one sequence and :meth:`pass_rows` of its samples, for the plan's decoder or, with a
        reference white, for this sequence's (:meth:`motion_white_gains`): (recovery, y (H, W, rows) float32,
        gains or None, the decoder (B, K), with an ambient frame's column: what the samples went through). ``sensor``:
        the sequence's frames corrected on the sensor's scale (:meth:`Corrections.moving`)."""
        ambient = self.corrections.ambient
        if self.white_motion is None:
            rec = self.warped(sensor, self.pass_rows(), seconds=seconds)
            return rec, rec.y, None, subtracting_ambient(self.plan.A, ambient)
        # every frame's warped sample (the identity's rows), the white measured, then the corrected decoder's rows
        rec = self.warped(sensor, np.eye(self.plan.K), seconds=seconds)
        gains = self.motion_white_gains(sensor, rec)
        A = self.white_motion.decoder(gains)
        R = self.white_rows(A, gains)
        cols = np.flatnonzero(np.any(R != 0, axis=0))
        # float32 samples by float32 rows (one BLAS product, no float64 copy of the K samples of every pixel)
        samples = rec.y if len(cols) == rec.y.shape[-1] else rec.y[..., cols]  # no copy where every frame is read
        y = np.matmul(samples, np.ascontiguousarray(R[:, cols].T, np.float32))
        return rec, y, gains, subtracting_ambient(A, ambient)

    def white_rows(self, A, gains) -> np.ndarray:
        """:meth:`pass_rows` of a reference white's decoder ``A`` for its ``gains``: where ``A`` is the plan's decoder
        with each column divided by its gain (what :meth:`specgpu.planning.correction.WhiteReference.decoder` gives
        unless the light's colour changed), the plan's rows made once with the same columns divided (every output's
        rows are linear in the decoder's columns; the guide's row is the plan's own), else rebuilt from ``A``."""
        g = np.asarray(gains, np.float64)
        if not np.array_equal(A, self.plan.A / g[None, :]):
            return self.pass_rows(A)
        if self._white_base is None:
            self._white_base = self.pass_rows(self.plan.A)
        rows = self._white_base / g[None, :]
        if self.denoise is not None:  # the guide's row stays the plan's
            rows[-1] = self._white_base[-1]
        return rows

    def motion_white_gains(self, sensor, rec) -> np.ndarray:
        """(K,) the reference white's gains of one sequence (``sensor``: its corrected frames) whose warped
        samples of every frame are ``rec.y`` (H, W, K): with ``white_moves="camera"`` on the raw pixels of the ROI
        (a white fixed in the field, as the still decoding measures it); with ``"scene"`` on the samples at the
        reference time (a white that moves with the scene), its pixels flagged outside the field or inconsistent
        left out, a saturated one refused (:meth:`specgpu.planning.correction.WhiteReference.gains`)."""
        corr, white = self.corrections, self.white_motion
        if self.white_moves == "camera":  # above the ambient frame where there is one, as the still decoding
            return white.gains(sensor, dark=corr.dark if corr.ambient is None else corr.level(sensor))
        x, y, w, h = white.roi
        flags = rec.mask[y:y + h, x:x + w] & ~np.uint8(Mask.LAYER)
        if np.any(flags & np.uint8(Mask.SATURATED)):
            raise ValueError(f"--white-roi {x},{y},{w},{h} is saturated in a frame: choose a darker white or a "
                             "shorter exposure")
        if np.all(flags):
            raise ValueError(f"--white-roi {x},{y},{w},{h}: the white moving with the scene was seen outside the "
                             "field or inconsistent in every pixel (a white fixed in the field: --white-roi-moves "
                             "camera)")
        # the samples (o - dark) * gain at the reference time put back on the sensor's scale the gains read: the
        # ROI's only (the gains read nothing else), in an array that holds the ROI where the frames would
        sl = (slice(y, y + h), slice(x, x + w))
        sensor_roi = np.empty((rec.y.shape[-1], y + h, x + w), np.float32)
        sensor_roi[:, y:, x:] = (np.moveaxis(rec.y[sl], -1, 0) / live_gain(self.calibration.flat_field[sl])[None]
                                 + np.asarray(corr.dark, np.float32)[sl][None])
        return white.gains(sensor_roi, dark=corr.dark)

    def filter_parts(self, y, mask):
        """:func:`specgpu.pipeline.denoise.compensated_parts` of a warped pass's rows ``y`` (the guide last): which
        pixels the filter smooths (a pixel with any row not finite is left out, and its neighbourhood unfiltered),
        the guide as it takes it and its level, made once for the outputs and their sigmas (None without
        ``denoise`` or where it smooths none)."""
        if self.denoise is None:
            return None
        return compensated_parts(y[..., :-1], y[..., -1], mask, radius=self.denoise[0])

    def smoothed(self, y, mask, *, samples=None, decoder=None, parts=PARTS_MADE_HERE) -> dict | None:
        """With ``denoise``, what carrying the sigmas through the filter needs of a warped pass's
        :meth:`pass_rows` samples ``y`` (H, W, rows; the guide last) and its ``mask``: ``pixels`` (H, W) bool, those
        the filter smooths (:func:`specgpu.pipeline.denoise.compensated_parts`; None: none), the guide as
        the filter takes it and its ``level``, ``radius``, ``eps``, and the unfiltered outputs' slopes: ``slopes``
        (H, W, B), the cube's rows of ``y``, or, where the pass holds the frames' samples instead (the cube not
        asked for), ``samples`` (H, W, K) and the ``decoder`` (B, K) that makes the cube of them (the pass's own,
        :meth:`warped_outputs`' fourth value); ``samples`` given: those (a reference white's pass of every frame's
        sample); None without ``denoise``. ``parts``: :meth:`filter_parts` of ``y`` already made."""
        if self.denoise is None:
            return None
        radius, eps = self.denoise
        parts = self.filter_parts(y, mask) if parts is PARTS_MADE_HERE else parts
        if parts is None:
            return {"pixels": None}
        _, pixels, guide, level = parts
        out = {"pixels": pixels, "guide": guide, "level": level, "radius": radius, "eps": eps}
        if self.spec is None or "cube" in self.slices:
            cube = self.slices["cube"] if self.spec is not None else slice(0, self.plan.A.shape[0])
            return {**out, "slopes": y[..., cube]}
        if decoder is None:
            raise ValueError("the pass holds the frames' samples, not the cube: give the decoder that makes it")
        return {**out, "samples": y[..., self.slices["samples"]] if samples is None else samples,
                "decoder": np.asarray(decoder, np.float64)}

    def variance_launch(self) -> PreparedWarpedVariance:
        """The sensor's dark level and flat field and the plan's noise on the device, set up on first use: the
        motion mode's sigma outputs are made with it (:func:`specgpu.pipeline.moving_decode.warped_uncertainty`)."""
        if self._variance is None:  # two threads may both make one: the same, and either is kept
            noise = NoiseModel.from_params(self.plan.params["noise"])
            dark = self.corrections.dark
            self._variance = PreparedWarpedVariance(
                get_queue(self.device), np.shape(dark), dark, self.gain, gain_e_per_dn=noise.gain_e_per_dn,
                read_var_dn2=noise.read_var_dn2, light_rms=noise.light_rms)
        return self._variance

    def _warped_sigmas(self, sensor, rec, A, XYZ, *, light, smoothed=None) -> dict:
        """The sigma outputs of one motion-compensated sequence (:func:`specgpu.pipeline.moving_decode.
        warped_uncertainty`, through the filter on the ``smoothed`` pixels): ``sigma`` (each output and their
        RMS), ``sigma_rms``, ``dE_sigma`` (the XYZ covariance propagated to dE2000 at ``XYZ``, as
        :func:`specgpu.planning.uncertainty.delta_E_sigma`)."""
        names = set(self.outputs)
        M = self.spec.to_XYZ if "dE_sigma" in names else None
        only_rms = "sigma" not in names
        sigma, cov = warped_uncertainty(sensor, self.plan, self.corrections.dark, self.gain, rec, A, M=M, light=light,
                                        smoothed=smoothed, rms=only_rms, variance=self.variance_launch())
        rms = sigma if only_rms else np.sqrt(np.mean(sigma.astype(np.float64) ** 2, axis=-1,
                                                     keepdims=True)).astype(np.float32)
        out = {"sigma": np.concatenate([sigma, rms], axis=-1)} if "sigma" in names else {}
        if "sigma_rms" in names:
            out["sigma_rms"] = rms[..., 0]
        if cov is not None:
            des = delta_E_sigma(np.nan_to_num(XYZ), np.nan_to_num(cov), self.spec.white)
            des[~np.isfinite(XYZ).all(axis=-1) | ~np.isfinite(cov).all(axis=(-2, -1))] = np.nan
            out["dE_sigma"] = des
        return out

    def _denoised(self, y, mask, pass_rows, parts=PARTS_MADE_HERE) -> dict:
        """The outputs of the warped pass's rows ``y`` (H, W, rows) with those the filter applies to filtered in one
        call (:meth:`filtered`: the guide's level, the flagged pixels' neighbourhood and the guide's statistics
        made once, and only as many channels as the span of their rows in ``pass_rows`` (rows, K) holds), read
        from ``y`` in place where they lead its rows (the filter copies what it reads)."""
        index = np.arange(y.shape[-1])
        names = list(self.spec.denoise["channels"])
        cols = np.concatenate([index[self.slices[name]] for name in names])
        rows = y[..., :len(cols)] if np.array_equal(cols, index[:len(cols)]) else y[..., cols]
        filtered = self.filtered(rows, y[..., self.slices["guide"].start], mask, rows=pass_rows[cols], parts=parts)
        out, at = {}, 0
        for name in names:  # views of the filtered maps: the sink reads them, nothing writes them but its NaN
            width = len(index[self.slices[name]])
            out[name] = filtered[..., at:at + width]
            at += width
        for name, rows in self.slices.items():  # any other row as it was decoded
            if name not in out and name not in ("guide", "samples"):
                out[name] = y[..., rows]
        return out

    def _colour(self, XYZ) -> tuple[dict, list]:
        """Lab and dE (those asked for) of the host XYZ map (H, W, 3) enqueued: the XYZ written into a pooled
        device buffer, the decoder's :class:`~specgpu.pipeline.decoder_outputs.ColourLaunch`, each output copied
        into a new host map; returns the host maps and (the events to wait for before reading them, the device
        buffers they read), so the host work after it (the sigmas) overlaps the device's."""
        q = self.queue
        if self._colour_launch is None:
            with self._lock:
                if self._colour_launch is None:
                    self._colour_launch = ColourLaunch(q, self.spec, self._reference, self.n)
        xyz = get_allocator(q)(XYZ.nbytes)
        cl.enqueue_copy(q, xyz, XYZ, is_blocking=False)  # XYZ (contiguous) is kept alive by the caller
        shapes, maps, events = self.shapes(), {}, []
        made = lab_and_delta_E(self._colour_launch, xyz)
        for name, buf in made.items():
            maps[name] = np.empty(*shapes[name])
            events.append(cl.enqueue_copy(q, maps[name], buf, is_blocking=False))
        return maps, (events, [xyz, *made.values()])  # the device buffers held until the read-back is done

    def _moving_maps(self, raw) -> dict:
        steps = {}
        sensor = self.corrections.moving(raw)  # once: the warped pass, the white and the sigmas all read it
        rec, y, gains, A = self.warped_outputs(sensor, seconds=steps)
        t0 = time.perf_counter()
        sigmas = {"sigma", "sigma_rms", "dE_sigma"} & set(self.outputs)
        # the sigmas read the unfiltered slopes: of the frames' samples (a reference white's pass made them)
        parts = self.filter_parts(y, rec.mask)  # the pixels filtered and the guide: the outputs' and the sigmas'
        smoothed = (self.smoothed(y, rec.mask, samples=None if gains is None else rec.y, decoder=A,
                                  parts=parts) if sigmas else None)
        if self.denoise is None:  # views of the pass's rows: the sink reads them as they are
            out = {name: y[..., rows] for name, rows in self.slices.items()}
        else:  # the linear outputs filtered; Lab and dE below from the filtered XYZ
            out = self._denoised(y, rec.mask, self.pass_rows(None if gains is None else A), parts)
        if "cube" in out:
            out["cube"] = out["cube"].astype(self.spec.cube_dtype, copy=False)
        reading = None
        if {"Lab", "dE"} & set(self.outputs):
            out["XYZ"] = np.ascontiguousarray(out["XYZ"])  # the one copy the upload needs (none if contiguous)
            colour, reading = self._colour(out["XYZ"])
            out.update(colour)
        if sigmas:
            out.update(self._warped_sigmas(sensor, rec, A, out.get("XYZ"), light=gains is None, smoothed=smoothed))
        if reading is not None:  # the colour's read-back: one wait, after the host's own work
            cl.wait_for_events(reading[0])
        with self._lock:
            for step, seconds in {**steps, "colour": time.perf_counter() - t0}.items():
                self.seconds[step] += seconds
            self.sequences += 1
        maps = {**{name: out[name] for name in self.outputs}, "mask": rec.mask, "estimate": rec.estimates[0],
                "layers": rec.layers}
        if gains is not None:
            maps["white_gains"] = gains
        return maps

    # ------------------------------------------------------------------------------------------ which frames
    def picked(self, frames, sequence, where) -> list[int]:
        """The sequences of ``frames`` (S, K, H, W) decoded: ``sequence`` (checked), or every one. A moving scene
        is decoded one sequence at a time."""
        count = len(frames)
        check_sequence(sequence, count, where)
        if self.motion != "none" and sequence is None:
            if count != 1:
                raise ValueError(f"motion=global recovers one sequence at a time (the scene moves between "
                                 f"sequences); {where} holds {count}: give the sequence (--sequence N)")
            sequence = 0
        return list(range(count)) if sequence is None else [sequence]

    def saturated(self, frames, picked) -> np.ndarray:
        """(H, W) bool: a pixel where a frame of a picked sequence sits at the sensor's maximum code."""
        return np.any(frames[picked] >= self.calibration.max_code, axis=(0, 1))

    # ---------------------------------------------------------------------------------------------- decoding
    def decode(self, frames, *, sequence=None, where="the frames", out_dtype=np.float32) -> np.ndarray:
        """The plan's outputs (H, W, B) of one sequence of ``frames`` (S, K, H, W), or of the mean of all
        (:func:`specgpu.pipeline.recovery.recover`); NaN where saturated."""
        picked = self.picked(frames, sequence, where)
        if self.motion != "none":
            rec, y, gains, A = self.warped_outputs(self.corrections.moving(frames[picked[0]]))
            if self.denoise is not None:
                y = self.filtered(y[..., :-1], y[..., -1], rec.mask,
                                  rows=self.pass_rows(None if gains is None else A)[:-1])
            return y.astype(out_dtype, copy=False)
        gain = live_gain(self.calibration.flat_field)
        if self.corrections.per_sequence:
            y = None
            for signal, _, A in self.sequence_decoders(frames, picked):
                ys = np.asarray(apply_linear(signal, A, None, gain, out_dtype=np.float32, device=self.device))
                y = ys if y is None else y + ys
            y = (y / len(picked)).astype(out_dtype)
        else:
            mean = self.mean_frames(frames, picked)
            if self.corrections.host:
                y = apply_linear(self.corrections.signal(mean), self.plan.A, None, gain, out_dtype=out_dtype,
                                 device=self.device)
            else:
                y = apply_linear(mean, self.plan.A, self.corrections.dark, gain, out_dtype=out_dtype,
                                 device=self.device)
        saturated = self.saturated(frames, picked)
        if saturated.any():
            y[saturated] = np.nan
        return y

    def filtered(self, y, guide, mask, *, rows=None, parts=PARTS_MADE_HERE) -> np.ndarray:
        """The warped outputs ``y`` (H, W, C) smoothed by the guided filter of the warped frames' sum ``guide``,
        flagged pixels left out, filtered in the span of their decoder's ``rows`` (C, K) where given
        (:func:`specgpu.pipeline.denoise.denoise_compensated`; ``parts``: :meth:`filter_parts` of the pass these
        rows are of, already made)."""
        radius, eps = self.denoise
        return denoise_compensated(y, guide, mask, radius=radius, eps=eps, rows=rows, device=self.device,
                                   parts=parts)

    @staticmethod
    def mean_frames(frames, picked) -> np.ndarray:
        """The picked sequences' mean frames (one sequence as it is)."""
        return frames[picked].mean(axis=0, dtype=np.float32) if len(picked) > 1 else frames[picked[0]]

    def sequence_decoders(self, frames, picked) -> list:
        """Per picked sequence, decoded on its own (an ambient frame, a reference white): its corrected signal,
        the level subtracted from it and its decoder."""
        plan, corr = self.plan, self.corrections
        prepared = []
        for s in picked:
            level = corr.level(frames[s])
            signal = corr.signal(frames[s], level)
            gains = (None if corr.white_roi is None else
                     white_gains(signal + level[None], plan, self.calibration, corr.white_roi,
                                 corr.white_reflectance, dark=level))
            prepared.append((signal, level, gains))
        if corr.white_roi is None:
            return [(signal, level, plan.A) for signal, level, _ in prepared]
        # The light's colour drifts over hours: one colour fit on the sequences' mean gains (each frame's own power
        # fluctuation averages down), then each sequence's frames rescaled by its own gains.
        mean_gains = np.exp(np.mean([np.log(g) for _, _, g in prepared], axis=0))
        A_mean = corrected_decoder(plan, mean_gains, self.calibration, corr.white_reflectance,
                                   sequences=len(prepared))
        return [(signal, level, A_mean / (gains / mean_gains)[None, :]) for signal, level, gains in prepared]

    def warped(self, sensor, A, *, seconds: dict | None = None):
        """The warped pass of one sequence through the decoder ``A`` (rows, K), ``sensor`` (K, H, W) its frames
        corrected on the sensor's scale (:meth:`Corrections.moving`; with an ambient frame, ``A`` reads each frame
        above it: :func:`specgpu.planning.correction.subtracting_ambient`), its motion
        estimated within the sequence (:func:`specgpu.pipeline.moving_layers.recover_moving`, with the plan's
        reference frames and residual check); a :class:`~specgpu.pipeline.moving_layers.MovingRecovery`. The motion
        is registered on the decoder's device (the default one without ``device``), so recover, the stream and the
        batch estimate it alike (:func:`specgpu.motion.methods.estimate_motion`)."""
        if self.motion == "none":
            raise ValueError("the warped pass needs a motion mode other than none")
        ambient = self.corrections.ambient
        return recover_moving(sensor, subtracting_ambient(A, ambient), dark=self.corrections.dark, gain=self.gain,
                              saturation=float(self.calibration.max_code), model=self.model,
                              device=get_queue(self.device), seconds=seconds,
                              reference_frames=self.reference_frames, residual=self.residual, ambient=ambient)
