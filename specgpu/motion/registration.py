"""Fast phase correlation of gradient images: what the global motion estimate of a live stream can afford.

The estimate of :mod:`specgpu.motion.global_motion` registers every pair of a sequence's frames (36 for K = 9) and a
few tiles of each frame. Three things make that cheap enough to keep up with a camera on a few CPU cores:

* **Real FFTs in single precision.** The registration images are real, so each spectrum is a half spectrum
  (``scipy.fft.rfft2``, float32 in, complex64 out) and each correlation surface one ``irfft2``: a quarter of the
  work of a complex double-precision FFT, and the same result to far below the estimate's noise.
* **The sub-pixel peak by a fit, not an upsampled DFT.** The whitened cross-power spectrum carries a Gaussian
  weight (:func:`frequency_weight`, ``exp(-f^2 / (2 cutoff^2))`` over the pair), so the correlation surface of a
  translation is a Gaussian of standard deviation ``1 / (2 pi cutoff)`` px around it (1.3 px at the default
  cutoff), sampled at the pixels. The logarithm of a Gaussian is a parabola: three samples through the peak along
  each axis give its centre exactly, with no upsampled DFT around it (what ``skimage``'s
  ``phase_cross_correlation`` spends most of its time on).
* **The gradient images by slicing** (:func:`sobel_magnitude`): the Sobel operator as a few whole-array float32
  additions, the result of ``scipy.ndimage.sobel`` (its ``reflect`` border) at a fraction of its time.

The correlation surface also says whether its peak can be trusted: :func:`second_peak_ratio`, the highest value
away from the main peak over the main peak, is high where two motions compete (an object moving on its own over
the scene) or where the scene repeats itself; only then is the slower check on tiles worth its time.
"""

from __future__ import annotations

import threading

import numpy as np
from scipy import fft

from specgpu.motion.whitening import frequency_weight, hann_window, whitened_half_spectrum, whitened_stack

# the whitening (specgpu.motion.whitening) is named here too: registration takes its spectra
__all__ = ["sobel_magnitude", "bin_image", "hann_window", "frequency_weight", "whitened_half_spectrum",
           "half_spectrum_energy", "correlation_surface", "fit_peak", "fit_peak_within", "fit_peaks", "peak_at",
           "peaks_at", "peak_error", "second_peak_ratio", "tile_displacements", "whitened_stack"]


def sobel_magnitude(image: np.ndarray) -> np.ndarray:
    """Gradient magnitude ``hypot(sobel(f, 0), sobel(f, 1))`` of a 2-D image as ``scipy.ndimage.sobel`` makes it
    (borders mirrored, ``mode="reflect"``), float32, by whole-array slicing into scratch arrays kept per thread
    (fresh temporaries of a frame's size cost more in page faults than the arithmetic)."""
    f = np.asarray(image, np.float32)
    h, w = f.shape
    p, s, gx = _scratch(("sobel", h, w), ((h + 2, w + 2), (h + 2, w + 2), (h, w)))
    p[1:-1, 1:-1] = f  # mirrored by one pixel: scipy's "reflect" repeats the edge
    p[0, 1:-1], p[-1, 1:-1] = f[0], f[-1]
    p[:, 0], p[:, -1] = p[:, 1], p[:, -2]
    # derivative along rows (axis 0) of the image smoothed [1, 2, 1] along columns, and the transpose
    sx = s[:, :w]
    np.multiply(p[:, 1:-1], 2.0, out=sx)
    sx += p[:, :-2]
    sx += p[:, 2:]
    gy = np.subtract(sx[2:], sx[:-2])
    sy = s[:h]
    np.multiply(p[1:-1], 2.0, out=sy)
    sy += p[:-2]
    sy += p[2:]
    np.subtract(sy[:, 2:], sy[:, :-2], out=gx)
    gy *= gy
    gx *= gx
    gy += gx
    return np.sqrt(gy, out=gy)


_SCRATCH = threading.local()


def _scratch(key, shapes) -> list:
    """float32 arrays of ``shapes`` kept by the calling thread under ``key`` (reused by its next call)."""
    kept = getattr(_SCRATCH, "arrays", None)
    if kept is None:
        kept = _SCRATCH.arrays = {}
    if key not in kept:
        kept[key] = [np.empty(shape, np.float32) for shape in shapes]
    return kept[key]


