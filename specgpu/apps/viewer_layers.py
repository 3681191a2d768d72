"""What the napari viewer shows of specgpu's files: layer data for cubes (EXR / ENVI / npz), maps (XYZ, Lab,
dE, sigma EXR), sequence folders and zarr recordings, and the napari reader that picks one by path.

Layers follow one layout so they line up in the viewer: the wavelength axis first (world coordinate in nm for an
evenly sampled cube: the slider reads the wavelength), then time (one step per sequence) for sequence folders
and recordings, then y, x. A rendering or a map (no wavelength axis) has the same trailing axes, so napari
aligns it with the cube. Sequence folders and recordings are read lazily (Dask, one chunk per sequence): a
sequence is read, and a sequence folder's recovered on the device, only when the time slider reaches it.

Each layer's ``metadata["specgpu"]`` says what it holds (``role``: ``"spectrum"``, ``"sigma"``, ``"sRGB"``,
``"dE"``, ...; ``wavelengths``; ``scene``: the truth the capture records), which the spectrum widget reads.
Nothing here imports Qt or napari: readers return napari's layer-data tuples ``(data, kwargs, layer_type)``.
"""

from __future__ import annotations

import functools
from pathlib import Path

import colour
import numpy as np

from specgpu import io
from specgpu.apps.report_figures import sRGB_rendering
from specgpu.core.spectra import XYZ_weights
from specgpu.io.previews import sRGB8
from specgpu.io.sequence import read_frames
from specgpu.pipeline.recovery import SequenceFolder, read_capture_header, recover

__all__ = ["CUBE_SUFFIXES", "napari_get_reader", "read_layers", "cube_layers", "map_layers", "sequence_layers",
           "recording_layers", "sRGB_of_cube", "wavelength_axis", "ILLUMINANTS"]

