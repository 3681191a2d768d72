"""The napari spectrum dock widget: the spectrum under the cursor, or the mean +- std over a drawn region, against
wavelength, with the truth when the data records its scene, the predicted +- 1 sigma band when a sigma layer
exists, the region's dE statistics, and the illuminant of the sRGB rendering chosen from colour-science's names.

:class:`SpectrumProbe` does the arithmetic on the viewer's layers (no Qt: tested alone); :func:`SpectrumWidget`
builds the Qt widget around it (napari's widget contribution calls it with the viewer). Layers are found by their
``metadata["specgpu"]["role"]`` (:mod:`specgpu.apps.viewer_layers`).
"""

from __future__ import annotations

import sys

import numpy as np

from specgpu.apps.viewer_layers import ILLUMINANTS, read_layers, sRGB_of_cube
from specgpu.rig.scene import load_scene

__all__ = ["SpectrumProbe", "SpectrumWidget", "add_layers", "open_viewer", "unreadable", "unreadable_note"]


def _role(layer):
    return (getattr(layer, "metadata", None) or {}).get("specgpu", {}).get("role")


class SpectrumProbe:
    """Spectra and statistics read from a napari viewer's specgpu layers.

    The spectrum layer is (wavelength, [time], y, x); the current time step's slice is cached (a recording's
    sequence is one Dask chunk: read once, then every cursor position is a lookup)."""

    def __init__(self, viewer):
        self.viewer = viewer
        self._cache = (None, None, None)
        self._truths = {}

    def layer(self, role):
        """The first layer with ``role`` (``"spectrum"``, ``"sigma"``, ``"dE"``, ``"sRGB"``), or None."""
        return next((layer for layer in self.viewer.layers if _role(layer) == role), None)

    def _time_index(self, layer) -> int | None:
        if layer.ndim < 4:
            return None
        world = self.viewer.dims.point
        data = layer.world_to_data(world[-layer.ndim:] if len(world) >= layer.ndim else world)
        return int(np.clip(round(float(data[1])), 0, layer.data.shape[1] - 1))

    def _slice(self, layer, t):
        """(B, H, W) of ``layer`` at time ``t`` (None: no time axis), as NumPy, cached per (layer, t)."""
        key = (id(layer), id(layer.data), t)  # a live view replaces the layer's data: a new key
        if self._cache[0] != key or self._cache[1] is None:
            data = layer.data if t is None else layer.data[:, t]
            self._cache = (key, np.asarray(data, np.float32), None)
        return self._cache[1]

    def _map_slice(self, layer, t):
        data = layer.data
        if t is not None and data.ndim == 3:
            data = data[t]
        return np.asarray(data, np.float32)

    def truth(self, layer, shape, t=None):
        """The true scene the data records at time step ``t`` (``metadata truths[t]``, a capture that moved, else
        ``scene``), at the data's size; None when it has none or it cannot be rebuilt."""
        meta = layer.metadata["specgpu"] if _role(layer) else {}
        truths = meta.get("truths")
        name = (truths[t] if t is not None and 0 <= t < len(truths) else None) if truths else meta.get("scene")
        if not name:
            return None
        key = (name, shape)
        if key not in self._truths:
            try:
                self._truths[key] = load_scene(name, *shape)
            except (ValueError, OSError):
                self._truths[key] = None
        return self._truths[key]

    def pixel(self, position=None) -> dict | None:
        """The spectrum at a world ``position`` (default the cursor): ``wavelengths``, ``values``, ``sigma`` (or
        None), ``truth`` ((wavelengths, values) or None), ``y``, ``x``, ``t``; None off the image or without a
        spectrum layer."""
        layer = self.layer("spectrum")
        if layer is None:
            return None
        position = self.viewer.cursor.position if position is None else position
        t = self._time_index(layer)
        coords = layer.world_to_data(tuple(position)[-layer.ndim:])
        y, x = (int(round(float(c))) for c in coords[-2:])
        cube = self._slice(layer, t)
        if not (0 <= y < cube.shape[1] and 0 <= x < cube.shape[2]):
            return None
        wl = np.asarray(layer.metadata["specgpu"]["wavelengths"], np.float64)
        sigma_layer = self.layer("sigma")
        sigma = None
        if sigma_layer is not None and sigma_layer.data.shape == layer.data.shape:
            data = sigma_layer.data if t is None else sigma_layer.data[:, t]
            sigma = np.asarray(data[:, y, x], np.float64)
        scene = self.truth(layer, cube.shape[1:], t)
        truth = (scene.wavelengths, scene.reflectance[y, x].astype(np.float64)) if scene is not None else None
        return {"wavelengths": wl, "values": cube[:, y, x].astype(np.float64), "sigma": sigma, "truth": truth,
                "y": y, "x": x, "t": t}

    def region(self, shapes) -> dict | None:
        """Mean +- std of the spectrum over the shapes of a Shapes layer (their union), the truth's mean there, and
        the region's dE statistics (mean, median, p95, max) from a dE layer; None without a spectrum or shapes."""
        layer = self.layer("spectrum")
        if layer is None or shapes is None or len(shapes.data) == 0:
            return None
        t = self._time_index(layer)
        cube = self._slice(layer, t)
        h, w = cube.shape[1:]
        masks = np.asarray(shapes.to_masks(mask_shape=(h, w)), bool).reshape(-1, h, w)
        mask = masks.any(axis=0)
        if not mask.any():
            return None
        pixels = cube[:, mask]
        ok = np.all(np.isfinite(pixels), axis=0)
        pixels = pixels[:, ok].astype(np.float64)
        out = {"wavelengths": np.asarray(layer.metadata["specgpu"]["wavelengths"], np.float64),
               "values": pixels.mean(axis=1), "std": pixels.std(axis=1), "pixels": int(ok.sum()), "truth": None,
               "dE": None}
        scene = self.truth(layer, (h, w), t)
        if scene is not None:
            out["truth"] = (scene.wavelengths, scene.reflectance[mask].astype(np.float64).mean(axis=0))
        de_layer = self.layer("dE")
        if de_layer is not None:
            de = self._map_slice(de_layer, t)
            if de.shape == (h, w):
                v = de[mask]
                v = v[np.isfinite(v)]
                if v.size:
                    out["dE"] = {"mean": float(v.mean()), "median": float(np.median(v)),
                                 "p95": float(np.percentile(v, 95)), "max": float(v.max())}
        return out

    def render(self, illuminant: str) -> bool:
        """Re-render the sRGB layer from the spectrum layer under ``illuminant``; False without both layers."""
        layer, rgb = self.layer("spectrum"), self.layer("sRGB")
        if layer is None or rgb is None:
            return False
        rgb.data = sRGB_of_cube(layer.data, layer.metadata["specgpu"]["wavelengths"], illuminant, axis=0)
        rgb.name = f"sRGB ({illuminant})"
        rgb.metadata["specgpu"]["illuminant"] = illuminant
        return True


