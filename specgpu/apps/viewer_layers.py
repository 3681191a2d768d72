"""What the napari viewer shows of specgpu's files: layer data for cubes (EXR / ENVI / npz), maps (XYZ, Lab,
dE, sigma EXR), sequence folders, zarr recordings and batch outputs, and the napari reader that picks one by path.

Layers follow one layout so they line up in the viewer: the wavelength axis first (world coordinate in nm for an
evenly sampled cube: the slider reads the wavelength), then time (one step per sequence) for sequence folders,
recordings and batch outputs, then y, x; every layer names its axes. A rendering or a map (no wavelength axis) has
the same trailing axes, so napari aligns it with the cube. Sequence folders and zarr outputs are read lazily (Dask,
one chunk per sequence): a sequence is read, and a sequence folder's recovered on the device, only when the time
slider reaches it. A recording's sequence is read through :meth:`specgpu.io.recording.Recording.read`, as every
specgpu reader reads it: a missing or corrupt chunk (or a batch's sequence not computed yet) is refused in one line
naming the path and the sequence, never shown as fill values. The reflectance of a recording of coefficients (the
stream's default) is made from them and their recorded basis, one sequence at a time.

Each layer's ``metadata["specgpu"]`` says what it holds (``role``: ``"spectrum"``, ``"sigma"``, ``"sRGB"``,
``"dE"``, ...; ``wavelengths``; ``scene``: the truth the capture records, or ``truths``: one motion truth file per
sequence of a capture that moved; ``unreadable``: {sequence: why} of the sequences of a zarr output that cannot be
shown), which the spectrum widget and :func:`add_layers <specgpu.apps.viewer_widget.add_layers>` read.
Nothing here imports Qt or napari: readers return napari's layer-data tuples ``(data, kwargs, layer_type)``.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import colour
import numpy as np

from specgpu import io
from specgpu.apps.report_figures import sRGB_rendering
from specgpu.core.spectra import XYZ_weights
from specgpu.io.motion_truth import TRUTH_FOLDER, truth_name
from specgpu.io.previews import sRGB8
from specgpu.io.sequence import read_frames
from specgpu.pipeline.batch import BATCH_FORMAT
from specgpu.pipeline.batch_output import open_batch_output
from specgpu.pipeline.capture_folder import PLAN_FILE, SequenceFolder, read_capture_header
from specgpu.pipeline.motion_record import motion_notice, moved
from specgpu.pipeline.recovery import recover
from specgpu.planning.plans import load_plan

__all__ = ["CUBE_SUFFIXES", "napari_get_reader", "read_layers", "cube_layers", "map_layers", "sequence_layers",
           "recording_layers", "batch_layers", "results_layers", "recorded_basis", "recorded_white_xy", "sRGB_of_cube",
           "wavelength_axis", "ILLUMINANTS", "VIEW_MOTION", "motion_note"]

CUBE_SUFFIXES = (".exr", ".npz", ".hdr")
#: The illuminants a rendering can be chosen under (colour-science's CIE 1931 names with a chromaticity).
ILLUMINANTS = tuple(name for name in colour.SDS_ILLUMINANTS
                    if name in colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"])
#: The compensation a sequence folder captured while the scene moved is decoded with (recover's --motion mode).
VIEW_MOTION = "global"
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
    when the slider reaches a sequence, the plan's outputs (wavelength, sequence, y, x) with their sRGB. A capture
    that moved (:func:`specgpu.pipeline.motion_record.moved`) is decoded with motion compensation
    (:data:`VIEW_MOTION`), and its spectrum layer records, instead of a still scene, the motion truth file of each
    sequence (``truths``)."""
    import dask
    import dask.array as da

    path = Path(path)
    records, meta, plan, bundle = read_capture_header(path)
    K, h, w = plan.K, meta["height"], meta["width"]
    S = len(records) // K
    recorded = meta.get("metadata", {}) or {}
    roi = recorded.get("white_roi")
    # a capture that moved: each sequence decoded motion-compensated, its truth the one recorded for it
    moving = moved(path)
    truths = [str(p) if p.is_file() else None for p in (path / TRUTH_FOLDER / truth_name(s)
                                                        for s in range(S))] if moving else None

    # the frames layer, the cube and its sRGB are computed apart by napari: each sequence is read and recovered
    # once, for the sequence shown and the one before it
    @functools.lru_cache(maxsize=2)
    def frames_of(s):
        return read_frames(path, records, meta, s * K, (s + 1) * K)

    @functools.lru_cache(maxsize=2)
    def recovered(s):
        one = SequenceFolder(path, frames_of(s)[None], plan, bundle, records, meta)
        return recover(one, motion=VIEW_MOTION) if moving else recover(one, white_roi=roi)

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
                              scene=None if moving else recorded.get("scene"), truths=truths,
                              motion=VIEW_MOTION if moving else "none", axes=("wavelength", "sequence", "y", "x"))},
            "image"))
        layers.insert(0, (sRGB_of_cube(y, plan.output_wavelengths, illuminant),
                          {"name": f"sRGB ({illuminant})", "rgb": True,
                           "metadata": _meta("sRGB", path, illuminant=illuminant)}, "image"))
    return layers


