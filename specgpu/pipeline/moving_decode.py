"""What the motion mode of the sequence decoder can make of a moving scene's sequence, and its ``sigma_rms``.

``specgpu recover --motion`` decodes one sequence of a moving scene through
:func:`specgpu.pipeline.moving_layers.recover_moving`:
the frames corrected as recover corrects them (the sensor's linearisation, the per-pattern flat ratio), each
frame's displacement estimated within the sequence, one warped device pass, the pixels seen outside the field or
whose compensated frames disagree left NaN with their mask bits.
:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder` in its motion mode (``specgpu batch --motion``,
``specgpu stream --motion``) runs it on each sequence with every linear output asked for (basis coefficients, the
cube, XYZ) stacked as rows of one decoder (:meth:`specgpu.pipeline.decoder_outputs.Outputs.rows`), so the estimate
and the warped pass are made once per sequence; Lab and dE follow from XYZ by the launches the denoised stream
uses (:func:`specgpu.pipeline.decoder_outputs.lab_and_delta_E`).

``sigma_rms`` is the noise model's RMS standard deviation at the warped samples
(:func:`specgpu.planning.uncertainty.frame_variance` with the sequence's shifts; an object layer's pixels with its
own): an upper bound, since interpolation averages up to four sensor pixels' noise. It serves the running estimate
along the motion (``stream --accumulate N --motion``). Outputs that are not motion-compensated (the per-band sigmas
and dE's, whose covariance model assumes each sample came from one sensor pixel; the denoiser's guide; a reference
white or an ambient frame, measured on fixed pixels) are refused in one line naming the option
(:func:`check_motion_options`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from specgpu.pipeline.moving import check_motion_mode
from specgpu.pipeline.moving_flow import MIN_FRAMES
from specgpu.planning.correction import ambient_index
from specgpu.planning.reference_frames import reference_indices
from specgpu.planning.uncertainty import constant_variance, frame_variance

__all__ = ["MOTION_OUTPUTS", "check_motion_options", "warped_sigma_rms"]

#: The outputs a motion-compensated decoding carries: linear maps of the warped samples, and colour from them.
MOTION_OUTPUTS = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma_rms")


def check_motion_options(motion, plan=None, *, outputs=()) -> str:
    """``motion`` checked (a key of :data:`specgpu.pipeline.moving.MOTION_MODES`) and, unless ``"none"``, every
    option that cannot be motion-compensated yet refused in one line naming it. Returns the mode."""
    mode = check_motion_mode(motion)
    if mode == "none":
        return mode
    for name in outputs:
        if name not in MOTION_OUTPUTS:
            raise ValueError(f"the {name} output with --motion {mode}: its covariance model assumes each pixel's "
                             f"samples came from one sensor pixel, which motion compensation breaks; motion "
                             f"outputs are {', '.join(MOTION_OUTPUTS)}")
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


def warped_sigma_rms(frames: ArrayLike, plan, dark, gain, rec, *, device=None) -> np.ndarray:
    """(H, W) float32: the RMS over ``plan``'s outputs of their standard deviation at the samples the
    motion-compensated decoding ``rec`` (a :class:`~specgpu.pipeline.moving_layers.MovingRecovery`) read: the
    sequence's shifts, an object layer's own on the pixels decoded with it; NaN where the outputs are (an upper
    bound: see the module notes). ``frames``: the corrected frames on the sensor's scale."""
    A = np.asarray(plan.A, np.float64)
    # the one row whose square is the mean over the outputs of A^2: frame_variance gives the mean variance
    rms_row = np.sqrt(np.mean(A * A, axis=0, keepdims=True))

    def variance(shifts):
        return frame_variance(frames, plan, dark, gain, A=rms_row, shifts=shifts, device=device)[..., 0]

    shifts = rec.estimates[0].shifts
    var = variance(shifts)
    own = (rec.mask & np.uint8(16)) != 0
    # a displacement per pixel (a flow's) holds the layers' own already
    for layer in rec.layers if np.ndim(shifts) != 4 else ():  # in the order their decodings were given
        mine = own & layer.decoded
        if mine.any():
            var[mine] = variance(layer.shifts)[mine]
    var += np.float32(np.mean(constant_variance(plan), dtype=np.float64))
    np.maximum(var, 0.0, out=var)
    np.sqrt(var, out=var)
    var[(rec.mask & np.uint8(~16 & 0xFF)) != 0] = np.nan
    return var
