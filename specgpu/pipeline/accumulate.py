"""Temporal accumulation (``specgpu stream --accumulate N``): a running estimate per pixel over up to N sequences,
reset where the pixel changes beyond its noise (:class:`AccumulateSink`); under ``--motion`` it moves with the scene.

Each new sequence's outputs ``y`` update the running mean ``m`` of ``c`` sequences (``c`` capped at N, so the
estimate follows the last N or so: a recursive mean that becomes an exponential one of time constant N)::

    m <- m + (y - m) / min(c + 1, N)

unless the pixel changed: the RMS over the cube's bands of ``y - m`` exceeds ``threshold`` times its expected
size without a change, ``sigma_rms sqrt(1 + 1 / c)`` (``sigma_rms``: the RMS of the per-band standard deviations,
the stream's ``sigma_rms`` or the last channel of ``sigma``). There the estimate restarts from ``y`` (``c = 1``),
so a moving object leaves no trail longer than one sequence. Only outputs linear in the frames are averaged
(``coefficients``, ``cube``, ``XYZ``): the mean of Lab or dE is not those of the averaged frames.

**The sigma of the estimate**: the sigma maps (``sigma``, ``sigma_rms``) are replaced by the estimate's own, so a
recording's uncertainty stays true. Each pixel keeps the factor ``v`` by which the running estimate's noise
variance is below one sequence's: 1 at a (re)start, and after an update of weight ``w = 1 / min(c + 1, N)``
``v <- (1 - w)^2 v + w^2`` (``1 / c`` while ``c <= N``, tending to ``1 / (2 N - 1)`` beyond). The noise part of
the variance (what the frames show) is scaled by ``v``; the prior's mismatch (the plan's constant variance, the
same in every sequence) is not averaged down and stays. The change test expects ``sigma_rms sqrt(1 + v)``, one
sequence's sigma against the estimate's.

**Along the motion** (``stream --accumulate N --motion global|affine``): each sequence is decoded at its own
reference time, and the scene has moved between two of them. Before the update the running estimate (and its
counts) is moved with the scene: the displacement between the two sequences is registered on their decoded cubes
(the band mean's gradient image, phase correlation with a sub-pixel peak as the frames within a sequence are
registered, then refined on tiles so that an object moving on its own does not pull it; two reflectance maps need
no illuminant in common), and the estimate is resampled where the new
sequence's pixels were (:func:`shift_image`, cubic convolution; NaN, so restarted, where they were outside the
field, more than half a pixel beyond an edge pixel's centre). The change
test then restarts every pixel the translation does not carry: an object moving on its own, a surface that came
into view, a registration that failed. The sigma is the motion decoder's ``sigma_rms`` at the warped samples (each
sample's variance over the squared bilinear weights of the pixels it reads). Each resampling by a fraction of a
pixel weighs neighbouring pixels of the estimate, which softens detail near the sampling frequency a little
(cubic convolution rather than bilinear interpolation keeps repeated resampling from blurring fine texture); a
translation by whole pixels is exact.
"""

from __future__ import annotations

import numpy as np

from specgpu.core.validate import check_number
from specgpu.motion.images import gradient_image
from specgpu.motion.registration import correlation_surface, fit_peak, tile_displacements, whitened_half_spectrum

__all__ = ["ACCUMULATED_OUTPUTS", "AccumulateSink", "sequence_displacement", "shift_image"]

#: The correlation weight's cutoff (cycles per pixel) of the registration between sequences, the within-sequence
#: estimate's default.
CUTOFF = 0.12
#: The grid of tiles (per side, at most; none smaller than MIN_TILE_PX) registered about the whole-image peak, and
#: how near their median a tile counts.
TILES = 4
MIN_TILE_PX = 32
AGREE_PX = 0.5

#: The stream outputs the accumulation averages.
ACCUMULATED_OUTPUTS = ("coefficients", "cube", "XYZ")
#: The sigma maps it makes the running estimate's.
SIGMA_OUTPUTS = ("sigma", "sigma_rms")


