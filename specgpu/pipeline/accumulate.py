"""Temporal accumulation for scenes that hold still (``specgpu stream --accumulate N``): a running estimate per
pixel over up to N sequences, reset where the pixel changes beyond its noise (:class:`AccumulateSink`).

Each new sequence's outputs ``y`` update the running mean ``m`` of ``c`` sequences (``c`` capped at N, so the
estimate follows the last N or so: a recursive mean that becomes an exponential one of time constant N)::

    m <- m + (y - m) / min(c + 1, N)

unless the pixel changed: the RMS over the cube's bands of ``y - m`` exceeds ``threshold`` times its expected
size without a change, ``sigma_rms sqrt(1 + 1 / c)`` (``sigma_rms``: the RMS of the per-band standard deviations,
the stream's ``sigma_rms`` or the last channel of ``sigma``). There the estimate restarts from ``y`` (``c = 1``),
so a moving object leaves no trail longer than one sequence. Only outputs linear in the frames are averaged
(``coefficients``, ``cube``, ``XYZ``): the mean of Lab or dE is not those of the averaged frames. The sigma maps
stay those of one sequence (the accumulated noise falls as ``1 / sqrt(c)``, the prior's mismatch does not).
"""

from __future__ import annotations

import numpy as np

from specgpu.core.validate import check_number

__all__ = ["ACCUMULATED_OUTPUTS", "AccumulateSink"]

#: The stream outputs the accumulation averages.
ACCUMULATED_OUTPUTS = ("coefficients", "cube", "XYZ")


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

    Attributes
    ----------
    counts : numpy.ndarray or None
        (H, W) sequences in each pixel's current estimate.
    resets : list of float
        Per result after the first, the fraction of pixels restarted.
    """

    def __init__(self, sequences: int, outputs, *, threshold: float = 3.0):
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
        self.mean: dict | None = None
        self.counts = None
        self.resets: list[float] = []

    def write(self, result) -> None:
        a = result.arrays
        y = {name: np.asarray(a[name], np.float32) for name in self.names}
        if "sigma_rms" in a:
            s = np.asarray(a["sigma_rms"], np.float32).reshape(y["cube"].shape[:2])
        else:
            s = np.asarray(a["sigma"], np.float32)[..., -1]
        if self.mean is None or self.mean["cube"].shape != y["cube"].shape:
            self.mean = {name: v.copy() for name, v in y.items()}
            self.counts = np.ones(y["cube"].shape[:2], np.int64)
            return
        c = self.counts
        d = np.sqrt(np.mean((y["cube"] - self.mean["cube"]) ** 2, axis=-1))
        still = d <= self.threshold * s * np.sqrt(1.0 + 1.0 / c)  # NaN (saturated) is a change
        c = np.where(still, np.minimum(c + 1, self.N), 1)
        w = (1.0 / c).astype(np.float32)[..., None]
        for name in self.names:
            m = self.mean[name] + (y[name] - self.mean[name]) * w
            m = np.where(still[..., None], m, y[name])
            self.mean[name] = m
            a[name][...] = m  # in place: the sinks after this one see the estimate
        self.counts = c
        self.resets.append(float(1.0 - still.mean()))

    def close(self) -> None:
        pass
