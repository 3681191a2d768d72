"""Spectral scenes: per-pixel reflectance cubes the twin photographs.

A :class:`SpectralScene` is a reflectance cube (H, W, B) in [0, 1] (values slightly above 1 are allowed for
fluorescent-white or specular samples, up to 1.5) on B strictly increasing wavelengths (nm), with optional named
boolean masks (the ColorChecker's 24 patches) that the evaluation can use.

Sources:

- cube files (:mod:`specgpu.io.exr`, :mod:`specgpu.io.npz`, :mod:`specgpu.io.envi`): OpenEXR in the
  JCGT 2021 spectral layout (Fichet, Pacanowski, Wilkie), reflective channels named ``T.<wavelength><unit>``
  (e.g. ``T.550,000000nm``; ``.`` also accepted as decimal separator on reading), through OpenImageIO; or
  ``.npz`` with ``wavelengths`` (B,) and ``reflectance`` (H, W, B) (and optional ``mask_<name>`` arrays). Bands are
  ordered by wavelength, never by channel order in the file.
- built-ins (:data:`BUILTIN_SCENES`): ``"colorchecker"`` (the 24-patch chart as an image from colour-science's
  measured spectra, with one mask per patch), ``"white"`` (a reference white plate) and ``"natural"`` (a
  scikit-image sample photograph turned into reflectance by Mallett and Yuksel's 2019 spectral upsampling,
  which is linear in linear-sRGB and therefore one matrix product for the whole image).

The field's illumination non-uniformity belongs to the light (``light.spot_*``, paper Figs. 4, 5), not to the
scene: the same chart can be photographed under a flat or a falling-off spot.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import colour
import numpy as np
import skimage.data
from numpy.typing import ArrayLike
from skimage.transform import resize

from specgpu.core.validate import BadArgument, check_array, check_number, check_wavelengths
from specgpu.io.envi import read_cube_envi
from specgpu.io.exr import read_cube_exr, write_cube_exr
from specgpu.io.npz import read_cube_npz, write_cube_npz

__all__ = [
    "SpectralScene", "read_scene", "write_scene", "colorchecker_scene", "patch_scene", "white_plate_scene",
    "natural_scene", "load_scene", "BUILTIN_SCENES", "interpolation_matrix", "RESIZE_MODES", "validate_resize",
    "resample_scene",
]

MAX_REFLECTANCE = 1.5


@dataclass
class SpectralScene:
    """A reflectance cube with its wavelengths and optional masks.

    Attributes
    ----------
    wavelengths : numpy.ndarray
        (B,) strictly increasing wavelengths, nm, float64.
    reflectance : numpy.ndarray
        (H, W, B) reflectance, float32, finite, in [0, 1.5].
    masks : dict of str to numpy.ndarray
        Named (H, W) boolean masks (e.g. one per ColorChecker patch, in chart order).
    name : str
        A label for reports.
    resampled : str
        How the scene was fitted to the frame it is used at (:func:`resample_scene`), e.g.
        ``"100 x 120 -> 640 x 480 pixels (stretch, nearest neighbour)"``; empty when it was not resampled.
    """

    wavelengths: np.ndarray
    reflectance: np.ndarray
    masks: dict = field(default_factory=dict)
    name: str = ""
    resampled: str = ""

    def __post_init__(self):
        label = f"scene {self.name!r}" if self.name else "scene"
        self.wavelengths = check_wavelengths(f"{label} wavelengths", self.wavelengths)
        r = np.asarray(self.reflectance)
        if r.ndim != 3 or r.shape[2] != self.wavelengths.size:
            raise ValueError(f"{label} reflectance must have shape (H, W, {self.wavelengths.size}), got {r.shape}")
        if r.shape[0] < 1 or r.shape[1] < 1:
            raise ValueError(f"{label} reflectance must not be empty, got shape {r.shape}")
        self.reflectance = check_array(f"{label} reflectance", r, low=0.0, high=MAX_REFLECTANCE, dtype=np.float32)
        masks = {}
        for key, m in dict(self.masks).items():
            m = np.asarray(m)
            if m.shape != r.shape[:2]:
                raise ValueError(f"{label} mask {key!r} must have shape {r.shape[:2]}, got {m.shape}")
            masks[str(key)] = m.astype(bool)
        self.masks = masks

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return self.reflectance.shape[:2]

    def band_weights(self, wavelengths: ArrayLike, weights: ArrayLike) -> np.ndarray:
        """Fold spectral weights on a uniform grid into per-band weights of this scene.

        With the reflectance linearly interpolated between bands (held constant beyond the first and last band),
        ``integral R(lambda) w(lambda) dlambda = sum_b R_b W_b``.

        Parameters
        ----------
        wavelengths
            (G,) uniform grid, nm.
        weights
            (..., G) weights per nm on that grid.

        Returns
        -------
        numpy.ndarray
            (..., B) per-band weights, ``W = (w * dlambda) @ P`` with P the (G, B) interpolation matrix.
        """
        wl = np.asarray(wavelengths, dtype=np.float64)
        dl = float(wl[1] - wl[0])
        return (np.asarray(weights, dtype=np.float64) * dl) @ interpolation_matrix(wl, self.wavelengths)

    def weighted_images(self, band_weights) -> np.ndarray:
        """(K, H, W) float32 images of the scene under (K, B) ``band_weights`` (:meth:`band_weights`): each pixel's
        reflectance bands weighted and summed. A uniform scene (one spectrum broadcast over the field: a white plate,
        a capped lens) gives its K values broadcast, not K x H x W products."""
        bw = np.asarray(band_weights, np.float32)
        h, w = self.shape
        if self.reflectance.strides[:2] == (0, 0):
            return np.repeat(bw @ self.reflectance[0, 0], h * w).reshape(-1, h, w)
        return (bw @ self.reflectance.reshape(h * w, -1).T).reshape(-1, h, w)  # C-contiguous: no transposed copy

    def resized(self, height: int, width: int) -> "SpectralScene":
        """Nearest-neighbour resampling to (height, width), masks included (no new spectra are invented); each axis
        is scaled on its own, so the aspect ratio may change (:func:`resample_scene` fits by a chosen mode and says
        what it did)."""
        h = check_number("height", height, low=1, integer=True)
        w = check_number("width", width, low=1, integer=True)
        if (h, w) == self.shape:
            return self
        ys = np.minimum(((np.arange(h) + 0.5) * self.shape[0] / h).astype(int), self.shape[0] - 1)
        xs = np.minimum(((np.arange(w) + 0.5) * self.shape[1] / w).astype(int), self.shape[1] - 1)
        return SpectralScene(self.wavelengths, self.reflectance[ys][:, xs],
                             {k: m[ys][:, xs] for k, m in self.masks.items()}, self.name)


#: How a scene of another size than the frame is fitted to it (``--resize``). Every mode samples the nearest
#: source pixel, so no spectrum is invented by mixing neighbours; only ``stretch`` changes the aspect ratio.
RESIZE_MODES = {
    "scale": "uniform scaling when the aspect ratios agree (within a pixel); another aspect ratio is refused",
    "exact": "no resampling: a scene of another size than the frame is refused",
    "stretch": "each axis scaled on its own to the frame (the aspect ratio changes)",
    "crop": "scaled uniformly to cover the frame, the overhang cropped equally on both sides",
    "pad": "scaled uniformly to fit inside the frame, centred, the border black (reflectance 0, in no mask)",
}


def validate_resize(mode) -> str:
    """The canonical name of a resize mode (case-insensitive, surrounding blanks ignored); ValueError naming the
    valid ones."""
    text = mode.strip().lower() if isinstance(mode, str) else None
    if text not in RESIZE_MODES:
        raise ValueError(f"resize mode {mode!r} is not one of {', '.join(RESIZE_MODES)}")
    return text


def _axis(n_out: int, n_in: int, scale: float, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest source index of each of ``n_out`` output pixels (``x_in = (x_out + 0.5 - offset) / scale``) and
    whether it falls inside the ``n_in`` source pixels."""
    u = (np.arange(n_out) + 0.5 - offset) / scale
    inside = (u >= 0) & (u < n_in)
    return np.clip(np.floor(u).astype(int), 0, n_in - 1), inside