CUBE_SUFFIXES = (".exr", ".npz", ".hdr")
#: The illuminants a rendering can be chosen under (colour-science's CIE 1931 names with a chromaticity).
ILLUMINANTS = tuple(name for name in colour.SDS_ILLUMINANTS
                    if name in colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"])
#: Colour map and limits of each map kind: (colormap, (low, high) or None for the data's 1st-99th percentile).
MAP_STYLE = {"dE": ("magma", (0.0, 10.0)), "dE_sigma": ("magma", None), "sigma": ("viridis", None),
             "sigma_rms": ("viridis", None)}


def wavelength_axis(wavelengths) -> tuple[float, float]:
    """(translate, scale) of the wavelength axis: nm for an evenly spaced grid (the slider reads nm), else band
    index (translate 0, scale 1)."""
    wl = np.asarray(wavelengths, np.float64)
    if wl.size > 1 and np.allclose(np.diff(wl), wl[1] - wl[0], rtol=1e-6, atol=1e-6) and wl[1] > wl[0]:
        return float(wl[0]), float(wl[1] - wl[0])
    return 0.0, 1.0


def _axes(names, translate, scale) -> dict:
    """The layer's named axes and units: the wavelength in nm on an even grid (else a band index), pixels
    elsewhere."""
    in_nm = (translate, scale) != (0.0, 1.0)
    return {"axis_labels": tuple(names),
            "units": tuple(("nm" if in_nm else "pixel") if n == "wavelength" else "pixel" for n in names)}


def _meta(role, source, **more) -> dict:
    return {"specgpu": {"role": role, "source": str(source), **more}}


def sRGB_of_cube(cube, wavelengths, illuminant: str = "D65", axis: int = -1):
    """(..., 3) uint8 sRGB of a reflectance cube (wavelengths along ``axis``) under ``illuminant``, adapted to
    sRGB's D65 white (a perfect white at 255); NumPy or Dask in, the same out (Dask lazily)."""
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"].get(illuminant)
    if xy is None:
        raise ValueError(f"unknown illuminant {illuminant!r}; valid: {', '.join(ILLUMINANTS)}")
    W = XYZ_weights(np.asarray(wavelengths, np.float64), illuminant)
    xy = colour.XYZ_to_xy(W.sum(axis=1))  # the white of these weights: a perfect white renders as 255
    W = W.astype(np.float32)

    def render(block):  # wavelengths on the last axis
        return sRGB8(np.asarray(block, np.float32) @ W.T, xy)

    if hasattr(cube, "map_blocks"):  # a Dask array: one rendering per block (per sequence)
        import dask.array as da

        moved = da.moveaxis(cube, axis, -1).rechunk({-1: -1})
        return moved.map_blocks(render, dtype=np.uint8, chunks=moved.chunks[:-1] + ((3,),))
    return render(np.moveaxis(np.asarray(cube), axis, -1))


def _limits(data, low=1.0, high=99.0) -> tuple[float, float]:
    sample = np.asarray(data)
    finite = sample[np.isfinite(sample)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(finite, [low, high]))
    return (lo, hi) if hi > lo else (lo, lo + 1.0)


def cube_layers(path, cube=None, wavelengths=None, meta=None, *, illuminant="D65") -> list:
    """Layers of a reflectance cube (H, W, B): the cube (wavelength axis first, in nm) and its sRGB rendering."""
    if cube is None:
        cube, wavelengths, meta = io.read_cube(path)
    translate, scale = wavelength_axis(wavelengths)
    wl = [float(w) for w in wavelengths]
    data = np.moveaxis(np.asarray(cube, np.float32), -1, 0)
    scene = (meta or {}).get("scene")
    return [
        (sRGB_of_cube(cube, wavelengths, illuminant), {"name": f"sRGB ({illuminant})", "rgb": True,
                                                        "metadata": _meta("sRGB", path, illuminant=illuminant)},
         "image"),
        (data, {"name": "reflectance", "colormap": "gray", "contrast_limits": (0.0, 1.0),
                "translate": (translate, 0.0, 0.0), "scale": (scale, 1.0, 1.0), "visible": False,
                **_axes(("wavelength", "y", "x"), translate, scale),
                "metadata": _meta("spectrum", path, wavelengths=wl, scene=scene, axes=("wavelength", "y", "x"))},
         "image"),
    ]


def map_layers(path) -> list:
    """Layers of a map EXR written by ``specgpu recover`` (XYZ, Lab, dE, sigma): XYZ as three channel layers with
    its sRGB rendering, a dE or sigma map with its colour map and limits."""
    data, names, meta = io.read_map(path)
    kind = meta.get("kind") or ("XYZ" if tuple(names) == ("X", "Y", "Z") else "map")
    if tuple(names) == ("X", "Y", "Z"):
        illuminant = meta.get("illuminant") if meta.get("illuminant") in ILLUMINANTS else "D65"
        rgb8 = sRGB_rendering(data, illuminant)
        return [(rgb8, {"name": f"sRGB ({illuminant})", "rgb": True, "metadata": _meta("sRGB", path)}, "image"),
                (np.moveaxis(data, -1, 0), {"name": ["X", "Y", "Z"], "channel_axis": 0, "visible": False,
                                            "colormap": ["red", "green", "blue"], "contrast_limits": [(0.0, 1.0)] * 3,
                                            "metadata": _meta("XYZ", path)}, "image")]
    layers = []
    for i, name in enumerate(names):
        base = "sigma" if name.startswith("sigma") else ("dE" if name.lower().startswith(("de", "delta")) else name)
        cmap, limits = MAP_STYLE.get(base, ("gray", None))
        channel = data[..., i]
        layers.append((channel, {"name": name, "colormap": cmap, "contrast_limits": limits or _limits(channel),
                                 "metadata": _meta(base, path, kind=kind)}, "image"))
    return layers


def sequence_layers(path, *, illuminant="D65") -> list:
    """Layers of a sequence folder, lazily: the raw frames (sequence, pattern, y, x) and, recovered on the device
    when the slider reaches a sequence, the plan's outputs (wavelength, sequence, y, x) with their sRGB."""
    import dask
    import dask.array as da

    path = Path(path)
    records, meta, plan, bundle = read_capture_header(path)
    K, h, w = plan.K, meta["height"], meta["width"]
    S = len(records) // K
    recorded = meta.get("metadata", {}) or {}
    roi = recorded.get("white_roi")

    # the frames layer, the cube and its sRGB are computed apart by napari: each sequence is read and recovered
    # once, for the sequence shown and the one before it
    @functools.lru_cache(maxsize=2)
    def frames_of(s):
        return read_frames(path, records, meta, s * K, (s + 1) * K)

    @functools.lru_cache(maxsize=2)
    def recovered(s):
        one = SequenceFolder(path, frames_of(s)[None], plan, bundle, records, meta)
        return recover(one, white_roi=roi)

    B = len(plan.output_wavelengths)
    # pattern first, then sequence: the frames line up with the cube's (wavelength, sequence, y, x)
    frames = da.stack([da.from_delayed(dask.delayed(frames_of)(s), (K, h, w), np.uint16) for s in range(S)], axis=1)
    y = da.stack([da.from_delayed(dask.delayed(recovered)(s), (h, w, B), np.float32) for s in range(S)])
    layers = [(frames, {"name": "frames", "colormap": "gray", "contrast_limits": (0.0, float(bundle.max_code)),
                        "visible": False, "metadata": _meta("frames", path, axes=("pattern", "sequence", "y", "x"))},
               "image")]
    if plan.output == "reflectance":
        translate, scale = wavelength_axis(plan.output_wavelengths)
        layers.append((da.moveaxis(y, -1, 0), {
            "name": "reflectance", "colormap": "gray", "contrast_limits": (0.0, 1.0), "visible": False,
            "translate": (translate, 0.0, 0.0, 0.0), "scale": (scale, 1.0, 1.0, 1.0),
            **_axes(("wavelength", "sequence", "y", "x"), translate, scale),
            "metadata": _meta("spectrum", path, wavelengths=[float(v) for v in plan.output_wavelengths],
                              scene=recorded.get("scene"), axes=("wavelength", "sequence", "y", "x"))}, "image"))
        layers.insert(0, (sRGB_of_cube(y, plan.output_wavelengths, illuminant),
                          {"name": f"sRGB ({illuminant})", "rgb": True,
                           "metadata": _meta("sRGB", path, illuminant=illuminant)}, "image"))
    return layers


def recording_layers(path, *, illuminant="D65") -> list:
    """Layers of a zarr recording, lazily (one Dask chunk per sequence, cut to the committed sequences): the
    cube (wavelength, time, y, x) with its sRGB, XYZ channels, dE and sigma maps with colour maps and limits."""
    import dask.array as da

    rec = io.open_recording(path)
    n = rec.sequences
    if n == 0:
        raise ValueError(f"{path}: the recording holds no committed sequence")
    names = set(rec.attrs.get("outputs", []))
    scene = (rec.attrs.get("metadata") or {}).get("scene")
    layers = []

    def lazy(name):
        return da.from_zarr(rec.array(name))[:n]

    if "cube" in names and "wavelength" in rec.group:
        wl = np.asarray(rec.group["wavelength"][:], np.float64)
        cube = lazy("cube")
        translate, scale = wavelength_axis(wl)
        layers.append((sRGB_of_cube(cube, wl, illuminant), {"name": f"sRGB ({illuminant})", "rgb": True,
                                                            "metadata": _meta("sRGB", path, illuminant=illuminant)},
                       "image"))
        layers.append((da.moveaxis(cube, -1, 0), {
            "name": "reflectance", "colormap": "gray", "contrast_limits": (0.0, 1.0), "visible": False,
            "translate": (translate, 0.0, 0.0, 0.0), "scale": (scale, 1.0, 1.0, 1.0),
            **_axes(("wavelength", "time", "y", "x"), translate, scale),
            "metadata": _meta("spectrum", path, wavelengths=[float(v) for v in wl], scene=scene,
                              axes=("wavelength", "time", "y", "x"))}, "image"))
        if "sigma" in names:
            sigma = lazy("sigma")[..., :len(wl)]
            layers.append((da.moveaxis(sigma, -1, 0), {
                "name": "sigma", "colormap": "viridis", "visible": False, "contrast_limits": (0.0, 0.05),
                "translate": (translate, 0.0, 0.0, 0.0), "scale": (scale, 1.0, 1.0, 1.0),
                **_axes(("wavelength", "time", "y", "x"), translate, scale),
                "metadata": _meta("sigma", path, wavelengths=[float(v) for v in wl])}, "image"))
    if "XYZ" in names:
        layers.append((da.moveaxis(lazy("XYZ"), -1, 0), {
            "name": ["X", "Y", "Z"], "channel_axis": 0, "visible": False, "colormap": ["red", "green", "blue"],
            "contrast_limits": [(0.0, 1.0)] * 3, "metadata": _meta("XYZ", path)}, "image"))
    for name in ("dE", "sigma_rms", "dE_sigma"):
        if name in names:
            data = lazy(name)
            cmap, limits = MAP_STYLE[name]
            layers.append((data, {"name": name, "colormap": cmap, "opacity": 0.7, "visible": False,
                                  "contrast_limits": limits or _limits(rec.read(name, 0)),
                                  "metadata": _meta(name, path)}, "image"))
    return layers


def read_layers(path) -> list:
    """The layers of any specgpu file or folder: a cube or map (.exr / .npz / .hdr), a sequence folder, a zarr
    recording; anything else is a one-line error naming the path."""
    p = Path(path)
    if p.is_dir():
        if (p / io.SEQUENCE_FILE).is_file():
            return sequence_layers(p)
        if (p / "zarr.json").is_file():
            return recording_layers(p)
        raise ValueError(f"{p}: neither a sequence folder ({io.SEQUENCE_FILE}) nor a zarr recording")
    if p.suffix.lower() not in CUBE_SUFFIXES:
        raise ValueError(f"{p}: not a specgpu cube, map, sequence folder or recording ({', '.join(CUBE_SUFFIXES)}, "
                         "a folder)")
    try:
        cube, wavelengths, meta = io.read_cube(p)
    except ValueError:
        if p.suffix.lower() != ".exr":
            raise
        return map_layers(p)
    return cube_layers(p, cube, wavelengths, meta)


def napari_get_reader(path):
    """napari's reader hook: a reader for one specgpu path (None for a list or a path that is not one)."""
    if isinstance(path, (list, tuple)):
        if len(path) != 1:
            return None
        path = path[0]
    p = Path(path)
    if p.is_dir():
        if not ((p / io.SEQUENCE_FILE).is_file() or (p / "zarr.json").is_file()):
            return None
    elif p.suffix.lower() not in CUBE_SUFFIXES:
        return None
    return lambda _path: read_layers(p)
