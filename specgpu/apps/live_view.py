"""``specgpu stream --view``: the stream's latest results in napari while it runs.

The stream runs in a thread of its own; the viewer (on the main thread, as Qt requires) polls a
:class:`specgpu.pipeline.sinks.ResultsRing` of one result that skips a result while the viewer has not taken the
previous one (``drop_newest``, before any copy): the ring never waits for the viewer and copies only the results
the viewer shows (a few a second, not every sequence), so a slow window shows fewer results and the stream's
frames are never dropped for it. Each shown result updates the sRGB rendering (from XYZ), the dE map, and the
cube (wavelength first, in nm; made from the coefficients and the plan's basis when the stream streams those
and no cube, as by default) the spectrum widget reads, each layer on named axes; the status overlay gives
frames/s, sequences/s, the drop counters, the results the view skipped and the latency. When the stream ends the
window stays open on its last result (``close_when_done`` closes it, for scripts and tests).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from specgpu.apps.report_figures import sRGB_rendering
from specgpu.apps.viewer_layers import wavelength_axis
from specgpu.apps.viewer_widget import SpectrumWidget
from specgpu.pipeline.sinks import ResultsRing

__all__ = ["VIEW_OUTPUTS", "LiveView", "run_with_view", "view_ring"]

#: Seconds between the window's opening and the stream's start.
START_DELAY_S = 1.0
#: The stream outputs the view shows (the others are not copied into its ring); the coefficients make the cube
#: when the stream has none (its default outputs).
VIEW_OUTPUTS = ("XYZ", "dE", "cube", "coefficients", "sigma")


def view_ring() -> ResultsRing:
    """The results ring a view polls: one result, skipped while the view has not taken the previous one, and
    optional to the stream (a view that fails is stopped and reported; the recording goes on)."""
    return ResultsRing(capacity=1, outputs=VIEW_OUTPUTS, policy="drop_newest", optional=True, label="view")


class LiveView:
    """The napari layers of a running stream, updated from a results ring (no Qt here but through the viewer)."""

    def __init__(self, viewer, stream, ring, *, wavelengths=None, illuminant: str = "D65", basis=None):
        self.viewer, self.stream, self.ring = viewer, stream, ring
        self.wavelengths = None if wavelengths is None else [float(w) for w in wavelengths]
        # (m, B): coefficients @ basis^T is the cube of a stream that streams coefficients and no cube
        self.basis_T = None if basis is None else np.asarray(basis, np.float32).T
        self.illuminant = illuminant
        self.shown = 0
        self.started = time.perf_counter()
        self.layers = {}

    def _set(self, name, data, **kwargs):
        layer = self.layers.get(name)
        if layer is None:
            self.layers[name] = self.viewer.add_image(data, name=name, **kwargs)
        else:
            layer.data = data

    def show(self, result) -> None:
        """Put one result's maps into the viewer's layers."""
        arrays = result.arrays
        cube = arrays.get("cube")
        if cube is None and "coefficients" in arrays and self.basis_T is not None:
            cube = np.asarray(arrays["coefficients"], np.float32) @ self.basis_T
        if cube is not None and self.wavelengths is not None:
            translate, scale = wavelength_axis(self.wavelengths)
            cube = np.moveaxis(np.asarray(cube, np.float32), -1, 0)
            self._set("reflectance", cube, colormap="gray", contrast_limits=(0.0, 1.0), visible=False,
                      translate=(translate, 0.0, 0.0), scale=(scale, 1.0, 1.0), axis_labels=("wavelength", "y", "x"),
                      metadata={"specgpu": {"role": "spectrum", "wavelengths": self.wavelengths,
                                            "axes": ("wavelength", "y", "x")}})
            if "sigma" in arrays:
                sigma = np.moveaxis(np.asarray(arrays["sigma"], np.float32)[..., :len(self.wavelengths)], -1, 0)
                self._set("sigma", sigma, colormap="viridis", visible=False, contrast_limits=(0.0, 0.05),
                          translate=(translate, 0.0, 0.0), scale=(scale, 1.0, 1.0),
                          axis_labels=("wavelength", "y", "x"),
                          metadata={"specgpu": {"role": "sigma"}})
        if "XYZ" in arrays:
            self._set(f"sRGB ({self.illuminant})", sRGB_rendering(arrays["XYZ"], self.illuminant), rgb=True,
                      axis_labels=("y", "x"),
                      metadata={"specgpu": {"role": "sRGB", "illuminant": self.illuminant}})
        if "dE" in arrays:
            self._set("dE", np.asarray(arrays["dE"], np.float32), colormap="magma", contrast_limits=(0.0, 10.0),
                      opacity=0.7, visible=False, axis_labels=("y", "x"), metadata={"specgpu": {"role": "dE"}})
        self.shown += 1

    def status_text(self, done: bool = False) -> str:
        """frames/s, sequences/s, drops, results skipped by the view, latency."""
        s = self.stream.status()
        elapsed = max(time.perf_counter() - self.started, 1e-9)
        return (f"{'finished: ' if done else ''}{s['frames_in'] / elapsed:.0f} frames/s, "
                f"{s['sequences_out'] / elapsed:.1f} sequences/s, drops {s['assembler_dropped']} "
                f"(ring {s['ring_dropped']}), view showed {self.shown}, skipped {self.ring.dropped}, "
                f"latency {s['latency_ms']:.0f} ms")

    def poll(self, done: bool = False) -> bool:
        """Show the newest result in the ring (never waiting); True when one was shown."""
        newest = None
        while True:
            result = self.ring.get(timeout=0)
            if result is None:
                break
            newest = result
        if newest is not None:
            self.show(newest)
        self.viewer.text_overlay.text = self.status_text(done)
        return newest is not None


def run_with_view(stream, seconds, *, wavelengths=None, illuminant: str = "D65", close_when_done: bool = False,
                  interval_ms: int = 200, title: str = "specgpu stream", on_sink_stopped=None):
    """Run ``stream`` for ``seconds`` in a thread while napari shows its latest results; returns the stream's
    report (after the window is closed, or at once when ``close_when_done``). An error in the stream is raised
    here; ``on_sink_stopped`` is given each optional sink the stream stopped (the view's ring among them), from
    the stream's thread."""
    import napari
    from qtpy.QtCore import QTimer

    ring = view_ring()
    stream.sinks.append(ring)
    outcome = {}

    def work():
        try:
            outcome["report"] = stream.run(seconds, on_sink_stopped=on_sink_stopped)
        except BaseException as error:  # noqa: BLE001 (re-raised on the main thread)
            outcome["error"] = error
        finally:
            ring.close()

    viewer = napari.Viewer(title=title)
    viewer.text_overlay.visible = True
    viewer.text_overlay.position = "top_left"
    view = LiveView(viewer, stream, ring, wavelengths=wavelengths, illuminant=illuminant,
                    basis=getattr(getattr(stream, "decoder", None), "basis", None))
    viewer.window.add_dock_widget(SpectrumWidget(viewer), name="Spectrum", area="right")
    thread = threading.Thread(target=work, name="specgpu-stream-view", daemon=True)
    timer = QTimer()

    def tick():
        done = not thread.is_alive()
        view.poll(done)
        if done:
            timer.stop()
            if close_when_done:
                viewer.close()

    def start():
        thread.start()
        timer.start(int(interval_ms))

    timer.timeout.connect(tick)
    # the stream starts once the window has drawn itself: napari's start-up (OpenGL, fonts, the first paint) is
    # a burst of CPU that would otherwise land on the stream's first sequences
    QTimer.singleShot(int(START_DELAY_S * 1000), start)
    try:
        napari.run()
    except KeyboardInterrupt:
        stream.stop()
    if thread.is_alive():  # the window closed early: stop the stream, keep what it did
        stream.stop()
        thread.join()
    if "report" not in outcome and "error" not in outcome:  # closed before the stream started
        raise KeyboardInterrupt
    if "error" in outcome:
        raise outcome["error"]
    return outcome["report"]