def resample_scene(scene: SpectralScene, height: int, width: int, mode: str = "scale", *,
                   label: str | None = None) -> SpectralScene:
    """``scene`` fitted to a (height, width) frame by ``mode`` (:data:`RESIZE_MODES`), masks included.

    A scene of the frame's size is returned as it is. Otherwise the result's :attr:`SpectralScene.resampled`
    says what was done (for a line on stderr and the outputs' metadata).

    Parameters
    ----------
    scene : SpectralScene
    height, width : int
        The frame, pixels (>= 1).
    mode : str
        ``"scale"`` (default): uniform scaling only, refusing a change of aspect ratio (more than a pixel);
        ``"exact"``: no resampling; ``"stretch"``, ``"crop"``, ``"pad"``: see :data:`RESIZE_MODES`.
    label : str, optional
        How errors name the scene (its file); default its name.

    Raises
    ------
    ValueError
        One line naming the scene, both sizes and the modes that would fit it.
    """
    mode = validate_resize(mode)
    h = int(check_number("height", height, low=1, integer=True))
    w = int(check_number("width", width, low=1, integer=True))
    sh, sw = scene.shape
    if (sh, sw) == (h, w):
        return scene
    what = label or (f"scene {scene.name!r}" if scene.name else "the scene")
    sizes = f"{what} is {sw} x {sh} pixels, the frame {w} x {h}"
    if mode == "exact":
        raise ValueError(f"{sizes}; give a scene of the frame's size, or a resize mode (--resize scale, stretch, "
                         "crop or pad)")
    if mode == "scale":
        # one scale factor must put both edges within half a pixel of the frame's
        lo = max((w - 0.5) / sw, (h - 0.5) / sh)
        hi = min((w + 0.5) / sw, (h + 0.5) / sh)
        if lo > hi:
            raise ValueError(f"{sizes}: another aspect ratio ({sw / sh:.4g} against {w / h:.4g}); choose how to fit "
                             "it (--resize stretch, crop or pad) or give a scene of the frame's aspect ratio")
    if mode in ("scale", "stretch"):
        (ys, iny), (xs, inx) = _axis(h, sh, h / sh, 0.0), _axis(w, sw, w / sw, 0.0)
    else:
        s = max(w / sw, h / sh) if mode == "crop" else min(w / sw, h / sh)
        (ys, iny), (xs, inx) = _axis(h, sh, s, (h - sh * s) / 2), _axis(w, sw, s, (w - sw * s) / 2)
    inside = iny[:, None] & inx[None, :]
    refl = scene.reflectance[ys][:, xs]
    masks = {k: m[ys][:, xs] for k, m in scene.masks.items()}
    if not inside.all():  # pad: the border is black and belongs to no patch
        refl = np.where(inside[..., None], refl, np.float32(0))
        masks = {k: m & inside for k, m in masks.items()}
    note = f"{sw} x {sh} -> {w} x {h} pixels ({mode}, nearest neighbour"
    if mode == "crop":
        kept_w, kept_h = min(sw, w / s), min(sh, h / s)
        note += f"; {sw - kept_w:.0f} source columns and {sh - kept_h:.0f} rows cropped"
    elif mode == "pad":
        note += f"; {int((~inside).sum())} border pixels padded black"
    elif mode == "stretch" and abs(sw / sh - w / h) > 1e-9:
        note += f"; aspect ratio {sw / sh:.4g} -> {w / h:.4g}"
    return SpectralScene(scene.wavelengths, refl, masks, scene.name, note + ")")


