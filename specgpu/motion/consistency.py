"""Whether a motion-compensated sequence's frames agree at each pixel: the check that flags an object moving on its
own, an occlusion, or a wrong motion, from the frames' gradient images (where no frame has structure, the residual
of the decoding judges instead: :mod:`specgpu.motion.residual`).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
from scipy import ndimage

from specgpu.engine.consistency import consistency_from_frames, consistency_maps
from specgpu.engine.noise_floor import FloorPlanes, PreparedNoiseFloors
from specgpu.engine.runtime import get_queue
from specgpu.motion.images import device_takes, frame_gradients

__all__ = ["CHECK_THRESHOLD", "NOISE_FLOOR", "inconsistent_pixels", "consistency", "noise_floors",
           "noise_floors_on_device"]

#: A pixel is inconsistent where some frame correlates below this with the median (:func:`inconsistent_pixels`).
CHECK_THRESHOLD = 0.3
#: A frame has structure of its own at a pixel only where its local energy is above this many times what its noise
#: alone gives there (:func:`noise_floors`): on a flat patch of noise alone the local energy of the gradient image
#: lies between about 0.3 and 2.2 times its expectation (a 9 x 9 box of correlated samples), so 4 times it is not
#: reached by noise, while an edge's energy is many times its noise's
NOISE_FLOOR = 4.0
#: The variance of the magnitude of a pair of uncorrelated zero-mean normal values of variance s^2 (a Rayleigh
#: variable), over s^2: 2 - pi / 2
_RAYLEIGH_VAR = 2.0 - np.pi / 2.0
#: The sum of the squared weights of each 3 x 3 Sobel derivative ([1, 2, 1] x [-1, 0, 1])
_SOBEL_WEIGHTS = 12.0


def noise_floors(frames, noise, dark=None, gain=None, *, window: int = 9, factor: float = NOISE_FLOOR) -> np.ndarray:
    """(K, H, W) float32: ``factor`` times the local energy (the variance over a ``window`` x ``window`` box) that
    the temporal noise alone gives each frame's :func:`~specgpu.motion.images.gradient_image` at each pixel, in the
    frame's own pixels.

    A raw sample x DN above ``dark`` has variance x / g + s_read^2 (``noise``: a
    :class:`~specgpu.planning.noise.NoiseModel`; its light fluctuation is common to a frame's pixels and leaves no
    gradient); flat-fielded by ``gain``, ``gain^2`` times that. Each Sobel derivative of uncorrelated noise of
    variance s^2 has variance 12 s^2, the two are uncorrelated, and their magnitude a Rayleigh variable of variance
    (2 - pi / 2) 12 s^2, over the frame's mean squared as the gradient image is. The signal is the box mean over
    the window, so that the floor follows the local brightness, not its noise.
    """
    frames = np.asarray(frames)
    dark = None if dark is None else np.asarray(dark, np.float32)
    flat = None if gain is None else np.nan_to_num(np.asarray(gain, np.float32), nan=0.0)  # as gradient_image
    flat2 = None if flat is None else flat * flat

    def box(a):
        return ndimage.uniform_filter(a, window, mode="nearest")

    # the box of gain^2 (x / g + s_read^2): the read term common to every frame, the shot term per frame
    read = np.float32(noise.read_var_dn2) * (box(flat2) if flat2 is not None else np.float32(1.0))
    out = np.empty(frames.shape, np.float32)
    for k in range(len(frames)):
        x = _above_dark(frames, k, dark)
        coef = _floor_coef(x, flat, factor)
        if flat2 is not None:
            x *= flat2
        shot = np.maximum(box(x), 0.0, out=x)
        shot *= np.float32(1.0 / noise.gain_e_per_dn)
        shot += read
        shot *= coef
        out[k] = shot
    return out


def _above_dark(frames, k: int, dark) -> np.ndarray:
    """Frame ``k`` above ``dark`` (one map, one per frame, or None), float32."""
    d = None if dark is None else (dark[k] if dark.ndim == 3 else dark)
    return np.subtract(frames[k], d, dtype=np.float32) if d is not None else np.array(frames[k], np.float32)


def _floor_coef(x, flat, factor: float) -> np.float32:
    """The factor of a frame's floor: ``factor`` times the Sobel magnitude's noise over the squared mean of the
    flat-fielded frame ``x`` (above dark), as its gradient image is divided by that mean."""
    mean = float(np.vdot(x.ravel(), flat.ravel())) / x.size if flat is not None else float(np.mean(x))
    return np.float32(factor * _RAYLEIGH_VAR * _SOBEL_WEIGHTS / (mean * mean if mean > 0 else 1.0))


def noise_floors_on_device(frames, noise, dark=None, gain=None, *, window: int = 9, factor: float = NOISE_FLOOR,
                           device=None, prepared: PreparedNoiseFloors | None = None) -> FloorPlanes:
    """:func:`noise_floors` made on the device and kept there (:class:`specgpu.engine.noise_floor.FloorPlanes`, which
    the consistency check reads in place): the box means in two separable passes; each frame's mean (its
    factor) on the host. ``prepared``: the sensor's set-up (its dark, flat field and read noise on the device, for
    ``window``), kept by the caller for a stream of sequences; made for this call without it. A dark level per
    frame: made on the host and uploaded."""
    frames = np.asarray(frames)
    queue = get_queue(device) if prepared is None else prepared.queue
    if dark is not None and np.ndim(dark) == 3:
        return FloorPlanes(cla.to_device(queue, noise_floors(frames, noise, dark, gain, window=window,
                                                             factor=factor)))
    if prepared is None:
        prepared = PreparedNoiseFloors(queue, frames.shape[1:], dark, gain, gain_e_per_dn=noise.gain_e_per_dn,
                                       read_var_dn2=noise.read_var_dn2, window=window)
    d = None if dark is None else np.asarray(dark, np.float32)
    flat = None if gain is None else np.nan_to_num(np.asarray(gain, np.float32), nan=0.0)
    coef = [_floor_coef(_above_dark(frames, k, d), flat, factor) for k in range(len(frames))]
    return prepared.floors(frames, coef)


def inconsistent_pixels(frames, shifts, dark=None, gain=None, *, window: int = 9, threshold: float = CHECK_THRESHOLD,
                        texture: float = 0.5, own: float = 4.0, gradients=None, noise=None) -> np.ndarray:
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
    (:attr:`MotionEstimate.gradients`; a None entry is made here). ``noise``: the camera's
    :class:`~specgpu.planning.noise.NoiseModel`; with it a frame has structure of its own only where its local
    energy is also above :data:`NOISE_FLOOR` times what its noise gives there (:func:`noise_floors`): the shot
    noise of a bright flat area, far above the median energy the dim areas set, is noise still.
    """
    _, worst = consistency(frames, shifts, dark, gain, window=window, texture=texture, own=own,
                           gradients=gradients, noise=noise)
    return worst < threshold


