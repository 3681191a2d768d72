"""The motion methods by name, and the one entry point that estimates a sequence's motion by any of them.

:data:`MOTION_METHODS` maps a name (``--motion`` on recover, stream and batch) to the function that estimates it,
in colour-science's style (``PLAN_METHODS``, ``DELTA_E_METHODS``): ``"none"`` (a still scene: every displacement
zero), ``"global"`` (a translation per frame: :mod:`specgpu.motion.global_motion`), ``"affine"`` (an affine map per
frame: :mod:`specgpu.motion.affine`) and ``"flow"`` (a displacement per pixel: :mod:`specgpu.motion.flow`, which
starts from the global translation; the dense field itself is fitted where the decodings are compared). Each takes
``(frames, dark, gain, *, reference_frames, upsample, binning, device, prior)`` and returns a
:class:`~specgpu.motion.estimate.MotionEstimate`; :func:`estimate_motion` finds one by name, an unknown name refused in
one line naming the choices.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from specgpu.core.validate import validate_method
from specgpu.motion.device_estimate import estimate_on_device
from specgpu.motion.estimate import MotionEstimate
from specgpu.motion.flow import MIN_FRAMES
from specgpu.motion.global_motion import estimate_global_motion
from specgpu.motion.images import frame_gradients
from specgpu.motion.reference import check_reference_frames, estimate_reference_motion

__all__ = ["MOTION_METHODS", "estimate_motion", "check_motion_mode", "still", "global_translation", "affine_maps",
           "flow_start"]


def still(frames: ArrayLike, dark=None, gain=None, *, reference_frames=None, upsample: int = 10, binning: int = 1,
          device=None, prior=None) -> MotionEstimate:
    """``"none"``: decode every pixel's samples where they are (a still scene): each frame's displacement zero."""
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"frames must be (K, H, W), got shape {frames.shape}")
    K = frames.shape[0]
    return MotionEstimate(np.zeros((K, 2)), np.ones(K, bool), np.full(K, np.nan), (K - 1) // 2)


def _by_model(frames, dark, gain, model: str, reference_frames, upsample: int, binning: int,
              device, prior=None) -> MotionEstimate:
    """A translation or an affine map per frame: from the plan's broadband reference frames where it has them
    (:func:`~specgpu.motion.reference.estimate_reference_motion`); else from every frame, registered on the device
    where one is given (:func:`~specgpu.motion.device_estimate.estimate_on_device`, the gradient images never
    leaving it until registered) and it takes the inputs, on the host otherwise
    (:func:`~specgpu.motion.global_motion.estimate_global_motion`, every frame's gradient image made at once on the
    device: the estimate registers them, the consistency check reads them again)."""
    refs = [] if not reference_frames else check_reference_frames(reference_frames, len(frames))
    if refs:
        return estimate_reference_motion(frames, refs, dark, gain, upsample=upsample, model=model)
    if device is not None and binning == 1:
        est = estimate_on_device(frames, dark, gain, model=model, prior=prior, upsample=upsample, device=device)
        if est is not None:
            return est
    return estimate_global_motion(frames, dark, gain, upsample=upsample, binning=binning, model=model,
                                  gradients=frame_gradients(frames, dark, gain, device=device))


def global_translation(frames: ArrayLike, dark=None, gain=None, *, reference_frames=None, upsample: int = 10,
                       binning: int = 1, device=None, prior=None) -> MotionEstimate:
    """``"global"``: a translation per frame (phase correlation of gradient images); the decoder samples frame k
    at x + d_k."""
    return _by_model(frames, dark, gain, "translation", reference_frames, upsample, binning, device, prior)


def affine_maps(frames: ArrayLike, dark=None, gain=None, *, reference_frames=None, upsample: int = 10,
                binning: int = 1, device=None, prior=None) -> MotionEstimate:
    """``"affine"``: an affine map per frame (translation, rotation, zoom; tiles registered and fitted); the
    decoder samples frame k at M_k x."""
    return _by_model(frames, dark, gain, "affine", reference_frames, upsample, binning, device, prior)


def flow_start(frames: ArrayLike, dark=None, gain=None, *, reference_frames=None, upsample: int = 10,
               binning: int = 1, device=None, prior=None) -> MotionEstimate:
    """``"flow"``: the global translation a dense flow starts from (tiles registered, a steady velocity each,
    interpolated per pixel: :func:`specgpu.motion.flow.tile_motion`, :func:`~specgpu.motion.flow.flow_field`),
    which decodes each pixel whose frames it makes agree where the global motion leaves it inconsistent,
    untextured or less consistent. Refused in one line with broadband reference frames (a flow is estimated from
    every frame) and for sequences too short for a tile's steady motion."""
    if reference_frames:
        raise ValueError("a flow is estimated from every frame of the sequence: with broadband reference frames, "
                         "compensate a translation (global) or an affine map per frame")
    if len(frames) < MIN_FRAMES + 1:
        raise ValueError(f"a flow needs sequences of at least {MIN_FRAMES + 1} frames (each tile's steady motion is "
                         f"fitted to {MIN_FRAMES} frames besides the reference), got {len(frames)}")
    return _by_model(frames, dark, gain, "translation", None, upsample, binning, device, prior)