def interpolation_matrix(grid, band_wavelengths) -> np.ndarray:
    """(G, B) matrix of linear-interpolation weights from B band samples to G grid points (constant beyond)."""
    grid = np.asarray(grid, dtype=np.float64)
    bw = np.asarray(band_wavelengths, dtype=np.float64)
    eye = np.eye(bw.size)
    return np.stack([np.interp(grid, bw, eye[b]) for b in range(bw.size)], axis=1)


# ---- files ---------------------------------------------------------------------------------------------------
def read_scene(path: str | os.PathLike[str]) -> SpectralScene:
    """Read a spectral cube: ``.exr`` (JCGT 2021 ``T.<wl>nm`` channels) or ``.npz`` (``wavelengths``, ``reflectance``).

    Raises
    ------
    ValueError
        Naming the file: missing, truncated or corrupt files, no reflective channels, unparsable or duplicated
        wavelengths, wrong shapes, NaN or out-of-range reflectance.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: scene file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            return _read_npz(path)
        if suffix == ".exr":
            return _read_exr(path)
        if suffix == ".hdr":  # ENVI: header + raw data
            refl, wl, _ = read_cube_envi(path)
            return SpectralScene(wl, refl, {}, path.stem)
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    raise ValueError(f"{path}: unknown scene format {suffix!r}; expected .exr, .npz or .hdr (ENVI)")


def _read_npz(path: Path) -> SpectralScene:
    refl, wl, extra = read_cube_npz(path)
    masks = {k[5:]: m for k, m in extra.items() if k.startswith("mask_")}
    return SpectralScene(wl, refl, masks, path.stem)


def _read_exr(path: Path) -> SpectralScene:
    refl, wl, _ = read_cube_exr(path)
    return SpectralScene(wl, refl, {}, path.stem)


def write_scene(path: str | os.PathLike[str], scene: SpectralScene, *, half: bool = False) -> Path:
    """Write a scene as ``.exr`` (JCGT ``T.<wl>nm`` channels, float32 or half) or ``.npz`` (masks as ``mask_*``).

    The file appears under its name only once complete (written to a temporary name, then renamed).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return write_cube_npz(path, scene.reflectance, scene.wavelengths,
                                      {f"mask_{k}": m for k, m in scene.masks.items()})
    if suffix != ".exr":
        raise ValueError(f"{path}: unknown scene format {suffix!r}; expected .exr or .npz")
    return write_cube_exr(path, scene.reflectance, scene.wavelengths, half=half)


