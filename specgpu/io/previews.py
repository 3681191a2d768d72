"""PNG previews: an 8-bit sRGB image from XYZ and a colour-difference heat map, and reading a PNG back.

The sRGB preview uses colour-science's ``XYZ_to_sRGB``, clipped, with an exposure (automatic by default); the heat
map uses a perceptually uniform colormap, with a colour bar drawn beside it (its scale, so the image reads on its
own) and the scale in the PNG text metadata. Both are written atomically.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from numpy.typing import ArrayLike

from specgpu.core.text import one_line
from specgpu.io.exr import write_image
from specgpu.io.paths import _suffix

__all__ = ["PERCEPTUAL_COLORMAPS", "MIN_BAR_HEIGHT", "sRGB8", "write_png", "write_sRGB_preview", "write_delta_E_png",
           "read_png"]

# ---- previews ------------------------------------------------------------------------------------------------------
#: Perceptually uniform matplotlib colormaps accepted for heat maps.
PERCEPTUAL_COLORMAPS = ("magma", "inferno", "viridis", "plasma", "cividis")


#: libpng's flag of the row filter "none" (``PNG_FILTER_NONE``).
PNG_FILTER_NONE = 0x08


def write_png(path: Path, rgb8: np.ndarray, attributes: dict) -> Path:
    """Write an (H, W, C) uint8 image as PNG, atomically, with ``attributes`` as its text metadata; return ``path``."""
    h, w, c = rgb8.shape
    spec = oiio.ImageSpec(w, h, c, "uint8")
    spec.attribute("oiio:ColorSpace", "sRGB")
    # no row filter, deflate level 3: half the CPU of libpng's adaptive filters at level 6, the file within a
    # fifth of their size for a noisy rendering and smaller for a heat map
    spec.attribute("png:filter", PNG_FILTER_NONE)
    spec.attribute("png:compressionLevel", 3)
    for key, value in attributes.items():
        spec.attribute(key, str(value))
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    return write_image(path, rgb8, spec, "png", "PNG")


def _auto_exposure_ev(Y: np.ndarray, percentile: float = 99.0) -> float:
    finite = Y[np.isfinite(Y)]
    level = float(np.percentile(finite, percentile)) if finite.size else 0.0
    return 0.0 if level <= 0 else -math.log2(level)


def sRGB8(XYZ, illuminant=None) -> np.ndarray:
    """(..., 3) uint8 sRGB of XYZ (Y = 1 for the white at code 255), chromatically adapted (CAT02) from the white
    of chromaticity ``illuminant`` (xy; None: D65) to sRGB's; NaN and infinite values render black."""
    import colour  # colour-science takes seconds to import: only the preview needs it
    arr = np.nan_to_num(np.asarray(XYZ, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    kwargs = {} if illuminant is None else {"illuminant": np.asarray(illuminant, np.float64)}
    with np.errstate(invalid="ignore", over="ignore"):
        rgb = colour.XYZ_to_sRGB(arr, **kwargs)
    return np.round(np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)


def write_sRGB_preview(path: str | os.PathLike[str], XYZ: ArrayLike, *, exposure: str = "auto",
                       illuminant: ArrayLike | None = None, metadata: dict | None = None) -> Path:
    """Write an 8-bit sRGB PNG rendering of an XYZ map.

    Parameters
    ----------
    path : str or os.PathLike
        ``.png`` target, written atomically.
    XYZ : array_like
        (H, W, 3) tristimulus values, domain [0, 1] with Y = 1 for the perfect diffuser (colour-science's
        reference scale). NaN pixels render black.
    exposure : float or "auto"
        Exposure in stops (EV): the image is ``XYZ * 2**exposure`` before encoding. ``"auto"`` picks the EV that
        brings the 99th percentile of Y to 1 (specular outliers clip, the rest is not crushed); 0 shows the
        values as they are (a perfect white at code 255).
    illuminant : array_like, optional
        CIE xy chromaticity of the XYZ white (e.g. illuminant A's (0.44758, 0.40745)); the rendering is
        chromatically adapted (CAT02) from it to sRGB's D65 white. None: the XYZ is already relative to D65.
    metadata : mapping, optional
        Extra PNG text entries (str keys; values written as text).

    Returns
    -------
    pathlib.Path
        ``path``; the PNG text holds ``specgpu:exposure_EV`` (the exposure applied).
    """
    path = Path(path)
    _suffix(path, (".png",), "preview")
    arr = np.asarray(XYZ, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"{path}: XYZ must have shape (H, W, 3), got {arr.shape}")
    if isinstance(exposure, str):
        if exposure != "auto":
            raise ValueError(f"{path}: exposure must be a number of stops or 'auto', got {exposure!r}")
        ev = _auto_exposure_ev(arr[..., 1])
    else:
        ev = float(exposure)
        if not math.isfinite(ev):
            raise ValueError(f"{path}: exposure must be finite, got {exposure!r}")
    kwargs = {}
    if illuminant is not None:
        kwargs["illuminant"] = np.asarray(illuminant, dtype=np.float64)
    rgb8 = sRGB8(arr * 2.0 ** ev, kwargs.get("illuminant"))
    attrs = {"specgpu:exposure_EV": repr(ev), "ImageDescription": f"sRGB preview of XYZ, exposure {ev:+.3f} EV"}
    attrs.update({str(k): v for k, v in (metadata or {}).items()})
    return write_png(path, rgb8, attrs)


#: The least height of a heat map's colour bar, px: a smaller map is drawn at the top left, the rest left white.
MIN_BAR_HEIGHT = 200


def _colour_bar(height: int, vmax: float, colormap: str, quantity: str, *, clipped: bool, nan: bool) -> np.ndarray:
    """(height, width, 3) uint8: a vertical colour bar from 0 (bottom) to ``vmax`` (top) with its ticks, the
    quantity above it, an arrow on top when values above ``vmax`` were clipped and, when ``nan``, the grey of NaN
    pixels labelled below it. Text grows with the height, so the bar reads at any map size."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MaxNLocator

    ticks = [float(t) for t in MaxNLocator(nbins=6).tick_values(0.0, vmax) if 0.0 <= t <= vmax * (1 + 1e-9)]
    if vmax - ticks[-1] > 0.1 * vmax:
        ticks.append(vmax)  # the top of the scale is labelled, whatever it is
    else:
        ticks[-1] = vmax
    labels = [f"{t:.3g}" for t in ticks]
    dpi = 100.0
    text = int(np.clip(round(height / 24), 11, 30))  # text height, px
    bar_x, bar_w = 0.6 * text, 1.6 * text
    width = int(round(max(bar_x + bar_w + text * (1.2 + 0.62 * max(map(len, labels))),
                          text * (0.8 + 0.62 * len(quantity)))))
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    top, bottom = 2.2 * text / height, (2.6 if nan else 1.0) * text / height
    points = text * 72.0 / dpi
    bar = fig.add_axes((bar_x / width, bottom, bar_w / width, 1.0 - top - bottom))
    cbar = fig.colorbar(ScalarMappable(norm=Normalize(0.0, vmax), cmap=colormap), cax=bar,
                        extend="max" if clipped else "neither")
    cbar.set_ticks(ticks)
    cbar.set_ticklabels(labels)
    cbar.ax.tick_params(labelsize=points, length=0.3 * points)
    fig.text(0.5, 1.0 - 0.4 * text / height, quantity, ha="center", va="top", fontsize=points)
    if nan:  # the grey NaN pixels are drawn in
        fig.patches.append(Rectangle((bar_x / width, 0.4 * text / height), bar_w / width, 1.2 * text / height,
                                     transform=fig.transFigure, figure=fig, facecolor=(128 / 255,) * 3,
                                     edgecolor="black", linewidth=0.5))
        fig.text((bar_x + bar_w + 0.4 * text) / width, 1.0 * text / height, "NaN", va="center", fontsize=points)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def write_delta_E_png(path: str | os.PathLike[str], delta_E: ArrayLike, *, vmax: float | None = None,
                      colormap: str = "magma", quantity: str = "dE2000",
                      metadata: dict | None = None, colorbar: bool = True) -> Path:
    """Write a colour-difference map as a heat-map PNG with a perceptually uniform colormap and its colour bar.

    Parameters
    ----------
    path : str or os.PathLike
        ``.png`` target, written atomically.
    delta_E : array_like
        (H, W) or (H, W, 1) colour differences, >= 0. NaN pixels render mid grey.
    vmax : float, optional
        dE mapped to the top of the colormap (larger values clip); default the largest finite value (1 if none
        is positive). The bottom is 0.
    colormap : str
        One of :data:`PERCEPTUAL_COLORMAPS` (matplotlib's).
    quantity : str
        Name of the difference for the metadata (``"dE2000"``, ``"dE76"`` ...).
    metadata : mapping, optional
        Extra PNG text entries.
    colorbar : bool
        Draw the colour bar (the scale, with ``quantity`` above it) to the right of the map. The map keeps its
        pixels at the top left of the image (pixel (y, x) of the map is pixel (y, x) of the PNG); a map lower
        than :data:`MIN_BAR_HEIGHT` is padded below with white.

    Returns
    -------
    pathlib.Path
        ``path``; the PNG text holds the scale: ``specgpu:quantity``, ``specgpu:colormap``, ``specgpu:vmin``
        (0), ``specgpu:vmax``, the map's own size ``specgpu:map_width`` and ``specgpu:map_height``, and a readable
        ``ImageDescription``.
    """
    import matplotlib

    path = Path(path)
    _suffix(path, (".png",), "heat map")
    if colormap not in PERCEPTUAL_COLORMAPS:
        raise ValueError(f"{path}: unknown colormap {colormap!r}; valid colormaps: {', '.join(PERCEPTUAL_COLORMAPS)}")
    arr = np.asarray(delta_E, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise ValueError(f"{path}: delta_E must have shape (H, W) or (H, W, 1), got {arr.shape}")
    finite = np.isfinite(arr)
    if vmax is None:
        top = float(arr[finite].max()) if finite.any() else 0.0
        vmax = top if top > 0 else 1.0
    vmax = float(vmax)
    if not math.isfinite(vmax) or vmax <= 0:
        raise ValueError(f"{path}: vmax must be finite and > 0, got {vmax!r}")
    lut = np.round(matplotlib.colormaps[colormap](np.linspace(0.0, 1.0, 256))[:, :3] * 255.0).astype(np.uint8)
    index = np.round(np.clip(np.where(finite, arr, 0.0) / vmax, 0.0, 1.0) * 255.0).astype(np.intp)
    rgb8 = lut[index]
    rgb8[~finite] = 128
    height, width = arr.shape
    if colorbar:
        clipped = bool(finite.any() and arr[finite].max() > vmax)
        bar = _colour_bar(max(height, MIN_BAR_HEIGHT), vmax, colormap, quantity, clipped=clipped,
                          nan=not finite.all())
        canvas = np.full((bar.shape[0], width + bar.shape[1], 3), 255, np.uint8)
        canvas[:height, :width] = rgb8
        canvas[:, width:] = bar
        rgb8 = canvas
    attrs = {"specgpu:quantity": quantity, "specgpu:colormap": colormap, "specgpu:vmin": "0",
             "specgpu:vmax": repr(vmax), "specgpu:map_width": str(width), "specgpu:map_height": str(height),
             "ImageDescription": f"{quantity} heat map, colormap {colormap}, 0 -> {vmax:g} (clipped above, NaN grey)"
                                 + (f"; the map is the {width} x {height} pixels at the top left, its colour bar "
                                    "to the right" if colorbar else "")}
    attrs.update({str(k): v for k, v in (metadata or {}).items()})
    return write_png(path, rgb8, attrs)


def read_png(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict]:
    """Read an 8-bit PNG: (H, W, C) uint8 pixels and its text metadata (name -> str)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: PNG not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: cannot open PNG ({one_line(oiio.geterror())})")
    try:
        spec = inp.spec()
        data = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
        err = inp.geterror()
        if data is None or err:
            raise ValueError(f"{path}: truncated or corrupt PNG ({one_line(err or 'no pixel data')})")
        meta = {a.name: a.value for a in spec.extra_attribs}
    finally:
        inp.close()
    return data.reshape(spec.height, spec.width, spec.nchannels), meta
