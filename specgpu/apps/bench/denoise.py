"""The denoiser's case of ``specgpu bench`` (``guided_filter``): what ``recover --denoise`` filters for a 9-frame
plan, the 9 coordinates of its outputs in their subspace (:func:`specgpu.pipeline.denoise.output_subspace`),
float32, smoothed by the guided filter (radius and eps its defaults) on the device, against the same filter in
NumPy with SciPy's box filter (windows clipped to the image, as the kernels)."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from specgpu.engine.guided import guided_filter
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


def guided_case(queue, width: int, height: int, reps, measure, row):
    """Time the device filter (data on the device), the NumPy-in / NumPy-out call and the NumPy baseline;
    ``measure`` and ``row`` are the bench's own timing and row builders."""
    rng = np.random.default_rng(3)
    g = rng.uniform(0.2, 1.0, (height, width)).astype(np.float32)
    p = (g[..., None] * rng.uniform(0.1, 0.9, BANDS) + rng.normal(0, 0.01, (height, width, BANDS))).astype(np.float32)
    p_dev, g_dev = cla.to_device(queue, p), cla.to_device(queue, g)

    def device():
        return guided_filter(p_dev, g_dev, radius=DENOISE_RADIUS, eps=DENOISE_EPS)

    def api():
        return guided_filter(p, g, radius=DENOISE_RADIUS, eps=DENOISE_EPS, device=queue)

    def baseline():
        return guided_numpy(p, g, DENOISE_RADIUS, DENOISE_EPS)

    device_ms, api_ms, baseline_ms, result, expected = measure(queue, device, api, baseline, reps)
    diff = float(np.max(np.abs(result - expected))) / max(float(np.max(np.abs(expected))), 1e-30)
    return row("guided_filter", width, height, None, device_ms, api_ms, baseline_ms, diff, "max relative", reps,
               f"NumPy guided filter (scipy uniform_filter), {BANDS} channels, r {DENOISE_RADIUS}")