# ---- built-ins ---------------------------------------------------------------------------------------------------
_CHARTS = ("ColorChecker N Ohta", "BabelColor Average")


def white_tile_roi(height: int = 480, width: int = 640) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the reference white tile :func:`colorchecker_scene` places above the chart (``white_tile``),
    inset by 3 pixels from the tile's edges (the ROI to give ``specgpu recover --white-roi``)."""
    pitch = min(width / 6.4, height / 4.4)
    top = (height - 4 * pitch) / 2
    th = max(4, int(top * 0.6))
    tw = max(8, int(pitch * 1.6))
    x0, y0 = int((width - tw) / 2), max(0, int((top - th) / 2))
    return x0 + 3, y0 + 3, max(1, tw - 6), max(1, th - 6)


def colorchecker_scene(height: int = 480, width: int = 640, *, chart: str = "ColorChecker N Ohta",
                       surround: float = 0.03, white_tile: float | None = None) -> SpectralScene:
    """The 24-patch ColorChecker as an image: 6 x 4 patches on a dark surround, one mask per patch.

    Parameters
    ----------
    height, width
        Image size in pixels (>= 24 x 36).
    chart
        colour-science's measured chart spectra: ``"ColorChecker N Ohta"`` (380-780 nm, 5 nm) or
        ``"BabelColor Average"``.
    surround
        Flat reflectance of the chart's black surround, in [0, 1].
    white_tile
        With a reflectance (e.g. 0.99), a flat reference white tile in the surround above the chart (the white
        of drift correction at capture: :func:`white_tile_roi` gives its ROI); not one of the masks.

    Returns
    -------
    SpectralScene
        Masks keyed by colour-science's patch names (``"dark skin"`` ... ``"black 2 (1.5 D)"``), in chart order;
        each covers the central 70 % of its patch, away from edges blurred by real optics.
    """
    if chart not in _CHARTS:
        raise ValueError(f"unknown chart {chart!r}; valid charts: {', '.join(_CHARTS)}")
    h = check_number("height", height, low=24, integer=True)
    w = check_number("width", width, low=36, integer=True)
    s = check_number("surround", surround, low=0, high=1)
    sds = colour.SDS_COLOURCHECKERS[chart]
    names = list(sds.keys())
    wl = np.asarray(sds[names[0]].wavelengths, dtype=np.float64)
    spectra = np.stack([np.interp(wl, sds[n].wavelengths, sds[n].values) for n in names])
    refl = np.full((h, w, wl.size), s, dtype=np.float32)
    pitch = min(w / 6.4, h / 4.4)
    size = 0.84 * pitch
    x0 = (w - 6 * pitch) / 2 + (pitch - size) / 2
    y0 = (h - 4 * pitch) / 2 + (pitch - size) / 2
    masks = {}
    for k, name in enumerate(names):
        row, col = divmod(k, 6)
        ya, xa = y0 + row * pitch, x0 + col * pitch
        ys, xs = slice(int(round(ya)), int(round(ya + size))), slice(int(round(xa)), int(round(xa + size)))
        refl[ys, xs, :] = spectra[k]
        m = np.zeros((h, w), bool)
        inset = 0.15 * size
        m[int(round(ya + inset)):int(round(ya + size - inset)),
          int(round(xa + inset)):int(round(xa + size - inset))] = True
        masks[name] = m
    if white_tile is not None:
        wt = check_number("white_tile", white_tile, low=0, low_open=True, high=MAX_REFLECTANCE)
        x, y, tw, th = white_tile_roi(h, w)
        refl[max(0, y - 3):y + th + 3, max(0, x - 3):x + tw + 3, :] = wt
    return SpectralScene(wl, refl, masks, "colorchecker")


