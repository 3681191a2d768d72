"""Motion-compensated decoding of one sequence into the maps ``specgpu batch`` and ``specgpu stream`` write.

``specgpu recover --motion`` decodes one sequence of a moving scene through
:func:`specgpu.pipeline.moving_layers.recover_moving`:
the frames corrected as recover corrects them (the sensor's linearisation, the per-pattern flat ratio), each
frame's displacement estimated within the sequence, one warped device pass, the pixels seen outside the field or
whose compensated frames disagree left NaN with their mask bits. :class:`MovingDecoder` calls it on each
sequence of a batch or a stream, with every linear output the caller asks for (basis coefficients, the cube, XYZ)
stacked as rows of one decoder, so the estimate and the warped pass are made once per sequence; Lab and dE follow
from XYZ as the offline path computes them (:func:`specgpu.pipeline.recovery.to_Lab`, ``delta_E``).

``sigma_rms`` is the noise model's RMS standard deviation at the warped samples
(:func:`specgpu.planning.uncertainty.frame_variance` with the sequence's shifts; an object layer's pixels with its
own): an upper bound, since interpolation averages up to four sensor pixels' noise. It serves the running estimate
along the motion (``stream --accumulate N --motion``). Outputs that are not motion-compensated (the per-band sigmas
and dE's, whose covariance model assumes each sample came from one sensor pixel; the denoiser's guide; a reference
white or an ambient frame, measured on fixed pixels) are refused in one line naming the option
(:func:`check_motion_options`).
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from specgpu.core.mask import Mask
from specgpu.core.validate import validate_method
from specgpu.engine.colorimetry import DELTA_E_METHODS, XYZ_to_Lab, delta_E
from specgpu.motion.flow import MIN_FRAMES
from specgpu.motion.methods import check_motion_mode
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.planning.correction import ambient_index
from specgpu.planning.reference_frames import reference_indices
from specgpu.planning.uncertainty import constant_variance, frame_variance

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan

__all__ = ["MOTION_OUTPUTS", "MovingDecoder", "check_motion_options"]

#: The outputs a motion-compensated decoding carries: linear maps of the warped samples, and colour from them.
MOTION_OUTPUTS = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma_rms")


def check_motion_options(motion, plan=None, *, outputs=(), denoise=None, white_roi=None) -> str:
    """``motion`` checked (a key of :data:`specgpu.motion.methods.MOTION_METHODS`) and, unless ``"none"``, every
    option that cannot be motion-compensated yet refused in one line naming it. Returns the mode."""
    mode = check_motion_mode(motion)
    if mode == "none":
        return mode
    for name in outputs:
        if name not in MOTION_OUTPUTS:
            raise ValueError(f"the {name} output with --motion {mode}: its covariance model assumes each pixel's "
                             f"samples came from one sensor pixel, which motion compensation breaks; motion "
                             f"outputs are {', '.join(MOTION_OUTPUTS)}")
    if denoise is not None:
        raise ValueError("--denoise with --motion: the filter's guide (the sum of the frames) is not "
                         "motion-compensated, so it would mix the surfaces the compensation separated")
    if white_roi is not None:
        raise ValueError("--white-roi with --motion: the reference white is measured on fixed pixels, which the "
                         "scene moves across")
    if mode == "flow" and plan is not None and plan.K < MIN_FRAMES + 1:
        raise ValueError(f"--motion flow needs a plan of at least {MIN_FRAMES + 1} frames (each tile's steady motion "
                         f"is fitted to {MIN_FRAMES} frames besides the reference), the {plan.method} plan has "
                         f"{plan.K}")
    if mode == "flow" and plan is not None and reference_indices(plan):
        raise ValueError("--motion flow with a plan with broadband reference frames: the flow is estimated from "
                         "every frame of the sequence; compensate with --motion global or affine")
    if plan is not None and ambient_index(plan) is not None:
        raise ValueError(f"--motion {mode} with a plan with an ambient frame: the ambient frame is subtracted "
                         "from fixed pixels, which the scene moves across")
    return mode


class MovingDecoder:
    """One sequence of a moving scene decoded as ``recover --motion`` decodes it, into the maps asked for.

    Parameters
    ----------
    plan, calibration
        The plan (decoder A) and the calibration it was made from.
    outputs : sequence of str
        Of :data:`MOTION_OUTPUTS`; ``"coefficients"`` are in the plan's output basis, as
        :class:`specgpu.pipeline.decoder.StreamDecoder` makes them (``basis``, ``A_coefficients``).
    mode : {"global", "affine", "flow"}
    reference : array_like, optional
        CIELAB reference of ``"dE"``: (3,) or (H, W, 3).
    method, illuminant, observer, integration
        Of dE, and of XYZ / Lab (resolved by the plan as the stream resolves them; Lab's white is the plan's
        :meth:`specgpu.planning.plans.Plan.white_XYZ`).
    cube_dtype : numpy dtype
        Storage of the cube (float16 or float32).
    device : optional
        OpenCL device selector or queue of the warped pass.
    """

    def __init__(self, plan: Plan, calibration: CalibrationBundle, outputs, *, mode: str, reference=None,
                 method: str = "CIE 2000", illuminant=None, observer=None, cube_dtype: DTypeLike = np.float32,
                 device=None, integration: str = "rectangle"):
        mode = check_motion_options(mode, plan, outputs=outputs)
        if mode == "none":
            raise ValueError("a MovingDecoder needs a motion mode other than none")
        self.plan, self.calibration, self.outputs = plan, calibration, tuple(outputs)
        self.device = device
        self.cube_dtype = np.dtype(cube_dtype)
        self.illuminant = plan.resolve_illuminant(illuminant)
        self.observer = plan.resolve_observer(observer)
        self.integration = integration
        self.method = validate_method(method, DELTA_E_METHODS) if "dE" in self.outputs else method
        self.reference = None if reference is None else np.asarray(reference, np.float32)
        if "dE" in self.outputs and self.reference is None:
            raise ValueError("the dE output needs a reference (an L,a,b colour or a per-pixel Lab image)")
        # the corrections, the motion estimate and the warped pass: recover --motion's, run on the stacked rows
        self.sequence = SequenceDecoder(plan, calibration, motion=mode, device=device)
        self.dark = self.sequence.corrections.dark
        A = np.asarray(plan.A, np.float64)
        rows, self.slices = [], {}

        def add(name, matrix):
            self.slices[name] = slice(sum(len(r) for r in rows), sum(len(r) for r in rows) + len(matrix))
            rows.append(np.asarray(matrix, np.float64))

        if "coefficients" in self.outputs:
            U, s, Vt = np.linalg.svd(A, full_matrices=False)
            m = int(plan.params.get("m", np.sum(s > s[0] * 1e-9)))
            add("coefficients", s[:m, None] * Vt[:m])
        if "cube" in self.outputs:
            add("cube", A)
        if {"XYZ", "Lab", "dE"} & set(self.outputs):
            add("XYZ", plan.outputs_to_XYZ(self.illuminant, self.observer, integration) @ A)
            self.white = plan.white_XYZ(self.illuminant, self.observer, integration)
        # sigma_rms alone: the pass still decodes the plan's outputs (its mask says which pixels have samples)
        self.matrix = np.vstack(rows) if rows else A
        if "sigma_rms" in self.outputs:
            if "noise" not in plan.params:
                raise ValueError(f"the {plan.method} plan records no noise model, so it has no sigma; re-plan it "
                                 "with specgpu plan --rig RIG.toml (the rig the calibration was made on) to record one")
            # the one row whose square is the mean over the outputs of A^2: frame_variance gives the mean variance
            self.rms_row = np.sqrt(np.mean(A * A, axis=0, keepdims=True))
            self.rms_constant = np.float32(np.mean(constant_variance(plan), dtype=np.float64))
        #: host seconds spent so far in each step (estimate, warped pass, consistency check with the object
        #: layers, colour), and the sequences decoded: where a moving stream's time goes
        self.seconds = dict.fromkeys(("estimate", "warp", "check", "colour"), 0.0)
        self.sequences = 0
        self._lock = threading.Lock()  # decode may run on several threads at once (the stream's)

    def frames(self, raw: ArrayLike) -> np.ndarray:
        """The frames the estimator, the warped pass and the noise model read: ``raw`` corrected as recover
        corrects them, on the sensor's scale (:meth:`specgpu.pipeline.sequence_decoder.Corrections.sensor`)."""
        return self.sequence.corrections.sensor(raw)

    def decode(self, raw: ArrayLike) -> dict:
        """The maps of one sequence (K, H, W) by output name, plus ``mask`` (H, W) uint8 (1 saturated, 4 outside
        the field, 8 inconsistent, 16 decoded with an object's own motion), NaN where masked; ``estimate``: the
        sequence's :class:`specgpu.motion.estimate.MotionEstimate`; ``layers``: its
        :class:`specgpu.pipeline.moving_layers.ObjectLayer` list."""
        steps = {}
        rec = self.sequence.warped(raw, self.matrix, seconds=steps)
        y, mask, est = rec.y, rec.mask, rec.estimates[0]
        t3 = time.perf_counter()
        out = {}
        for name, rows in self.slices.items():
            out[name] = np.ascontiguousarray(y[..., rows])
        if "cube" in out:
            out["cube"] = out["cube"].astype(self.cube_dtype, copy=False)
        XYZ = out.get("XYZ")
        if {"Lab", "dE"} & set(self.outputs):
            Lab = np.asarray(XYZ_to_Lab(XYZ, self.white, device=self.device))
            if "Lab" in self.outputs:
                out["Lab"] = Lab
            if "dE" in self.outputs:
                out["dE"] = np.asarray(delta_E(self.reference, Lab, self.method, device=self.device), np.float32)
        if "XYZ" not in self.outputs:
            out.pop("XYZ", None)
        if "sigma_rms" in self.outputs:
            out["sigma_rms"] = self.sigma_rms(self.frames(raw), rec)
        with self._lock:
            for step, seconds in {**steps, "colour": time.perf_counter() - t3}.items():
                self.seconds[step] += seconds
            self.sequences += 1
        return {**{name: out[name] for name in self.outputs}, "mask": mask, "estimate": est, "layers": rec.layers}

    def sigma_rms(self, frames: ArrayLike, rec) -> np.ndarray:
        """(H, W) float32: the RMS over the outputs of their standard deviation at the samples ``rec`` decoded (the
        sequence's shifts; an object layer's own on the pixels decoded with it), NaN where the outputs are (an
        upper bound: see the module notes)."""
        gain = self.calibration.flat_field

        def variance(shifts):
            return frame_variance(frames, self.plan, self.dark, gain, A=self.rms_row, shifts=shifts,
                                  device=self.device)[..., 0]

        shifts = rec.estimates[0].shifts
        var = variance(shifts)
        own = (rec.mask & np.uint8(Mask.LAYER)) != 0
        # a displacement per pixel (a flow's) holds the layers' own already
        for layer in rec.layers if np.ndim(shifts) != 4 else ():  # in the order their decodings were given
            mine = own & layer.decoded
            if mine.any():
                var[mine] = variance(layer.shifts)[mine]
        var += self.rms_constant
        np.maximum(var, 0.0, out=var)
        np.sqrt(var, out=var)
        var[(rec.mask & ~np.uint8(Mask.LAYER)) != 0] = np.nan
        return var  # the images served the check; not kept with a result
