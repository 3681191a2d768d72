"""The denoiser's case of ``specgpu bench`` (``guided_filter``): what ``recover --denoise`` and ``stream --denoise``
filter for a 9-frame plan, the 9 coordinates of its outputs in their subspace
(:func:`specgpu.pipeline.denoise.output_subspace`), float32, smoothed by the guided filter (radius and eps its
defaults) on the device (:func:`specgpu.engine.guided.guided_filter_device`, data and output on the device),
against the same filter of the same image in NumPy with SciPy's box filter (windows clipped to the image, as the
kernels). The two are timed in interleaved rounds, so both see the same load of the machine; the case's speedup
is the median over the rounds of each round's ratio."""

from __future__ import annotations

import statistics
import time

import numpy as np
import pyopencl.array as cla

from specgpu.engine.guided import guided_filter, guided_filter_device
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS

__all__ = ["BANDS", "guided_numpy", "guided_case"]

BANDS = 9


def guided_numpy(p, g, radius: int, eps: float) -> np.ndarray:
    """The guided filter in NumPy / SciPy (float32): box means by ``scipy.ndimage.uniform_filter`` over the
    window clipped to the image (the sum over the window inside, divided by the count inside)."""
    from scipy.ndimage import uniform_filter  # scipy: heavy, needed by this case alone

    size = 2 * radius + 1
    count = uniform_filter(np.ones(g.shape, np.float32), size, mode="constant")

    def box(a):
        if a.ndim == 3:
            return uniform_filter(a, (size, size, 1), mode="constant") / count[..., None]
        return uniform_filter(a, size, mode="constant") / count

    mg, mp = box(g), box(p)
    a = (box(g[..., None] * p) - mg[..., None] * mp) / (np.maximum(box(g * g) - mg * mg, 0.0)[..., None] + eps)
    b = mp - a * mg[..., None]
    return box(a) * g[..., None] + box(b)


def _ms(fn) -> float:
    start = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - start)


def guided_case(queue, width: int, height: int, reps, row):
    """Time the device filter (data on the device, enqueue + finish), the NumPy-in / NumPy-out call and the NumPy
    baseline in ``reps[1]`` interleaved rounds (each round ``reps[0] // reps[1]`` device calls, at least one, and
    one call of the others); ``row`` is the bench's row builder. The row's times are medians over every call, its
    speedup the median of the rounds' ratios (baseline / the round's median device time)."""
    rng = np.random.default_rng(3)
    g = rng.uniform(0.2, 1.0, (height, width)).astype(np.float32)
    p = (g[..., None] * rng.uniform(0.1, 0.9, BANDS) + rng.normal(0, 0.01, (height, width, BANDS))).astype(np.float32)
    p_dev, g_dev = cla.to_device(queue, p), cla.to_device(queue, g)
    out = cla.empty(queue, p.shape, np.float32)

    def device():
        guided_filter_device(queue, p_dev, g_dev, DENOISE_RADIUS, DENOISE_EPS, out=out)
        queue.finish()

    expected = None

    def baseline():
        nonlocal expected
        expected = guided_numpy(p, g, DENOISE_RADIUS, DENOISE_EPS)

    device()  # program build, intermediates made
    rounds, per_round = max(1, reps[1]), max(1, reps[0] // max(1, reps[1]))
    device_ms, api_ms, baseline_ms, ratios = [], [], [], []
    for _ in range(rounds):
        times = [_ms(device) for _ in range(per_round)]
        device_ms += times
        baseline_ms.append(_ms(baseline))
        api_ms.append(_ms(lambda: guided_filter(p, g, radius=DENOISE_RADIUS, eps=DENOISE_EPS, device=queue)))
        ratios.append(baseline_ms[-1] / statistics.median(times))
    result = out.get()
    diff = float(np.max(np.abs(result - expected))) / max(float(np.max(np.abs(expected))), 1e-30)
    case = row("guided_filter", width, height, None, statistics.median(device_ms), statistics.median(api_ms),
               statistics.median(baseline_ms), diff, "max relative", (len(device_ms), rounds),
               f"NumPy guided filter (scipy uniform_filter), {BANDS} channels, r {DENOISE_RADIUS}; speedup: median of "
               f"{rounds} interleaved rounds")
    case.speedup = statistics.median(ratios)
    return case