def patch_scene(names, wavelengths, spectra, height: int = 240, width: int = 320, *, surround: float = 0.03,
                name: str = "held-out chart", white_tile: float | None = None):
    """A chart scene of arbitrary patch spectra (N, B): a grid of square patches on a dark surround, one mask
    per patch (its central 70 %), like :func:`colorchecker_scene`; ``white_tile`` (a flat reflectance) puts a
    reference white above the patches at :func:`white_tile_roi` (not a mask), for the drift correction of a lab
    rig."""
    spectra = np.asarray(spectra, np.float64)
    n = spectra.shape[0]
    cols = int(math.ceil(math.sqrt(n * width / height)))
    rows = int(math.ceil(n / cols))
    pitch = min(width / (cols + 0.4), height / (rows + 0.4))
    size = 0.84 * pitch
    x0 = (width - cols * pitch) / 2 + (pitch - size) / 2
    y0 = (height - rows * pitch) / 2 + (pitch - size) / 2
    refl = np.full((height, width, spectra.shape[1]), surround, np.float32)
    masks = {}
    for k in range(n):
        r, c = divmod(k, cols)
        ya, xa = y0 + r * pitch, x0 + c * pitch
        refl[int(round(ya)):int(round(ya + size)), int(round(xa)):int(round(xa + size))] = spectra[k]
        m = np.zeros((height, width), bool)
        inset = 0.15 * size
        y0i, y1i = int(round(ya + inset)), int(round(ya + size - inset))
        m[y0i:y1i, int(round(xa + inset)):int(round(xa + size - inset))] = True
        masks[str(names[k])] = m
    if white_tile is not None:
        wt = check_number("white_tile", white_tile, low=0, low_open=True, high=1.5)
        x, y, tw, th = white_tile_roi(height, width)
        tile = np.zeros((height, width), bool)
        tile[max(0, y - 3):y + th + 3, max(0, x - 3):x + tw + 3] = True
        if np.any(tile & np.any(list(masks.values()), axis=0)):
            raise ValueError(f"white_tile: no room above {n} patches at {width} x {height}")
        refl[tile] = wt
    return SpectralScene(np.asarray(wavelengths, np.float64), refl, masks, name)


def white_plate_scene(height: int = 480, width: int = 640, *, reflectance: float = 0.99,
                      wavelengths: ArrayLike | None = None) -> SpectralScene:
    """A uniform reference white plate of flat ``reflectance`` (default 0.99, a pressed-PTFE standard).

    ``wavelengths`` defaults to 380-780 nm at 5 nm. The mask ``"plate"`` covers the whole image.
    """
    h = check_number("height", height, low=1, integer=True)
    w = check_number("width", width, low=1, integer=True)
    r = check_number("reflectance", reflectance, low=0, high=MAX_REFLECTANCE)
    wl = np.arange(380.0, 781.0, 5.0) if wavelengths is None else check_wavelengths("wavelengths", wavelengths)
    refl = np.broadcast_to(np.float32(r), (h, w, wl.size))
    return SpectralScene(wl, refl, {"plate": np.ones((h, w), bool)}, "white")