def motion_note(path) -> str | None:
    """The one line ``specgpu view`` says of a sequence folder captured while the scene moved (None otherwise):
    what :func:`sequence_layers` shows of it."""
    return motion_notice(path, f"shown as `specgpu recover --motion {VIEW_MOTION} --sequence N` decodes each "
                               "sequence (motion-compensated), the spectrum widget's truth the motion truth recorded "
                               "for the sequence shown") if Path(path).is_dir() else None



def _lazy(results, name, n, block=None):
    """Array ``name`` of a recording or batch output as Dask, one chunk per sequence, each read through
    ``results.read`` (so a sequence with a missing or corrupt chunk, or not computed yet, is refused in one line
    naming it, never shown as fill values); ``block`` maps each sequence's array (e.g. coefficients to a cube)."""
    import dask.array as da

    arr = results.array(name)
    sample = np.zeros((1, *arr.shape[1:]), np.dtype(arr.dtype).newbyteorder("="))
    sample = sample if block is None else block(sample)

    def read(block_info=None):
        values = results.read(name, block_info[None]["chunk-location"][0])[None]
        return values if block is None else block(values)

    return da.map_blocks(read, chunks=((1,) * n, *((s,) for s in sample.shape[1:])), dtype=sample.dtype,
                         meta=sample[:0])


def recorded_basis(results, path):
    """(basis (B, m), wavelengths (B,)) that turn a recording's coefficients into reflectance: the basis and its
    recorded ``basis_wavelength``, else the output wavelengths of the plan copied into the recording when it is the
    recorded plan and its output is reflectance; None when the recording has no such basis."""
    if "coefficients" not in results.attrs.get("outputs", []) or "basis" not in results.group:
        return None
    basis = np.asarray(results.group["basis"][:], np.float64)
    if "basis_wavelength" in results.group:
        return basis, np.asarray(results.group["basis_wavelength"][:], np.float64)
    plan_file = Path(path) / PLAN_FILE
    if not plan_file.is_file():
        return None
    try:
        plan = load_plan(plan_file)
    except (ValueError, OSError):
        return None
    wl = np.asarray(plan.output_wavelengths, np.float64)
    if plan.hash != results.attrs.get("plan_hash") or plan.output != "reflectance" or wl.shape != basis.shape[:1]:
        return None
    return basis, wl


def _unreadable(results, names) -> dict:
    """{sequence: why} of the sequences that cannot be shown: not computed yet (a batch output) or a chunk of one
    of the arrays ``names`` missing."""
    bad = {i: "not computed yet" for i in getattr(results, "pending", [])}
    for name in names:
        for i in results.missing(name):
            bad.setdefault(i, f"its {name} chunk is missing")
    return dict(sorted(bad.items()))


def _time_layer(data, name, meta, **kwargs):
    """A layer along (time, y, x) (an rgb one with its 3 channels after) with named axes."""
    return data, {"name": name, "axis_labels": ("time", "y", "x"), "metadata": meta, **kwargs}, "image"


def recorded_white_xy(results, path, illuminant, colours):
    """The chromaticity of the white a recording's (or batch output's) XYZ is relative to: its plan's
    (:meth:`specgpu.planning.plans.Plan.white_XYZ` for the ``observer`` and ``integration`` of ``colours``, what
    the decoder divided by), so a perfect white renders as 255; None when the plan is missing or not the one the
    XYZ were decoded with."""
    plan_file = Path(path) / PLAN_FILE
    if not plan_file.is_file():
        return None
    try:
        plan = load_plan(plan_file)
        if plan.hash != results.attrs.get("plan_hash"):
            return None
        white = plan.white_XYZ(illuminant, colours.get("observer"), colours.get("integration") or "rectangle")
    except (ValueError, OSError):
        return None
    return np.asarray(colour.XYZ_to_xy(white), np.float64)