class AccumulateSink:
    """A stream sink, first in line, that replaces each result's linear outputs by their running estimate (see
    the module notes); the sinks after it see the accumulated maps.

    Parameters
    ----------
    sequences : int
        N, the most sequences averaged (>= 2).
    outputs : sequence of str
        The stream's outputs: ``cube`` and ``sigma`` or ``sigma_rms`` are needed (the change test), Lab and dE
        refused.
    threshold : float
        The change test's multiple of the expected difference (default 3).
    motion : bool
        Move the estimate with the scene between sequences (see the module notes).
    constant_variance : array_like, optional
        (B,) the variance of each plan output that no frame shows (the prior's mismatch:
        :func:`specgpu.planning.uncertainty.constant_variance`), kept as it is in the accumulated sigma; default
        none.

    Attributes
    ----------
    counts : numpy.ndarray or None
        (H, W) sequences in each pixel's current estimate.
    factor : numpy.ndarray or None
        (H, W) the estimate's noise variance over one sequence's (see the module notes).
    resets : list of float
        Per result after the first, the fraction of pixels restarted.
    shifts : list of numpy.ndarray
        With ``motion``, per result after the first: the (x, y) displacement of the scene since the previous one.
    """

    def __init__(self, sequences: int, outputs, *, threshold: float = 3.0, motion: bool = False,
                 constant_variance=None):
        self.N = int(check_number("--accumulate", sequences, integer=True, low=2, high=1_000_000))
        self.threshold = float(check_number("threshold", threshold, low=0, low_open=True))
        outputs = tuple(outputs)
        bad = [o for o in outputs if o in ("Lab", "dE", "dE_sigma")]
        if bad:
            raise ValueError(f"--accumulate averages {', '.join(ACCUMULATED_OUTPUTS)}; {', '.join(bad)} are not "
                             "linear in the frames and cannot be accumulated (leave them out)")
        if "cube" not in outputs or not {"sigma", "sigma_rms"} & set(outputs):
            raise ValueError("--accumulate needs the cube and sigma (or sigma_rms) outputs: a pixel's change is "
                             "judged against its noise")
        self.names = [o for o in ACCUMULATED_OUTPUTS if o in outputs]
        self.motion = bool(motion)
        self.mean: dict | None = None
        self.counts = None
        self.factor = None
        k = np.zeros(0) if constant_variance is None else np.asarray(constant_variance, np.float64).reshape(-1)
        if not np.all(np.isfinite(k)) or np.any(k < 0):
            raise ValueError("constant_variance must be finite and >= 0")
        self.constant = k
        self.resets: list[float] = []
        self.shifts: list[np.ndarray] = []
        self._image = None

    def write(self, result) -> None:
        a = result.arrays
        y = {name: np.asarray(a[name], np.float32) for name in self.names}
        if "sigma_rms" in a:
            s = np.asarray(a["sigma_rms"], np.float32).reshape(y["cube"].shape[:2])
        else:
            s = np.asarray(a["sigma"], np.float32)[..., -1]
        image = cube_registration_image(y["cube"]) if self.motion else None
        if self.mean is None or self.mean["cube"].shape != y["cube"].shape:
            self.mean = {name: v.copy() for name, v in y.items()}
            self.counts = np.ones(y["cube"].shape[:2], np.int64)
            self.factor = np.ones(y["cube"].shape[:2], np.float32)
            self._image = image
            return
        if self.motion:  # the estimate moved with the scene to this sequence's reference time
            shift = displacement(self._image, image)
            self._image = image
            self.shifts.append(shift)
            self.mean = {name: shift_image(m, shift) for name, m in self.mean.items()}
            self.counts = np.maximum(shift_image(self.counts, np.round(shift), fill=0), 1)  # 1 where it was out
            factor = shift_image(self.factor, shift)
            self.factor = np.where(np.isfinite(factor), np.clip(factor, 0.0, 1.0), 1.0).astype(np.float32)
        c, v = self.counts, self.factor
        diff = y["cube"] - self.mean["cube"]
        d = np.sqrt(np.einsum("hwb,hwb->hw", diff, diff) / np.float32(diff.shape[-1]))
        still = d <= self.threshold * s * np.sqrt(1.0 + v)  # NaN (saturated, out of the field) is a change
        c = np.where(still, np.minimum(c + 1, self.N), 1)
        w = (1.0 / c).astype(np.float32)
        self.factor = np.where(still, (1.0 - w) ** 2 * v + w * w, 1.0).astype(np.float32)
        w = w[..., None]
        changed = ~still
        for name in self.names:  # m + (y - m) / c in place, then the restarted pixels set to y
            m = self.mean[name]
            step = diff if name == "cube" else y[name] - m
            step *= w
            m += step
            m[changed] = y[name][changed]
            a[name][...] = m  # in place: the sinks after this one see the estimate
        self.counts = c
        self.resets.append(float(1.0 - still.mean()))
        self._scale_sigma(a)

    def _scale_sigma(self, a) -> None:
        """The result's sigma maps, in place, made the running estimate's: the noise variance times
        :attr:`factor`, the constant variance kept (see the module notes)."""
        v = self.factor
        rms = np.float32(self.constant.mean()) if self.constant.size else np.float32(0.0)
        for name in SIGMA_OUTPUTS:
            if name not in a:
                continue
            sigma = a[name]
            f = v.reshape(v.shape + (1,) * (sigma.ndim - 2))
            # the RMS channel's constant is the mean of the constant variances
            k = rms if name == "sigma_rms" or not self.constant.size else np.append(self.constant, rms)
            sigma2 = np.asarray(sigma, np.float32) ** 2
            sigma[...] = np.sqrt(f * np.maximum(sigma2 - k, 0.0) + k)

    def close(self) -> None:
        pass