def SpectrumWidget(napari_viewer):
    """The spectrum dock widget for ``napari_viewer`` (a Qt widget: a plot, a region button, an illuminant
    choice and a status line). It opens on the spectrum of the image's centre pixel, follows the cursor, and
    keeps the pixel last shown when the time slider moves."""
    from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
    from matplotlib.figure import Figure
    from qtpy.QtWidgets import QComboBox, QHBoxLayout, QLabel, QPushButton, QVBoxLayout, QWidget

    probe = SpectrumProbe(napari_viewer)
    widget = QWidget()
    widget.setObjectName("specgpu-spectrum")
    layout = QVBoxLayout(widget)
    figure = Figure(figsize=(4, 3), layout="constrained")
    canvas = FigureCanvasQTAgg(figure)
    ax = figure.add_subplot()
    status = QLabel("move the cursor over the image")
    status.setWordWrap(True)
    row = QHBoxLayout()
    button = QPushButton("Region (shapes)")
    illuminants = QComboBox()
    illuminants.addItems(list(ILLUMINANTS))
    illuminants.setCurrentText("D65")
    row.addWidget(button)
    row.addWidget(QLabel("render under"))
    row.addWidget(illuminants)
    layout.addWidget(canvas)
    layout.addLayout(row)
    layout.addWidget(status)

    def draw(result, label, band=None):
        ax.clear()
        wl = result["wavelengths"]
        if result.get("truth") is not None:
            ax.plot(*result["truth"], "k--", lw=1, label="truth")
        ax.plot(wl, result["values"], "C3", lw=1.5, label=label)
        if band is not None:
            ax.fill_between(wl, result["values"] - band[0], result["values"] + band[0], color="C3", alpha=0.25,
                            lw=0, label=band[1])
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel("reflectance")
        ax.set_xlim(wl.min(), wl.max())
        ax.legend(fontsize=7, loc="upper left")
        canvas.draw_idle()

    shown = {}  # the pixel last plotted: the plot follows it along the time slider

    def show(position=None):
        """Plot the spectrum at a world ``position`` (default the cursor); a sequence the data refuses (a
        damaged recording's) is named in the status line instead."""
        try:
            result = probe.pixel(position)
        except ValueError as exc:
            status.setText(str(exc))
            return
        if result is None:
            return
        shown["yx"] = (float(result["y"]), float(result["x"]))
        band = (result["sigma"], "± 1σ predicted") if result["sigma"] is not None else None
        where = f"x {result['x']}, y {result['y']}" + (f", sequence {result['t']}" if result["t"] is not None else "")
        draw(result, f"pixel {where}", band)
        status.setText(where)

    def on_move(viewer=None, event=None):
        show()

    def on_step(event=None):
        if "yx" in shown:
            show(tuple(napari_viewer.dims.point[:-2]) + shown["yx"])

    def on_region():
        shapes = next((la for la in reversed(napari_viewer.layers) if la.__class__.__name__ == "Shapes"), None)
        result = probe.region(shapes)
        if result is None:
            status.setText("draw a shape on a Shapes layer over the image first")
            return
        draw(result, f"mean of {result['pixels']} pixels", (result["std"], "± 1 std over the region"))
        de = result["dE"]
        status.setText(f"region: {result['pixels']} pixels" + (
            f"; ΔE00 mean {de['mean']:.2f}, median {de['median']:.2f}, p95 {de['p95']:.2f}, max {de['max']:.2f}"
            if de else ""))

    napari_viewer.mouse_move_callbacks.append(on_move)
    napari_viewer.dims.events.point.connect(on_step)
    spectrum = probe.layer("spectrum")
    if spectrum is not None:  # the centre pixel's spectrum until the cursor moves
        h, w = spectrum.data.shape[-2:]
        show(tuple(napari_viewer.dims.point[:-2]) + ((h - 1) // 2, (w - 1) // 2))
    button.clicked.connect(on_region)
    illuminants.currentTextChanged.connect(lambda name: probe.render(name))
    widget.probe, widget.figure, widget.status, widget.on_move, widget.on_region = (probe, figure, status, on_move,
                                                                                    on_region)
    widget.illuminants, widget.on_step = illuminants, on_step
    return widget


def add_layers(viewer, layers) -> list:
    """Add napari layer-data tuples ``(data, kwargs, layer_type)`` to ``viewer``; the viewer's axes take the
    layers' names (wavelength, time or sequence, y, x). The layers are added hidden and shown once the time slider
    is on a sequence they can show: napari opens at the middle one, which may be one a zarr output refuses (see
    :func:`unreadable`; a corrupt chunk found on the way joins those). Returns the layers added; a zarr output with
    no sequence to show is a one-line error."""
    added, shown = [], []
    for data, kwargs, kind in layers:
        visible = kwargs.get("visible", True)
        new = getattr(viewer, f"add_{kind}")(data, **{**kwargs, "visible": False})
        new = new if isinstance(new, list) else [new]
        added += new
        shown += list(visible) if isinstance(visible, (list, tuple)) else [visible] * len(new)
    named = [layer for layer in added if "axes" in (layer.metadata.get("specgpu") or {})]
    widest = max(named, key=lambda layer: (_role(layer) == "spectrum", layer.ndim), default=None)
    if widest is not None and widest.ndim == viewer.dims.ndim:
        viewer.dims.axis_labels = tuple(widest.metadata["specgpu"]["axes"])
    labels = tuple(viewer.dims.axis_labels)
    if "time" not in labels:
        for layer, visible in zip(added, shown):
            layer.visible = visible
        return added
    # a zarr output: from the middle sequence outwards, the first one every layer shown can read (a corrupt chunk
    # is found only by reading it: its sequence then joins the unreadable ones)
    axis = labels.index("time")
    now = int(viewer.dims.current_step[axis])
    source = next((layer.metadata["specgpu"].get("source") for layer in added if _role(layer)), "")
    bad = unreadable(added)
    for step in sorted(range(int(viewer.dims.nsteps[axis])), key=lambda i: (abs(i - now), i)):
        viewer.dims.set_current_step(axis, step)
        try:  # (a sequence missing only a hidden layer's chunk is shown)
            for layer, visible in zip(added, shown):
                layer.visible = visible
            return added
        except ValueError as exc:  # "PATH/ARRAY: ..." (Recording.read)
            name = str(exc).removeprefix(f"{source}/").split(":", 1)[0]
            bad.setdefault(step, f"its {name} chunk cannot be read")
            for layer in added:
                layer.visible = False
                if _role(layer):
                    layer.metadata["specgpu"]["unreadable"] = dict(sorted(bad.items()))
    first, why = next(iter(sorted(bad.items())))
    raise ValueError(f"{source}: no sequence can be shown, every one is damaged (sequence {first}: {why}, ...)")


def unreadable(layers) -> dict:
    """{sequence: why} of the sequences of which the layers (of a zarr recording or batch output) refuse some."""
    bad = {}
    for layer in layers:
        bad.update((getattr(layer, "metadata", None) or {}).get("specgpu", {}).get("unreadable") or {})
    return dict(sorted(bad.items()))


def unreadable_note(path, layers) -> str | None:
    """One line naming the damaged sequences of ``path`` and why; None when every one is whole."""
    bad = unreadable(layers)
    if not bad:
        return None
    first, why = next(iter(bad.items()))
    more = f" and {len(bad) - 1} more" if len(bad) > 1 else ""
    return f"{path}: sequence {first} is damaged ({why}){more}; the viewer refuses what is missing there"


def open_viewer(path, *, show: bool = True, run: bool = True):
    """A napari viewer on a specgpu path (cube or map, sequence folder, recording) with the spectrum dock widget;
    ``run`` starts napari's event loop (returns when the window closes). Returns the viewer."""
    layers = read_layers(path)  # first: a path that is not specgpu's is refused with or without napari
    import napari

    viewer = napari.Viewer(title=f"specgpu: {path}", show=show)
    added = add_layers(viewer, layers)
    note = unreadable_note(path, added)
    if note:
        print(f"specgpu: {note}", file=sys.stderr)
        viewer.status = note
    viewer.window.add_dock_widget(SpectrumWidget(viewer), name="Spectrum", area="right")
    if run:
        napari.run()
    return viewer