_NATURAL_IMAGES = ("chelsea", "astronaut", "coffee", "rocket", "motorcycle_left")
_UPSAMPLING = ("Mallett 2019",)


@functools.lru_cache(maxsize=8)
def _natural_cube(image: str, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    rgb = getattr(skimage.data, image)()[..., :3].astype(np.float64) / 255.0
    # Centre-crop to the target aspect ratio, then resample with anti-aliasing.
    ih, iw = rgb.shape[:2]
    target = width / height
    if iw / ih > target:
        cw = int(round(ih * target))
        rgb = rgb[:, (iw - cw) // 2:(iw - cw) // 2 + cw]
    else:
        ch = int(round(iw / target))
        rgb = rgb[(ih - ch) // 2:(ih - ch) // 2 + ch]
    rgb = resize(rgb, (height, width), anti_aliasing=True, order=1)
    linear = np.clip(colour.cctf_decoding(np.clip(rgb, 0.0, 1.0), function="sRGB"), 0.0, 1.0)
    basis = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019
    refl = (linear.reshape(-1, 3) @ basis.values.T).reshape(height, width, -1)
    refl = np.clip(refl, 0.0, 1.0).astype(np.float32)
    refl.setflags(write=False)
    return np.asarray(basis.wavelengths, dtype=np.float64), refl


def natural_scene(height: int = 480, width: int = 640, *, image: str = "chelsea",
                  method: str = "Mallett 2019") -> SpectralScene:
    """A natural scene: a scikit-image sample photograph upsampled to reflectance spectra.

    The sRGB photograph is centre-cropped to the aspect ratio, resized, linearized (sRGB decoding) and turned
    into spectra by Mallett and Yuksel (2019): three non-negative basis spectra weighted by linear R, G, B, so
    every reflectance lies in [0, 1] and reproduces the pixel's sRGB colour under D65. Vectorized (one matrix
    product) and cached per (image, size): a 640 x 480 cube takes well under a second.

    Parameters
    ----------
    height, width
        Image size in pixels.
    image
        scikit-image sample: one of ``"chelsea"``, ``"astronaut"``, ``"coffee"``, ``"rocket"``,
        ``"motorcycle_left"``.
    method
        Spectral upsampling method; ``"Mallett 2019"``.
    """
    if image not in _NATURAL_IMAGES:
        raise ValueError(f"unknown image {image!r}; valid images: {', '.join(_NATURAL_IMAGES)}")
    if method not in _UPSAMPLING:
        raise ValueError(f"unknown upsampling method {method!r}; valid methods: {', '.join(_UPSAMPLING)}")
    h = check_number("height", height, low=1, integer=True)
    w = check_number("width", width, low=1, integer=True)
    wl, refl = _natural_cube(image, h, w)
    return SpectralScene(wl, refl, {}, f"natural:{image}")


#: Built-in scene name -> factory ``f(height, width) -> SpectralScene``.
BUILTIN_SCENES = {
    "colorchecker": colorchecker_scene,
    "white": white_plate_scene,
    "natural": natural_scene,
}


def load_scene(source, height: int = 480, width: int = 640, *, resize: str = "scale") -> SpectralScene:
    """A built-in scene by name (``"natural:<image>"`` picks the photograph), or a cube file by path, at
    (height, width).

    Built-ins are drawn at that size. A file (or a :class:`SpectralScene`) of another size is fitted by
    :func:`resample_scene` with ``resize`` (default ``"scale"``: uniform scaling, another aspect ratio refused);
    the result's ``resampled`` says what was done.
    """
    resize = validate_resize(resize)
    if isinstance(source, SpectralScene):
        return resample_scene(source, height, width, resize)
    text = str(source)
    if text in BUILTIN_SCENES:
        return BUILTIN_SCENES[text](height, width)
    if text.startswith("natural:"):
        return natural_scene(height, width, image=text.partition(":")[2])
    path = Path(text)
    if path.suffix.lower() in (".exr", ".npz", ".hdr"):
        return resample_scene(read_scene(path), height, width, resize, label=str(path))
    raise BadArgument(f"unknown scene {text!r}; give a .exr, .npz or .hdr (ENVI) file or one of: "
                     f"{', '.join(BUILTIN_SCENES)}, natural:<image> with <image> one of {', '.join(_NATURAL_IMAGES)}")