def results_layers(results, path, *, illuminant="D65", scene=None, xyz_illuminant="D65", xyz_colours=None) -> list:
    """Layers of a zarr recording or batch output, lazily (one Dask chunk per sequence): the reflectance
    (wavelength, time, y, x; from the cube, or from the coefficients and their basis) with its sRGB (else the sRGB
    of XYZ, adapted from the white of the plan's weights, :func:`recorded_white_xy`, for the ``observer`` and
    ``integration`` of ``xyz_colours``), hidden XYZ channels, dE and sigma maps with colour maps and limits. Every
    layer names its axes and lists in its metadata (``unreadable``) the sequences it refuses."""
    n = results.sequences
    names = [name for name in results.attrs.get("outputs", []) if name in results.group]
    unreadable = _unreadable(results, names)
    layers = []
    cube = wl = None
    if "cube" in names and "wavelength" in results.group:
        wl = np.asarray(results.group["wavelength"][:], np.float64)
        cube = _lazy(results, "cube", n)
    elif (basis := recorded_basis(results, path)) is not None:
        U = basis[0].T.astype(np.float32)
        wl = basis[1]
        cube = _lazy(results, "coefficients", n, block=lambda c: np.asarray(c, np.float32) @ U)
    if cube is not None:
        translate, scale = wavelength_axis(wl)
        layers.append(_time_layer(sRGB_of_cube(cube, wl, illuminant), f"sRGB ({illuminant})",
                                  _meta("sRGB", path, illuminant=illuminant, unreadable=unreadable), rgb=True))
        spectral = {"translate": (translate, 0.0, 0.0, 0.0), "scale": (scale, 1.0, 1.0, 1.0),
                    **_axes(("wavelength", "time", "y", "x"), translate, scale)}
        wavelengths = [float(v) for v in wl]
        layers.append((_channels_first(cube), {
            "name": "reflectance", "colormap": "gray", "contrast_limits": (0.0, 1.0), "visible": False, **spectral,
            "metadata": _meta("spectrum", path, wavelengths=wavelengths, scene=scene,
                              axes=("wavelength", "time", "y", "x"), unreadable=unreadable)}, "image"))
        if "sigma" in names:
            sigma = _lazy(results, "sigma", n)[..., :len(wl)]
            layers.append((_channels_first(sigma), {
                "name": "sigma", "colormap": "viridis", "visible": False, "contrast_limits": (0.0, 0.05), **spectral,
                "metadata": _meta("sigma", path, wavelengths=wavelengths, unreadable=unreadable)}, "image"))
    elif "XYZ" in names:
        xy = recorded_white_xy(results, path, xyz_illuminant, xyz_colours or {})
        rgb = _lazy(results, "XYZ", n, block=lambda x: (sRGB_rendering(x[0], xyz_illuminant) if xy is None
                                                        else sRGB8(x[0], xy))[None])
        layers.append(_time_layer(rgb, f"sRGB ({xyz_illuminant})",
                                  _meta("sRGB", path, illuminant=xyz_illuminant, unreadable=unreadable), rgb=True))
    if "XYZ" in names:
        layers.append((_channels_first(_lazy(results, "XYZ", n)), {
            "name": ["X", "Y", "Z"], "channel_axis": 0, "visible": False, "colormap": ["red", "green", "blue"],
            "contrast_limits": [(0.0, 1.0)] * 3, "axis_labels": [("time", "y", "x")] * 3,
            "metadata": _meta("XYZ", path, unreadable=unreadable)}, "image"))
    readable = next((i for i in range(n) if i not in unreadable), None)
    for name in ("dE", "sigma_rms", "dE_sigma"):
        if name in names:
            cmap, limits = MAP_STYLE[name]
            if limits is None:
                limits = _limits(results.read(name, readable)) if readable is not None else (0.0, 1.0)
            layers.append(_time_layer(_lazy(results, name, n), name, _meta(name, path, unreadable=unreadable),
                                      colormap=cmap, opacity=0.7, visible=False, contrast_limits=limits))
    if not layers:
        raise ValueError(f"{path}: holds nothing the viewer shows (outputs: {', '.join(names) or 'none'})")
    return layers


def _channels_first(data):
    """(time, y, x, channel) -> (channel, time, y, x): the channel (wavelength) axis first, as the cubes."""
    import dask.array as da

    return da.moveaxis(data, -1, 0)


def recording_layers(path, *, illuminant="D65") -> list:
    """Layers of a zarr recording (:func:`results_layers`), cut to its committed sequences."""
    rec = io.open_recording(path)
    if rec.sequences == 0:
        raise ValueError(f"{path}: the recording holds no committed sequence")
    meta = rec.attrs.get("metadata") or {}
    return results_layers(rec, path, illuminant=illuminant, scene=meta.get("scene"),
                          xyz_illuminant=_illuminant(meta.get("illuminant")), xyz_colours=meta)


def batch_layers(path, *, illuminant="D65") -> list:
    """Layers of a ``specgpu batch`` output (:func:`results_layers`): every sequence of its source along time,
    those the batch has not computed refused."""
    out = open_batch_output(path)
    return results_layers(out, path, illuminant=illuminant, xyz_illuminant=_illuminant(out.attrs.get("illuminant")),
                          xyz_colours=out.attrs)


def _illuminant(name) -> str:
    return name if name in ILLUMINANTS else "D65"


def _zarr_format(path: Path):
    """The ``format`` attribute of the zarr group at ``path`` (None when it has none or cannot be read)."""
    try:
        return json.loads((path / "zarr.json").read_text()).get("attributes", {}).get("format")
    except (OSError, ValueError, AttributeError):
        return None


def read_layers(path) -> list:
    """The layers of any specgpu file or folder: a cube or map (.exr / .npz / .hdr), a sequence folder, a zarr
    recording or batch output; anything else is a one-line error naming the path."""
    p = Path(path)
    if p.is_dir():
        if (p / io.SEQUENCE_FILE).is_file():
            return sequence_layers(p)
        if (p / "zarr.json").is_file():
            return batch_layers(p) if _zarr_format(p) == BATCH_FORMAT else recording_layers(p)
        raise ValueError(f"{p}: neither a sequence folder ({io.SEQUENCE_FILE}) nor a zarr recording or batch output")
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
