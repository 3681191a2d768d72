"""Whether a motion-compensated sequence's frames agree at each pixel: the check that flags an object moving on its
own, an occlusion, or a wrong motion, from the frames' gradient images (where no frame has structure, the residual
of the decoding judges instead: :mod:`specgpu.motion.residual`).
"""

from __future__ import annotations

import numpy as np

from specgpu.engine.consistency import consistency_from_frames, consistency_maps
from specgpu.motion.images import device_takes, frame_gradients

__all__ = ["CHECK_THRESHOLD", "inconsistent_pixels", "consistency"]

#: A pixel is inconsistent where some frame correlates below this with the median (:func:`inconsistent_pixels`).
CHECK_THRESHOLD = 0.3


def inconsistent_pixels(frames, shifts, dark=None, gain=None, *, window: int = 9, threshold: float = CHECK_THRESHOLD,
                        texture: float = 0.5, own: float = 4.0, gradients=None) -> np.ndarray:
    """(H, W) bool: pixels where the motion-compensated frames disagree, so their decoded spectrum would mix
    surfaces.

    Each frame's :func:`gradient_image` is sampled where the motion says that frame saw each pixel; where the
    motion is right, their edges coincide whatever the illuminant (their contrasts differ, not their places). Per
    pixel, the normalised cross-correlation over a ``window`` x ``window`` neighbourhood between each compensated
    gradient image and their median is computed; a pixel is inconsistent where some frame with structure of its
    own there (local energy above ``own`` times its median: not just noise) correlates below ``threshold``,
    whether or not the median has texture: a wrong motion leaves the median of misaligned images flat where each
    frame has an edge. Where no frame has structure this check cannot judge; the residual check of the decoding
    does (:mod:`specgpu.motion.residual`). ``gradients``: the frames' gradient images already made
    (:attr:`MotionEstimate.gradients`; a None entry is made here).
    """
    _, worst = consistency(frames, shifts, dark, gain, window=window, texture=texture, own=own,
                                  gradients=gradients)
    return worst < threshold


def consistency(frames, shifts, dark=None, gain=None, *, window: int = 9, texture: float = 0.5, own: float = 4.0,
                gradients=None) -> tuple[np.ndarray, np.ndarray]:
    """The two maps :func:`inconsistent_pixels` thresholds, (H, W) each: ``textured`` (bool: the median
    compensated gradient image has structure there) and ``worst`` (float32: the lowest normalised
    cross-correlation of a frame with structure of its own against that median; 1 where none has). Two
    hypotheses of a pixel's motion are compared by their ``worst``. The per-pixel work runs on the default OpenCL
    device (:func:`specgpu.engine.consistency.consistency_maps`); where no gradient image is given, they are made
    there too and never read back (:func:`specgpu.engine.consistency.consistency_from_frames`)."""
    frames = np.asarray(frames)
    none_given = gradients is None or all(g is None for g in gradients)
    if none_given and np.all(np.isfinite(np.asarray(shifts, np.float64))) and device_takes(
            frames, None if dark is None else np.asarray(dark, np.float32), gain):
        return consistency_from_frames(frames, shifts, dark, gain, window=window, texture=texture, own=own)
    g = frame_gradients(frames, dark, gain, gradients)
    return consistency_maps(g, shifts, window=window, texture=texture, own=own)

