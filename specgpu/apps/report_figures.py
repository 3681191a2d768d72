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
    # fixed axes, the image's at its aspect and the bar's beside it: a layout solver would cost more than the
    # drawing itself
    image_w = 3.5
    image_h = image_w * h / w
    top = 0.35 if title else 0.1
    width, height = 4.6, image_h + 0.15 + top
    fig = plt.figure(figsize=(width, height))
    ax = fig.add_axes((0.1 / width, 0.15 / height, image_w / width, image_h / height))
    cax = fig.add_axes(((image_w + 0.3) / width, (0.15 + 0.05 * image_h) / height, 0.16 / width,
                        0.9 * image_h / height), label="<colorbar>")
    colormap = plt.get_cmap(cmap).with_extremes(bad="0.5")
    image = ax.imshow(np.ma.masked_invalid(arr), cmap=colormap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=10)
    bar = fig.colorbar(image, cax=cax, extend="max" if np.nanmax(arr, initial=vmin) > vmax else "neither")
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(labelsize=8)
    return fig


def spectra_figure(names, wavelengths, recovered, truth_wavelengths, truth, *, sigma=None, title: str = "",
                   columns: int = 6):
    """Recovered (solid) against true (broken) reflectance of each patch, one panel per patch; ``sigma`` (P, B)
    draws the +- 1 sigma band around the recovery. Returns the figure.

    The panels are drawn in one axes, each patch's curves placed by a transform of their own (their data stays in
    nanometres and reflectance): a figure of 24 axes spends two seconds of CPU on their ticks alone, this one a
    tenth of that, and looks the same at the size a page shows it."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.transforms import Affine2D, Bbox, TransformedBbox

    plt = _pyplot()
    rec = np.asarray(recovered, np.float64)
    tru = np.asarray(truth, np.float64)
    wl, twl = np.asarray(wavelengths, np.float64), np.asarray(truth_wavelengths, np.float64)
    if rec.shape[0] != len(names) or tru.shape[0] != len(names):
        raise ValueError(f"{len(names)} patch names, {rec.shape[0]} recovered and {tru.shape[0]} true spectra")
    rows = -(-len(names) // columns)
    height = 1.8 * rows + 0.8
    fig = plt.figure(figsize=(2.3 * columns, height))
    ax = fig.add_axes((0.055, 0.45 / height, 0.935, 1 - 1.0 / height))
    ax.set_xlim(0, columns)
    ax.set_ylim(0, rows)
    ax.set_axis_off()
    top = max(1.0, float(np.nanmax(np.concatenate([rec.ravel(), tru.ravel()]), initial=0.0)) * 1.05)
    w0, w1 = float(min(wl.min(), twl.min())), float(max(wl.max(), twl.max()))
    pw, ph = 0.86, 0.66  # a panel's share of its cell: room for its title above and tick labels below
    xticks = np.arange(np.ceil(w0 / 100) * 100, w1 + 1e-9, 100.0)
    yticks = np.arange(0.0, top + 1e-9, 0.5)
    frames, marks = [], []
    for i, name in enumerate(names):
        r, c = divmod(i, columns)
        x0, y0 = c + 0.1, rows - 1 - r + 0.16
        place = Affine2D().translate(-w0, 0.0).scale(pw / (w1 - w0), ph / top).translate(x0, y0) + ax.transData
        clip = TransformedBbox(Bbox([[w0, 0.0], [w1, top]]), place)
        if sigma is not None:
            s = np.asarray(sigma, np.float64)[i]
            band = ax.fill_between(wl, rec[i] - s, rec[i] + s, color="C3", alpha=0.25, lw=0, transform=place)
            band.set_clip_box(clip)
        for x, y, style in ((twl, tru[i], dict(color="k", ls="--", lw=1)), (wl, rec[i], dict(color="C3", lw=1.3))):
            line, = ax.plot(x, y, transform=place, **style)
            line.set_clip_box(clip)
        frames.append([(x0, y0), (x0 + pw, y0), (x0 + pw, y0 + ph), (x0, y0 + ph), (x0, y0)])
        for t in xticks:
            x = x0 + (t - w0) / (w1 - w0) * pw
            marks.append([(x, y0), (x, y0 - 0.03)])
            if i + columns >= len(names):  # the bottom panel of its column: the wavelengths beneath
                ax.text(x, y0 - 0.05, f"{t:g}", ha="center", va="top", fontsize=7)
        for t in yticks:
            y = y0 + t / top * ph
            marks.append([(x0, y), (x0 - 0.02, y)])
            if c == 0:
                ax.text(x0 - 0.03, y, f"{t:g}", ha="right", va="center", fontsize=7)
        ax.text(x0 + pw / 2, y0 + ph + 0.04, f"{i + 1} {name}", ha="center", va="bottom", fontsize=8)
    ax.add_collection(LineCollection(frames + marks, colors="0.3", lw=0.6))
    handles = [Line2D([], [], color="k", ls="--", lw=1, label="truth"),
               Line2D([], [], color="C3", lw=1.3, label="recovered")]
    if sigma is not None:
        handles.append(Patch(color="C3", alpha=0.25, lw=0, label="± 1σ per pixel"))
    fig.legend(handles=handles, fontsize=7, loc="upper right", ncols=len(handles), frameon=False)
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
    fig, ax = plt.subplots(figsize=(7, 3.4))
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.14, top=0.91)  # fixed margins: no layout solver to run
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