def bin_image(image: np.ndarray, binning: int) -> np.ndarray:
    """``image`` averaged over ``binning`` x ``binning`` blocks (a remainder row or column dropped), float32."""
    f = np.asarray(image, np.float32)
    if binning <= 1:
        return f
    h, w = (f.shape[0] // binning) * binning, (f.shape[1] // binning) * binning
    return f[:h, :w].reshape(h // binning, binning, w // binning, binning).mean(axis=(1, 3), dtype=np.float32)


def half_spectrum_energy(F: np.ndarray, width: int) -> float:
    """Sum of |F|^2 over the whole spectrum of an image ``width`` wide of which ``F`` is the ``rfft2`` half (the
    columns mirrored in the other half counted twice: all but the first and, for an even width, the last)."""
    power = np.einsum("ij,ij->j", F.real, F.real) + np.einsum("ij,ij->j", F.imag, F.imag)
    return float(power.sum() * 2.0 - power[0] - (power[-1] if width % 2 == 0 else 0.0))


def peak_error(top: float, energy_a: float, energy_b: float, size: int) -> float:
    """The registration error of a correlation peak of height ``top`` between two spectra of
    :func:`half_spectrum_energy` ``energy_a`` and ``energy_b`` over a surface of ``size`` samples: near 0 where the
    images match once moved, near 1 where they share little."""
    amp = energy_a * energy_b / float(size) ** 2
    return float(np.sqrt(abs(1.0 - top * top / max(amp, 1e-30))))


def correlation_surface(Fa: np.ndarray, Fb: np.ndarray, shape: tuple) -> np.ndarray:
    """(H, W) float32 phase correlation of two :func:`whitened_half_spectrum` s of images of ``shape``: it peaks
    at the displacement of the content of image b relative to image a (periodic: index -1 is -1 px)."""
    return fft.irfft2(Fb * np.conj(Fa), s=shape, workers=1)


def _vertex(left: np.ndarray, centre: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Offsets in [-0.5, 0.5] of the maxima of the Gaussians (or, where a sample is not positive, the parabolas)
    through three samples one apart, each argument one sample of every triple (float64 arrays)."""
    positive = (left > 0.0) & (right > 0.0) & (centre > 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        left, centre, right = (np.where(positive, np.log(np.where(positive, v, 1.0)), v) for v in (left, centre, right))
        curvature = left - 2.0 * centre + right
        # no maximum between them (a flat or noisy top): the sample itself
        offset = np.where(curvature < 0.0, 0.5 * (left - right) / curvature, 0.0)
    return np.clip(offset, -0.5, 0.5)


def fit_peak(surface: np.ndarray) -> tuple[np.ndarray, float]:
    """(x, y) of the highest peak of a periodic correlation surface, sub-pixel by a Gaussian through the three
    samples across it along each axis, in [-N/2, N/2) px; and the peak's value."""
    d, top = fit_peaks(np.asarray(surface)[None])
    return d[0], float(top[0])


def _window(surface: np.ndarray, within: int | None):
    """The rows and columns of a periodic surface within ``within`` px of zero displacement along each axis
    (index arrays, wrapping round), or None where that window holds the whole surface."""
    h, w = surface.shape
    if within is None or 2 * int(within) + 1 >= min(h, w):
        return None
    r = np.arange(-int(within), int(within) + 1)
    return r % h, r % w


def fit_peak_within(surface: np.ndarray, within: int | None) -> tuple[np.ndarray, float]:
    """:func:`fit_peak` of the highest sample at most ``within`` px from zero displacement along each axis (None:
    anywhere): a displacement the motion cannot have reached (a repeating scene's peak a period away) is not
    looked at. The sub-pixel fit reads the samples on either side, inside the window or not."""
    rc = _window(surface, within)
    if rc is None:
        return fit_peak(surface)
    rows, cols = rc
    box = surface[np.ix_(rows, cols)]
    i, j = np.unravel_index(int(np.argmax(box)), box.shape)
    y, x = int(rows[i]), int(cols[j])
    return peak_at(surface, y, x), float(surface[y, x])


def fit_peaks(surfaces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_peak` of each surface of an (N, H, W) stack at once: (N, 2) peaks (x, y) and (N,) their values."""
    surfaces = np.asarray(surfaces)
    n, h, w = surfaces.shape
    y, x = np.divmod(np.argmax(surfaces.reshape(n, -1), axis=1), w)
    return peaks_at(surfaces, y, x), surfaces[np.arange(n), y, x].astype(np.float64)


def peak_at(surface: np.ndarray, y: int, x: int) -> np.ndarray:
    """(x, y) of the peak of a periodic correlation surface whose top sample is at row ``y``, column ``x``,
    sub-pixel as :func:`fit_peak` locates it, in [-N/2, N/2) px."""
    return peaks_at(np.asarray(surface)[None], np.array([int(y)]), np.array([int(x)]))[0]


def peaks_at(surfaces: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """:func:`peak_at` of each surface of an (N, H, W) stack, its top sample at (``y[i]``, ``x[i]``): (N, 2)."""
    n, h, w = surfaces.shape
    rows = np.arange(n)

    def at(yy, xx):
        return surfaces[rows, yy, xx].astype(np.float64)

    c = at(y, x)
    dy = _vertex(at((y - 1) % h, x), c, at((y + 1) % h, x))
    dx = _vertex(at(y, (x - 1) % w), c, at(y, (x + 1) % w))
    return np.stack([(x + w // 2) % w - w // 2 + dx, (y + h // 2) % h - h // 2 + dy], axis=1)


def _circular_max(a: np.ndarray, start: int, length: int, axis: int) -> float:
    """Largest value of ``a`` over ``length`` indices from ``start`` along ``axis``, wrapping round (views)."""
    n = a.shape[axis]
    start %= n
    parts = [(start, min(start + length, n)), (0, max(start + length - n, 0))]
    return max(float((a[lo:hi] if axis == 0 else a[:, lo:hi]).max()) for lo, hi in parts if hi > lo)


def second_peak_ratio(surface: np.ndarray, peak: np.ndarray, radius: int, within: int | None = None) -> float:
    """The highest value of a periodic correlation surface more than ``radius`` px (along either axis) from
    ``peak`` (x, y), over the value at ``peak``'s nearest sample: near 1 where two displacements compete.
    ``within``: only displacements at most that far from zero along each axis compete (the window of
    :func:`fit_peak_within`); None: the whole surface."""
    h, w = surface.shape
    x, y = int(round(peak[0])) % w, int(round(peak[1])) % h
    top = float(surface[y, x])
    side = 2 * radius + 1
    rc = _window(surface, within)
    if rc is not None:
        if top <= 0.0:
            return 1.0
        rows, cols = rc
        box = surface[np.ix_(rows, cols)].copy()
        # the peak's own (2 radius + 1)^2 samples, where they fall in the window, do not compete
        dy = (rows - y + h // 2) % h - h // 2
        dx = (cols - x + w // 2) % w - w // 2
        box[np.ix_(np.abs(dy) <= radius, np.abs(dx) <= radius)] = -np.inf
        rest = float(box.max())
        return rest / top if np.isfinite(rest) else 0.0
    if top <= 0.0 or side >= min(h, w):
        return 1.0  # no clear top, or no sample far enough from it
    band = surface[np.arange(y - radius, y + radius + 1) % h]  # the rows about the peak (a small copy)
    rest = max(_circular_max(surface, y + radius + 1, h - side, 0), _circular_max(band, x + radius + 1, w - side, 1))
    return rest / top


def tile_displacements(g_ref: np.ndarray, g_k: np.ndarray, shift, cutoff: float, tiles: int,
                       reference_spectra: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 2) of the ``tiles`` x ``tiles`` tiles of the reference image ``g_ref`` and where image
    ``g_k`` saw each (N, 2): every tile registered (all at once, by :func:`fit_peak`) where the global ``shift``
    (x, y) puts it in ``g_k``; tiles it moves off the field are skipped. ``reference_spectra``: a dict kept by the
    caller across the frames of a sequence, so the reference's tiles are transformed once."""
    h, w = g_ref.shape
    th, tw = h // tiles, w // tiles
    t = np.rint(np.asarray(shift, np.float64)).astype(int)
    cells = [(i * th, j * tw) for i in range(tiles) for j in range(tiles)
             if 0 <= i * th + t[1] and i * th + t[1] + th <= h and 0 <= j * tw + t[0] and j * tw + t[0] + tw <= w]
    if not cells:
        return np.zeros((0, 2)), np.zeros((0, 2))
    cache = {} if reference_spectra is None else reference_spectra
    key = (id(g_ref), tiles, float(cutoff))
    if key not in cache:
        stack = np.stack([g_ref[i * th:(i + 1) * th, j * tw:(j + 1) * tw] for i in range(tiles)
                          for j in range(tiles)])
        cache[key] = whitened_stack(stack, cutoff)
    ref = cache[key]
    index = [(y0 // th) * tiles + x0 // tw for y0, x0 in cells]
    moving = whitened_stack(np.stack([g_k[y0 + t[1]:y0 + t[1] + th, x0 + t[0]:x0 + t[0] + tw]
                                       for y0, x0 in cells]), cutoff)
    surfaces = fft.irfft2(moving * np.conj(ref[index]), s=(th, tw), axes=(-2, -1), workers=1)
    src = np.array([[x0 + (tw - 1) / 2.0, y0 + (th - 1) / 2.0] for y0, x0 in cells])
    return src, src + t + fit_peaks(surfaces)[0]