#: How frames are decoded with respect to motion, by name: the function that estimates it (see each one's
#: docstring for what the decoder then does).
MOTION_METHODS = {
    "none": still,
    "global": global_translation,
    "affine": affine_maps,
    "flow": flow_start,
}


def check_motion_mode(motion) -> str:
    """``motion`` as a key of :data:`MOTION_METHODS` (case-insensitive); an unknown one is a
    :class:`~specgpu.core.validate.BadArgument` listing them."""
    validate_method(motion, MOTION_METHODS, "motion")
    return motion.lower()


def estimate_motion(frames: ArrayLike, dark: ArrayLike | None = None, gain: ArrayLike | None = None, *,
                    method: str = "global", reference_frames=None, upsample: int = 10, binning: int = 1,
                    device=None, prior=None) -> MotionEstimate:
    """The motion of one sequence by the method named ``method`` (a key of :data:`MOTION_METHODS`).

    Parameters
    ----------
    frames : array_like, (K, H, W)
        The raw frames of one sequence.
    dark : array_like, (H, W) or (K, H, W), optional
        Dark level subtracted before registration.
    gain : array_like, (H, W), optional
        Flat field applied before registration.
    method : {"none", "global", "affine", "flow"}
        The motion method; an unknown name is a one-line :class:`~specgpu.core.validate.BadArgument` naming the
        choices.
    reference_frames : sequence of int, optional
        The sequence's broadband reference frames (:func:`specgpu.planning.reference_frames.reference_indices`):
        the global and affine motion are estimated from them alone.
    upsample, binning
        Of :func:`~specgpu.motion.global_motion.estimate_global_motion`.
    device : optional
        OpenCL device selector (or queue). Given, the translation or affine map of every frame is registered there
        (:func:`~specgpu.motion.device_estimate.estimate_on_device`); None: on the host
        (:func:`~specgpu.motion.global_motion.estimate_global_motion`, its gradient images made on the default
        device), the reference the device's estimate is checked against.
    prior : array_like, (2,), optional
        The velocity expected, px per frame (a stream's previous sequence's): with a device, where peaks of a
        repeating scene compete, the one it predicts is taken
        (:func:`~specgpu.motion.device_estimate.start_candidates`).

    Returns
    -------
    MotionEstimate
        Each frame's displacement from the sequence's reference time.
    """
    estimator = validate_method(method, MOTION_METHODS, "method")
    return estimator(frames, dark, gain, reference_frames=reference_frames, upsample=upsample, binning=binning,
                     device=device, prior=prior)
