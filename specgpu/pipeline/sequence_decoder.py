"""The decoding of one sequence, written once: the corrections a (calibration, plan) pair calls for, then the
linear or the warped pass.

:func:`corrections_for` decides, once, what a calibration and a plan ask of the frames before the decoder
(:class:`Corrections`): the level subtracted (the calibration's dark at the plan's exposure, or the plan's ambient
frame), the sensor's linearisation, the per-pattern flat field and a reference white. :class:`SequenceDecoder`
applies them and runs the pass: ``pipeline.recover`` and :func:`~specgpu.pipeline.recovery.uncertainty` (and so the
report and the viewer) decode through it, the stream's and the batch's device decoder
(:class:`specgpu.pipeline.decoder.StreamDecoder`) takes its host corrections from it, and their motion-compensated
decoder (:class:`specgpu.pipeline.moving_decode.MovingDecoder`) runs its warped pass.

Frames corrected on the host are handed to the linear map as the signal above the level, with no dark: the level
is subtracted once. The motion estimate, the warped pass and the noise model read the corrected frames on the
sensor's scale (:meth:`Corrections.sensor`): they compare samples with the sensor's maximum code and model the
dark level's own noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from specgpu.core.numerics import live_gain
from specgpu.engine.linear_map import apply_linear
from specgpu.motion.methods import check_motion_mode
from specgpu.motion.residual import residual_check
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.planning.correction import ambient_index, corrected_decoder, white_gains
from specgpu.planning.reference_frames import reference_indices

__all__ = ["Corrections", "SequenceDecoder", "check_sequence", "corrections_for", "motion_model"]


def motion_model(mode: str) -> str:
    """The estimator's model of a motion mode (``"global"``: one translation per frame)."""
    return "translation" if mode == "global" else mode


def check_sequence(sequence, count: int, where) -> None:
    """Refuse, in one line naming ``where``, a sequence index outside the ``count`` sequences held there."""
    if sequence is not None and not 0 <= sequence < count:
        raise ValueError(f"sequence {sequence} is out of range: {where} holds {count}")


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
    for a scene that moved, the warped pass with the motion estimated within the sequence.

    Parameters
    ----------
    plan : specgpu.planning.plans.Plan
    calibration : specgpu.calibration.bundle.CalibrationBundle
    white_roi, white_reflectance : optional
        A reference white in the field (as :func:`specgpu.pipeline.recovery.recover`).
    motion : {"none", "global", "affine", "flow"}
        How the scene's motion within a sequence is compensated (:data:`specgpu.motion.methods.MOTION_METHODS`).
    device : optional
        OpenCL device selector or queue.
    """

    def __init__(self, plan, calibration, *, white_roi=None, white_reflectance=None, motion: str = "none",
                 device=None):
        self.plan, self.calibration, self.device = plan, calibration, device
        self.corrections = corrections_for(calibration, plan, white_roi=white_roi,
                                           white_reflectance=white_reflectance)
        self.motion = check_motion_mode(motion)
        self.gain = calibration.flat_field
        if self.motion != "none":
            if self.corrections.per_sequence:
                raise ValueError("motion=global does not combine with a reference white or an ambient frame yet "
                                 "(both assume the same pixels in every frame)")
            self.model = motion_model(self.motion)
            self.reference_frames = reference_indices(plan)  # the motion from them where the plan has them
            self.residual = residual_check(plan, calibration)  # samples judged against the plan's model

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
            return self.warped(frames[picked[0]], self.plan.A).y.astype(out_dtype, copy=False)
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

    def warped(self, raw, A, *, seconds: dict | None = None):
        """The warped pass of one sequence ``raw`` (K, H, W) through the decoder ``A`` (rows, K), its motion
        estimated within the sequence (:func:`specgpu.pipeline.moving_layers.recover_moving`, with the plan's
        reference frames and residual check); a :class:`~specgpu.pipeline.moving_layers.MovingRecovery`."""
        if self.motion == "none":
            raise ValueError("the warped pass needs a motion mode other than none")
        return recover_moving(self.corrections.sensor(raw), A, dark=self.corrections.dark, gain=self.gain,
                              saturation=float(self.calibration.max_code), model=self.model, device=self.device,
                              seconds=seconds, reference_frames=self.reference_frames, residual=self.residual)
