"""Float64 references the kernels are checked against: NumPy for the linear map, colour-science for colorimetry.

Used by the tests and by ``tools/maintenance/make_golden.py`` (which writes the golden set the selftest reproduces).
"""

from __future__ import annotations

import warnings

import colour
import numpy as np

OBSERVER = "CIE 1931 2 Degree Standard Observer"


def linear_ref(frames, A, dark=None, gain=None, layout="interleaved"):
    """y = A (o - dark) * gain in float64; frames (K, *spatial); dark (*spatial) or (K, *spatial)."""
    o = np.asarray(frames, dtype=np.float64)
    if dark is not None:
        o = o - np.asarray(dark, dtype=np.float64)
    y = np.tensordot(np.asarray(A, dtype=np.float64), o, axes=(1, 0))  # (B, *spatial)
    if gain is not None:
        y = y * np.asarray(gain, dtype=np.float64)
    return np.moveaxis(y, 0, -1) if layout == "interleaved" else y


def mask_ref(frames, saturation=None):
    """1 where any frame sample >= saturation, 2 where any is non-finite (OR-ed), per pixel."""
    o = np.asarray(frames)
    mask = np.zeros(o.shape[1:], dtype=np.uint8)
    if saturation is not None:
        with np.errstate(invalid="ignore"):
            mask |= np.any(o >= saturation, axis=0).astype(np.uint8)
    if o.dtype.kind == "f":
        mask |= (np.any(~np.isfinite(o), axis=0).astype(np.uint8) * 2).astype(np.uint8)
    return mask


def XYZ_to_Lab_ref(XYZ, illuminant="D65", observer=OBSERVER, wavelengths=None, integration="rectangle"):
    """colour-science's CIELAB for the white of a named illuminant as the package defines it, built by
    colour-science alone: the perfect diffuser integrated on ``wavelengths`` (360-780 nm at 1 nm by default) by
    ``integration``; or for the white given as xy / XYZ."""
    if isinstance(illuminant, str):
        w = np.arange(360.0, 781.0, 1.0) if wavelengths is None else np.asarray(wavelengths, np.float64)
        white = reflectance_to_XYZ_ref(np.ones(w.size), w, illuminant, observer, integration)
        xy = colour.XYZ_to_xy(white)
    else:
        xy = np.asarray(illuminant, dtype=np.float64)
        xy = colour.XYZ_to_xy(xy) if xy.shape == (3,) else xy
    return colour.XYZ_to_Lab(np.asarray(XYZ, dtype=np.float64), xy)


