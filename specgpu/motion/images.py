"""The spectrum-independent images a sequence's motion is registered and checked on.

Edges stay where they are whatever the illuminant, while the relative brightness of two surfaces does not: the
gradient magnitude of each dark-subtracted, flat-fielded frame normalised by its mean keeps the first and discards
the sign of the second, and phase correlation whitens what is left. So no extra frame is needed. The images are made
on the OpenCL device where it takes the inputs as they are (:func:`specgpu.engine.gradients.gradient_images`), on
the host otherwise (:func:`gradient_image`).
"""

from __future__ import annotations

import numpy as np

from specgpu.engine.gradients import gradient_images
from specgpu.motion.registration import bin_image, sobel_magnitude
from specgpu.motion.whitening import hann

__all__ = ["gradient_image", "registration_image", "frame_gradients", "device_takes"]


def gradient_image(frame, dark=None, gain=None, *, binning: int = 1) -> np.ndarray:
    """The spectrum-independent image a frame is registered on: gradient magnitude (Sobel) of the
    dark-subtracted, flat-fielded frame over its mean, float32; ``binning`` averages b x b pixels first."""
    f = np.subtract(frame, dark, dtype=np.float32) if dark is not None else np.array(frame, np.float32)
    if gain is not None:  # a NaN gain (a pixel with no response) reads 0 here: one NaN would spoil the FFTs
        f *= np.nan_to_num(np.asarray(gain, np.float32), nan=0.0)
    f = bin_image(f, binning)
    mean = float(np.mean(f, dtype=np.float64))
    g = sobel_magnitude(f)  # linear in f: the division by the mean on the result
    if mean > 0:
        g *= np.float32(1.0 / mean)
    return g



def registration_image(frame, dark=None, gain=None, *, binning: int = 1) -> np.ndarray:
    """:func:`gradient_image` under a Hann window."""
    return hann(gradient_image(frame, dark, gain, binning=binning))



def frame_gradients(frames, dark=None, gain=None, gradients=None, which=None, device=None) -> list:
    """Each frame's :func:`gradient_image` (``dark``: (H, W) or one per frame), taking those already made
    (``gradients``: a sequence with None where one is to be made, or None); ``which``: only those frames, None for
    the others. The ones to make are made together on the OpenCL ``device`` (a selector or queue; default: the
    default device; :func:`specgpu.engine.gradients.gradient_images`, equal to the host's to float32 rounding, a
    tenth of its time); on the host where the device cannot take the inputs as they are (an integer type other
    than uint8 or uint16, a dark frame or flat field that is not finite)."""
    dark = None if dark is None else np.asarray(dark, np.float32)
    wanted = range(len(frames)) if which is None else {int(k) for k in which}
    out = [gradients[k] if gradients is not None and k in wanted else None for k in range(len(frames))]
    made = [k for k in range(len(frames)) if k in wanted and out[k] is None]
    if not made:
        return out

    def dark_of(k):
        return None if dark is None else (dark[k] if dark.ndim == 3 else dark)

    frames = np.asarray(frames)
    stack = frames if len(made) == len(frames) else frames[made]  # every frame (the usual case): no copy
    if device_takes(stack, dark, gain):
        per_frame = None if dark is None else (dark[made] if dark.ndim == 3 else dark)
        for k, image in zip(made, gradient_images(stack, per_frame, gain, device=device).get()):
            out[k] = image
    else:
        for k in made:
            out[k] = gradient_image(frames[k], dark_of(k), gain)
    return out


def device_takes(frames: np.ndarray, dark, gain) -> bool:
    """Whether :func:`specgpu.engine.gradients.gradient_images` takes these inputs as :func:`gradient_image` does:
    uint8, uint16 or float frames (float64 is made float32 by both), a finite dark frame, a flat field with no
    infinity (a NaN reads 0 in both). (The device refuses the others, the host computes on.)"""
    if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        return False
    if frames.dtype == np.float64 and np.abs(frames[np.isfinite(frames)]).max(initial=0.0) > np.finfo(np.float32).max:
        return False
    return (dark is None or bool(np.isfinite(dark).all())) and (
        gain is None or not bool(np.isinf(np.asarray(gain, np.float32)).any()))

