"""The float64 reference of the guided filter's variance (:mod:`specgpu.engine.guided_variance`), written out
window by window, that the device's kernels are tested against."""

from __future__ import annotations

import numpy as np


def shifted(a, dy, dx):
    """a[y + dy, x + dx] and whether that lies in the image (0 where not)."""
    h, w = a.shape[:2]
    out = np.zeros_like(a)
    ok = np.zeros((h, w), bool)
    if abs(dy) >= h or abs(dx) >= w:  # nothing of the image there
        return out, ok
    src = (slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0)))
    dst = (slice(max(-dy, 0), h + min(-dy, 0)), slice(max(-dx, 0), w + min(-dx, 0)))
    out[dst] = a[src]
    ok[dst] = True
    return out, ok


def reference_filtered_variance(own, total, guide, radius, eps, slopes, guide_var, terms, offsets=None, sqrt=False,
                                mask=None, bits=0):
    """float64, written out window by window: each pixel's weights W_ij of the guided filter of ``guide`` (windows
    clipped to the image), sum_j W_ij^2 own'_j (own' 0 where own or total is not finite or the mask flags the
    pixel), the guide's noise passed by each channel's slope terms, plus total - own' + offsets."""
    g = np.asarray(guide, np.float64)
    own, total = np.asarray(own, np.float64), np.asarray(total, np.float64)
    slopes = np.asarray(slopes, np.float64)
    r, (h, w) = radius, own.shape[:2]
    offs = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    n, s, s2 = np.zeros((h, w)), np.zeros((h, w)), np.zeros((h, w))
    sd, sdg = np.zeros(slopes.shape), np.zeros(slopes.shape)
    for dy, dx in offs:
        v, ok = shifted(g, dy, dx)
        sv, _ = shifted(slopes, dy, dx)
        n += ok
        s += v
        s2 += v * v
        sd += sv
        sdg += sv * v[..., None]
    mu = s / n
    alpha = 1.0 / (np.maximum(s2 / n - mu * mu, 0) + eps)
    a = (sdg / n[..., None] - mu[..., None] * sd / n[..., None]) * alpha[..., None]
    weights, boxes, m, abar = {}, {}, np.zeros((h, w)), np.zeros(slopes.shape)
    for dy, dx in offs:
        nk, okk = shifted(n, dy, dx)
        muk, _ = shifted(mu, dy, dx)
        ak, _ = shifted(alpha, dy, dx)
        abar += shifted(a, dy, dx)[0]
        m += okk
        inv = np.where(okk, 1.0 / np.where(okk, nk, 1.0), 0.0)
        for ey, ex in offs:
            gj, okj = shifted(g, dy + ey, dx + ex)
            key = (dy + ey, dx + ex)
            weights[key] = weights.get(key, 0.0) + np.where(okj & okk, inv * (1 + ak * (g - muk) * (gj - muk)), 0.0)
            boxes[key] = boxes.get(key, 0.0) + np.where(okj & okk, inv, 0.0)
    bad = ~np.isfinite(own) | ~np.isfinite(total)
    if mask is not None:
        bad |= ((np.asarray(mask) & bits) != 0)[..., None]
    o = np.where(bad, 0.0, own)
    acc = np.zeros_like(o)
    for (dy, dx), wt in weights.items():
        acc += ((wt / m) ** 2)[..., None] * shifted(o, dy, dx)[0]
    abar /= m[..., None]
    # the guide's noise at the pixel less that of its box means (the weights of a flat guide)
    gv = np.asarray(guide_var, np.float64) * (1 - 2 * boxes[(0, 0)] / m + sum(b ** 2 for b in boxes.values()) / m ** 2)
    pas = np.stack([sum(wt * abar[..., d] * abar[..., e] for d, e, wt in ch) * gv if ch else np.zeros((h, w))
                    for ch in terms], axis=-1)
    v = acc + pas + total - o + (0.0 if offsets is None else np.asarray(offsets))
    return np.where(np.isnan(v), v, np.sqrt(np.maximum(v, 0.0))) if sqrt else v