def delta_E_ref(Lab_1, Lab_2, method):
    a = np.asarray(Lab_1, dtype=np.float64)
    b = np.asarray(Lab_2, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    return colour.delta_E(a, b, method=method)


def reflectance_to_XYZ_ref(R, wavelengths, illuminant="D65", cmfs=OBSERVER, integration="rectangle"):
    """colour-science's XYZ / 100: its integration on the grid (rectangle rule) or its ASTM E308 tables."""
    w = np.asarray(wavelengths, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    if integration == "ASTM E308":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            XYZ = [colour.sd_to_XYZ(colour.SpectralDistribution(r, w), colour.MSDS_CMFS[cmfs],
                                    colour.SDS_ILLUMINANTS[illuminant], method="ASTM E308")
                   for r in R.reshape(-1, w.size)]
        return np.reshape(XYZ, (*R.shape[:-1], 3)) / 100
    shape = colour.SpectralShape(w[0], w[-1], w[1] - w[0])
    return colour.msds_to_XYZ(R, colour.MSDS_CMFS[cmfs], colour.SDS_ILLUMINANTS[illuminant], method="Integration",
                              shape=shape) / 100


def near_hue_discontinuity(Lab_1, Lab_2, margin_deg=0.5):
    """Pairs whose a'b' hues are within ``margin_deg`` of 180 degrees apart (CIEDE2000's discontinuity, where a
    last-bit difference legitimately flips the mean-hue branch)."""
    a1, b1 = np.broadcast_arrays(np.asarray(Lab_1, np.float64), np.asarray(Lab_2, np.float64))
    C1 = np.hypot(a1[..., 1], a1[..., 2])
    C2 = np.hypot(b1[..., 1], b1[..., 2])
    Cbar7 = ((C1 + C2) / 2) ** 7
    G = 0.5 * (1 - np.sqrt(Cbar7 / (Cbar7 + 25.0**7)))
    h1 = np.degrees(np.arctan2(a1[..., 2], (1 + G) * a1[..., 1])) % 360
    h2 = np.degrees(np.arctan2(b1[..., 2], (1 + G) * b1[..., 1])) % 360
    return np.abs(np.abs(h1 - h2) - 180) < margin_deg


def random_Lab(rng, shape):
    """CIELAB colours of real surfaces: XYZ in [0.005, 1] per channel under D65, converted by colour-science."""
    XYZ = rng.uniform(0.005, 1.0, (*shape, 3))
    return XYZ_to_Lab_ref(XYZ)


def sharma_pairs(path):
    d = np.loadtxt(path, delimiter=",", comments="#", skiprows=5)
    return d[:, 1:4], d[:, 4:7], d[:, 7]


def guided_filter_numpy(p, g, r, eps):
    """NumPy reference of the guided filter (He, Sun and Tang 2010) with windows clipped to the image: box
    means by cumulative sums, divided by the number of pixels inside each window."""
    p = np.asarray(p, np.float64)
    g = np.asarray(g, np.float64)

    def box(a):
        H, W = a.shape[:2]
        out = a
        for axis, n in ((0, H), (1, W)):
            c = np.cumsum(out, axis=axis)
            c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
            idx = np.arange(n)
            hi, lo = np.minimum(idx + r, n - 1) + 1, np.maximum(idx - r, 0)
            s = np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)
            shape = [1] * out.ndim
            shape[axis] = n
            out = s / (hi - lo).reshape(shape)
        return out

    gg = g[..., None]
    mg, mp = box(gg), box(p)
    cov = box(gg * p) - mg * mp
    var = np.maximum(box(gg * gg) - mg * mg, 0.0)
    a = cov / (var + eps)
    b = mp - a * mg
    return box(a) * gg + box(b)


def linear_warp_ref(frames, A, shifts, dark=None, gain=None):
    """Motion-compensated linear map in float64: y(x) = A s(x), s_k the corrected frame (o_k - dark) * gain sampled
    bilinearly at x + d_k (``shifts`` (K, 2)) or at M_k (x, y, 1) (``shifts`` (K, 2, 3)), its coordinates clamped
    to the pixel centres; NaN where a sample point lies outside the sensor's footprint [-1/2, W-1/2] x
    [-1/2, H-1/2]. Returns (y (H, W, B), outside (H, W) bool)."""
    o = np.asarray(frames, np.float64)
    K, h, w = o.shape
    c = o - (0 if dark is None else np.asarray(dark, np.float64))
    if gain is not None:
        c = c * np.asarray(gain, np.float64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    s = np.empty((K, h, w))
    outside = np.zeros((h, w), bool)
    for k in range(K):
        m = np.asarray(shifts[k], np.float64)
        if m.shape == (2,):
            sx, sy = xx + m[0], yy + m[1]
        elif m.shape == (2, h, w):
            sx, sy = xx + m[0], yy + m[1]
        else:
            sx, sy = m[0, 0] * xx + m[0, 1] * yy + m[0, 2], m[1, 0] * xx + m[1, 1] * yy + m[1, 2]
        out = (sx < -0.5 - 1e-3) | (sy < -0.5 - 1e-3) | (sx > w - 0.5 + 1e-3) | (sy > h - 0.5 + 1e-3)
        outside |= out
        sx, sy = np.clip(sx, 0, w - 1), np.clip(sy, 0, h - 1)
        x0 = np.minimum(np.floor(sx).astype(int), w - 1)
        y0 = np.minimum(np.floor(sy).astype(int), h - 1)
        x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
        fx, fy = sx - x0, sy - y0
        ck = c[k]
        s[k] = (ck[y0, x0] * (1 - fx) * (1 - fy) + ck[y0, x1] * fx * (1 - fy) + ck[y1, x0] * (1 - fx) * fy
                + ck[y1, x1] * fx * fy)
    y = np.tensordot(s, np.asarray(A, np.float64), axes=(0, 1))
    y[outside] = np.nan
    return y, outside
