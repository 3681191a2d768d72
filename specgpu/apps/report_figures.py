"""The report's figures, drawn with matplotlib and returned as PNG bytes to embed in one self-contained page.

Every map carries a colour bar labelled with its quantity and unit, and maps that are compared (one per method)
share one scale, passed in by the caller; spectra plots show the recovered patch means against the truth, with
the predicted per-pixel standard deviation as a band where a sigma map exists; sRGB renderings are the images
themselves (no axes, JPEG: a noisy recovery compresses like a photograph), chromatically adapted to sRGB's D65
white from the illuminant they were taken under.
"""

from __future__ import annotations

from io import BytesIO

import colour
import numpy as np

from specgpu.io.previews import sRGB8

__all__ = ["DELTA_E_LABEL", "SIGMA_LABEL", "figure_png", "rgb_jpeg", "sRGB_rendering", "map_figure",
           "spectra_figure", "illuminant_figure", "common_scale"]

#: Colour-bar label of a CIEDE2000 map: the quantity and its unit (CIELAB units).
DELTA_E_LABEL = "ΔE00 (CIEDE2000, CIELAB units)"
#: Colour-bar label of a reflectance sigma map.
SIGMA_LABEL = "σ reflectance (RMS over bands, reflectance units)"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_png(fig, dpi: int = 80) -> bytes:
    """A matplotlib figure as PNG bytes; the figure is closed."""
    plt = _pyplot()
    buffer = BytesIO()
    try:
        fig.savefig(buffer, format="png", dpi=dpi)
    finally:
        plt.close(fig)
    return buffer.getvalue()


def rgb_jpeg(rgb8, quality: int = 90) -> bytes:
    """An (H, W, 3) uint8 image as JPEG bytes: the renderings of noisy recoveries, a photograph's content, which
    PNG keeps at about 1 MB each at 640 x 480 and JPEG at quality 90 in a sixth of that."""
    import matplotlib.image

    arr = np.asarray(rgb8)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.dtype != np.uint8:
        raise ValueError(f"rgb8 must be (H, W, 3) uint8, got {arr.shape} {arr.dtype}")
    buffer = BytesIO()
    matplotlib.image.imsave(buffer, arr, format="jpeg", pil_kwargs={"quality": int(quality)})
    return buffer.getvalue()


def sRGB_rendering(XYZ, illuminant: str = "D65") -> np.ndarray:
    """(H, W, 3) uint8 sRGB of an XYZ image (Y = 1 for the perfect white) taken under ``illuminant`` (a
    colour-science name), adapted (CAT02) to sRGB's D65 white; no exposure change (a white at code 255), NaN
    black."""
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"].get(illuminant)
    if xy is None:
        raise ValueError(f"unknown illuminant {illuminant!r} for an sRGB rendering")
    return sRGB8(XYZ, xy)


def common_scale(maps, percentile: float = 95.0, floor: float = 1e-6) -> float:
    """One colour-scale top for maps that are compared: the largest of their ``percentile``-th percentiles over
    finite pixels (so the few pixels of a patch's edge, or one outlier, do not flatten every map), rounded up to two
    significant digits."""
    tops = [float(np.percentile(m[np.isfinite(m)], percentile)) for m in maps if np.isfinite(m).any()]
    top = max(tops, default=0.0)
    if top <= floor:
        return 1.0
    digits = 10.0 ** (np.floor(np.log10(top)) - 1)
    return float(np.ceil(top / digits) * digits)


def map_figure(data, *, vmax: float, label: str, title: str = "", cmap: str = "magma", vmin: float = 0.0):
    """One map with its colour bar: ``label`` (quantity and unit) on the bar, the scale fixed to
    [``vmin``, ``vmax``] (values above clip, the bar's arrow says so), NaN pixels grey. Returns the figure."""
    plt = _pyplot()
    arr = np.asarray(data, np.float64)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise ValueError(f"a map must be (H, W), got shape {arr.shape}")
    if not (np.isfinite(vmax) and vmax > vmin):
        raise ValueError(f"vmax must be finite and above vmin {vmin}, got {vmax!r}")
    h, w = arr.shape
    fig, ax = plt.subplots(figsize=(4.6, 4.6 * h / w + 0.6), layout="constrained")
    colormap = plt.get_cmap(cmap).with_extremes(bad="0.5")
    image = ax.imshow(np.ma.masked_invalid(arr), cmap=colormap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=10)
    bar = fig.colorbar(image, ax=ax, shrink=0.9, extend="max" if np.nanmax(arr, initial=vmin) > vmax else "neither")
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(labelsize=8)
    return fig