def cube_registration_image(cube) -> np.ndarray:
    """The image two sequences' decoded ``cube`` s (H, W, B) are registered on: the gradient image of the band mean
    (non-finite pixels at the field's mean)."""
    image = np.mean(np.asarray(cube, np.float32), axis=-1)
    bad = ~np.isfinite(image)
    if bad.any():
        image[bad] = float(np.mean(image[~bad])) if not bad.all() else 0.0
    return gradient_image(image)


def displacement(previous, image) -> np.ndarray:
    """(x, y) displacement, px, of the content of :func:`cube_registration_image` ``image`` relative to ``previous``:
    the whole-image correlation peak, then the tiles of a grid of up to :data:`TILES` x :data:`TILES` registered
    about it and the mean of those within :data:`AGREE_PX` of their median (an object moving on its own pulls the
    whole-image peak; it holds few tiles). Images too small for 2 x 2 tiles of :data:`MIN_TILE_PX` keep the
    whole-image peak."""
    shape = np.shape(image)
    d = fit_peak(correlation_surface(whitened_half_spectrum(previous, CUTOFF), whitened_half_spectrum(image, CUTOFF),
                                     shape))[0]
    tiles = min(TILES, min(shape) // MIN_TILE_PX)
    if tiles < 2:
        return d
    src, dst = tile_displacements(previous, image, d, CUTOFF, tiles)
    if len(src) < 3:
        return d
    t = dst - src
    median = np.median(t, axis=0)
    near = np.abs(t - median).max(axis=1) <= AGREE_PX
    return t[near].mean(axis=0) if near.sum() >= 3 else median


def sequence_displacement(previous_cube, cube) -> np.ndarray:
    """(x, y) displacement, px, of the scene in the decoded ``cube`` (H, W, B) since ``previous_cube``: where a
    point seen at x in the previous one is seen now, x + d."""
    return displacement(cube_registration_image(previous_cube), cube_registration_image(cube))


def shift_image(a, shift, *, fill=np.nan) -> np.ndarray:
    """``a`` (H, W, ...) moved by ``shift`` (x, y) px: ``out(x) = a(x - shift)``, by separable cubic convolution
    (Keys, a = -1/2: exact for whole pixels and for quadratics, far less smoothing than bilinear, so repeated
    resampling keeps texture). The field is the pixels' footprint: ``fill`` only where the sample point lies more
    than half a pixel beyond an edge pixel's centre; nearer the edge the taps are clamped to it. Where a tap reads
    a NaN the nearest sample is taken, so a NaN stays one pixel instead of spreading over the taps' reach. Float
    arrays come back float32; integer ones (whole-pixel shifts only, a finite ``fill``) as they are."""
    a = np.asarray(a)
    if a.dtype.kind in "iu":
        if not np.isfinite(fill):
            raise ValueError(f"an integer image needs a finite fill, got {fill!r}")
        out = a
    else:
        out = np.asarray(a, np.float32)  # never written: each axis makes a new array
    for axis, d in ((1, float(shift[0])), (0, float(shift[1]))):
        out = _shift_axis(out, -d, axis, fill)
    return out


def _keys(t: float) -> np.ndarray:
    """The four cubic-convolution weights (Keys, a = -1/2) of the samples at -1, 0, 1, 2 for a point ``t`` in
    [0, 1) past sample 0."""
    return np.array([((-0.5 * t + 1.0) * t - 0.5) * t,
                     (1.5 * t - 2.5) * t * t + 1.0,
                     ((-1.5 * t + 2.0) * t + 0.5) * t,
                     (0.5 * t - 0.5) * t * t], np.float64)


def _along(a: np.ndarray, axis: int, start: int, stop: int) -> np.ndarray:
    """``a[start:stop]`` along ``axis`` (a view)."""
    index = [slice(None)] * a.ndim
    index[axis] = slice(start, stop)
    return a[tuple(index)]


def _shift_axis(a: np.ndarray, s: float, axis: int, fill) -> np.ndarray:
    """``out[j] = a(j + s)`` along ``axis``: the sample itself for whole pixels (``fill`` off the field); else the
    cubic convolution of the four samples about ``j + s``, clamped to the field, ``fill`` where ``j + s`` is outside
    [-1/2, n - 1/2], the nearest sample where a tap is NaN."""
    n = a.shape[axis]
    i = int(np.floor(s))
    t = s - i
    if t and a.dtype.kind in "iu":
        raise ValueError(f"an integer image moves by whole pixels only, got {-s!r}")
    out = np.full_like(a, fill)
    if not t:
        lo, hi = max(0, -i), min(n, n - i)
        if hi > lo:
            _along(out, axis, lo, hi)[...] = _along(a, axis, lo + i, hi + i)
        return out
    inside = np.flatnonzero(np.abs(np.arange(n) + s - (n - 1) / 2.0) <= n / 2.0)
    if not len(inside):
        return out
    lo, hi = int(inside[0]), int(inside[-1]) + 1
    # two samples of the edge beyond each end: the taps clamped to the field, read as plain slices
    padded = np.pad(a, [(2, 2) if ax == axis else (0, 0) for ax in range(a.ndim)], mode="edge")
    acc = _along(out, axis, lo, hi)  # a view: the taps are summed in place, with one scratch array
    scratch = None
    for j, (tap, w) in enumerate(zip((-1, 0, 1, 2), _keys(t))):
        src = _along(padded, axis, lo + i + tap + 2, hi + i + tap + 2)
        if j == 0:
            np.multiply(src, np.float32(w), out=acc)
        else:
            scratch = np.multiply(src, np.float32(w), out=scratch)
            acc += scratch
    bad = np.isnan(acc)
    if bad.any():  # a NaN among the taps: the nearest sample (NaN only if it is)
        nearest = _along(padded, axis, lo + i + int(t >= 0.5) + 2, hi + i + int(t >= 0.5) + 2)
        acc[bad] = nearest[bad]
    return out
