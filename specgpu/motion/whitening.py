"""The whitening of phase correlation, one for every registration of the motion estimate: the frames' whole
gradient images and their tiles, by the fitted peak or the upsampled DFT.

A registration image's spectrum is divided by its magnitude (phase only: what is left of a translation is a linear
phase) and weighted towards low spatial frequencies by a Gaussian (:func:`frequency_weight`): a sub-pixel shift of
a sampled image is a linear phase only well below the Nyquist frequency (interpolation and the pixels' own
footprint bend it towards zero near it, which would bias the estimate towards no motion). The weight of one
spectrum is ``exp(-f^2 / (4 cutoff^2))``, so the product of two is ``exp(-f^2 / (2 cutoff^2))`` and the correlation
peak of a translation a Gaussian of ``1 / (2 pi cutoff)`` px. Two layouts: the half spectrum of a real FFT in
single precision (:func:`whitened_half_spectrum`, :func:`whitened_stack`: the fitted peak of
:mod:`specgpu.motion.registration`) and the full complex spectrum (:func:`whitened_spectrum`: skimage's upsampled
DFT, ``peak="dft"``).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import fft

__all__ = ["hann_window", "hann", "frequency_weight", "whitened_half_spectrum", "whitened_stack",
           "whitened_spectrum"]


@functools.lru_cache(maxsize=16)
def hann_window(shape: tuple) -> np.ndarray:
    """The 2-D Hann window of ``shape`` (float32; phase correlation assumes periodic images)."""
    window = np.outer(np.hanning(shape[0]), np.hanning(shape[1])).astype(np.float32)
    window.flags.writeable = False
    return window


def hann(image: np.ndarray) -> np.ndarray:
    """``image`` under a 2-D Hann window (:func:`hann_window`)."""
    return image * hann_window(image.shape)


@functools.lru_cache(maxsize=32)
def frequency_weight(shape: tuple, cutoff: float, half: bool = True) -> np.ndarray:
    """Gaussian weight ``exp(-f^2 / (4 cutoff^2))`` of one spectrum of an image of ``shape``: the half spectrum of a
    real FFT (``rfft2`` layout, float32) or, with ``half`` False, the full one (``fft2`` layout, float64). Made once
    per (shape, cutoff), not per image (a sequence whitens K whole images and many tiles of the same few shapes)."""
    fy = fft.fftfreq(shape[0])[:, None]
    fx = (fft.rfftfreq(shape[1]) if half else fft.fftfreq(shape[1]))[None, :]
    weight = np.exp(-0.25 * (fx**2 + fy**2) / cutoff**2)
    if half:
        weight = weight.astype(np.float32)
    weight.flags.writeable = False
    return weight


def whitened_half_spectrum(image: np.ndarray, cutoff: float) -> np.ndarray:
    """Phase-only half spectrum of ``image`` under a Hann window, weighted by :func:`frequency_weight`
    (complex64, ``rfft2`` layout)."""
    return whitened_stack(np.asarray(image)[None], cutoff)[0]


def whitened_stack(stack: np.ndarray, cutoff: float) -> np.ndarray:
    """:func:`whitened_half_spectrum` of each image of an (N, H, W) stack."""
    stack = np.asarray(stack, np.float32)
    F = fft.rfft2(stack * hann_window(stack.shape[1:]), axes=(-2, -1), workers=1)
    magnitude = np.abs(F)
    np.maximum(magnitude, 1e-30, out=magnitude)
    np.divide(frequency_weight(stack.shape[1:], float(cutoff)), magnitude, out=magnitude)
    F *= magnitude
    return F


def whitened_spectrum(image: np.ndarray, cutoff: float) -> np.ndarray:
    """Phase-only full spectrum of ``image`` (already windowed), weighted by :func:`frequency_weight` (complex128,
    ``fft2`` layout): what skimage's upsampled DFT registers."""
    F = fft.fft2(image)
    return F / np.maximum(np.abs(F), 1e-30) * frequency_weight(F.shape, float(cutoff), half=False)