def spectra_figure(names, wavelengths, recovered, truth_wavelengths, truth, *, sigma=None, title: str = "",
                   columns: int = 6):
    """Recovered (solid) against true (broken) reflectance of each patch, one panel per patch; ``sigma`` (P, B)
    draws the +- 1 sigma band around the recovery. Returns the figure."""
    plt = _pyplot()
    rec = np.asarray(recovered, np.float64)
    tru = np.asarray(truth, np.float64)
    if rec.shape[0] != len(names) or tru.shape[0] != len(names):
        raise ValueError(f"{len(names)} patch names, {rec.shape[0]} recovered and {tru.shape[0]} true spectra")
    rows = -(-len(names) // columns)
    # a fixed grid: the constrained layout's solver costs half a second per 24-panel figure
    height = 1.8 * rows + 0.8
    fig, axes = plt.subplots(rows, columns, figsize=(2.3 * columns, height), sharex=True, sharey=True,
                             squeeze=False)
    fig.subplots_adjust(left=0.055, right=0.99, bottom=0.45 / height, top=1 - 0.55 / height, wspace=0.12,
                        hspace=0.45)
    top = max(1.0, float(np.nanmax(np.concatenate([rec.ravel(), tru.ravel()]), initial=0.0)) * 1.05)
    for i, ax in enumerate(axes.flat):
        if i >= len(names):
            ax.set_visible(False)
            continue
        ax.plot(truth_wavelengths, tru[i], "k--", lw=1, label="truth")
        ax.plot(wavelengths, rec[i], "C3", lw=1.3, label="recovered")
        if sigma is not None:
            s = np.asarray(sigma, np.float64)[i]
            ax.fill_between(wavelengths, rec[i] - s, rec[i] + s, color="C3", alpha=0.25, lw=0,
                            label="± 1σ per pixel")
        ax.set_title(f"{i + 1} {names[i]}", fontsize=8)
        ax.set_ylim(0, top)
        ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=6, loc="upper left")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.supxlabel("wavelength (nm)", fontsize=9)
    fig.supylabel("reflectance", fontsize=9)
    return fig


#: How an illuminant plot tells the targets from what the patterns emit: (line style, width, opacity) of each; a
#: pattern emits nearly its target, so the target is a wide faint band and the emitted curve a dashed line on it.
TARGET_STYLE, EMITTED_STYLE = ("-", 4.0, 0.3), ("--", 1.2, 1.0)


def illuminant_figure(plan, bundle, *, title: str = ""):
    """A plan's illuminant sequence: each target spectrum (solid, wide and faint) and what its quantized DMD
    pattern emits by the calibrated model (dashed, thin), one colour per illuminant, with a legend naming both
    styles. Returns the figure."""
    from matplotlib.lines import Line2D

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.4), layout="constrained")
    emitted = bundle.emitted(plan.patterns)
    for k in range(plan.K):
        for (ls, lw, alpha), wl, curve in ((TARGET_STYLE, plan.light_wavelengths, plan.target_spectra[k]),
                                          (EMITTED_STYLE, bundle.wavelengths, emitted[k])):
            ax.plot(wl, curve, ls=ls, lw=lw, alpha=alpha, color=f"C{k % 10}")
    ax.legend(handles=[Line2D([], [], color="0.3", ls=ls, lw=lw, alpha=alpha, label=label) for (ls, lw, alpha), label
                       in ((TARGET_STYLE, "target"), (EMITTED_STYLE, "emitted by its quantized pattern"))],
              fontsize=7, loc="upper right", title="colour: illuminant", title_fontsize=7)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("spectral irradiance (W m$^{-2}$ nm$^{-1}$)")
    ax.set_title(title or f"{plan.method}: {plan.K} illuminants", fontsize=9)
    return fig