def consistency(frames, shifts, dark=None, gain=None, *, window: int = 9, texture: float = 0.5, own: float = 4.0,
                gradients=None, noise=None, floor=None) -> tuple[np.ndarray, np.ndarray]:
    """The two maps :func:`inconsistent_pixels` thresholds, (H, W) each: ``textured`` (bool: the median
    compensated gradient image has structure there) and ``worst`` (float32: the lowest normalised
    cross-correlation of a frame with structure of its own against that median; 1 where none has). Two
    hypotheses of a pixel's motion are compared by their ``worst``. The per-pixel work runs on the default OpenCL
    device (:func:`specgpu.engine.consistency.consistency_maps`); where no gradient image is given, they are made
    there too and never read back (:func:`specgpu.engine.consistency.consistency_from_frames`). ``noise``: as
    :func:`inconsistent_pixels` (None: the median's test alone); ``floor``: the frames' :func:`noise_floors` already
    made (one per frame, whatever the motion), used instead of making them from ``noise``."""
    frames = np.asarray(frames)
    if floor is None and noise is not None:
        floor = noise_floors(frames, noise, dark, gain, window=window)
    none_given = gradients is None or all(g is None for g in gradients)
    if none_given and np.all(np.isfinite(np.asarray(shifts, np.float64))) and device_takes(
            frames, None if dark is None else np.asarray(dark, np.float32), gain):
        return consistency_from_frames(frames, shifts, dark, gain, window=window, texture=texture, own=own,
                                       floor=floor)
    g = frame_gradients(frames, dark, gain, gradients)
    return consistency_maps(g, shifts, window=window, texture=texture, own=own, floor=floor)

