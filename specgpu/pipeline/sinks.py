"""What a stream hands its results to: :class:`StreamResult` (the maps of one sequence) and the sinks that
consume them on the stream's sink thread: a callback, a ring of copies for a polling consumer, EXR snapshots
and a live sRGB preview. The recording sink, which keeps every sequence, is
:class:`specgpu.io.recording.ZarrRecorder`.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import colour
import numpy as np
from numpy.typing import ArrayLike

from specgpu import io
from specgpu.capture.ringbuffer import wait_for_items
from specgpu.core.spectra import DEFAULT_CMFS, white_point_XYZ
from specgpu.io.previews import write_png

__all__ = ["CallbackSink", "ExrSequenceWriter", "PreviewSink", "ResultsRing", "Sink", "StreamResult", "sink_label"]


# ----------------------------------------------------------------------------------------------------- results


@dataclass
class StreamResult:
    """The maps of one complete, aligned sequence, handed to every sink in turn.

    The arrays are views of recycled buffers: valid only while the sink is called; copy what you keep.

    Attributes
    ----------
    index : int
        Ordinal of the result in the stream (0, 1, ...).
    cycle : int
        The assembler's cycle of the sequence (which pass through the light's pattern sequence).
    frame_ids : numpy.ndarray
        (K,) consecutive frame ids, frame ``j`` lit by pattern ``j``.
    timestamps_s : numpy.ndarray
        (K,) exposure starts in the driver's clock, s.
    arrays : dict of str to numpy.ndarray
        Per output of the stream: ``coefficients`` (H, W, m), ``cube`` (H, W, B), ``XYZ`` / ``Lab`` (H, W, 3),
        ``dE`` (H, W).
    saturated_pixels : int
        Pixels where a frame sat at the sensor's maximum code: their outputs are NaN (as ``pipeline.recover``).
    latency_s : float
        From the arrival of the sequence's last frame in host memory (the driver's fill returned: for a camera,
        exposure end plus readout) to the result being ready for the sinks, s.
    frames : numpy.ndarray, optional
        (K, H, W) the sequence's raw frames (DN), valid during the call only (a recorder keeps them on request).
    white_gains : numpy.ndarray, optional
        (K,) the white reference's measured / predicted output per pattern that corrected this sequence's
        decoder (a stream with ``white_roi``), else None.
    motion : specgpu.motion.estimate.MotionEstimate, optional
        The sequence's estimated displacements (a stream with ``motion``): the maps are the scene at the
        sequence's reference time, NaN where a frame saw it outside the field or the frames disagree.
    layers : list, optional
        The :class:`specgpu.pipeline.moving_layers.ObjectLayer` of each object decoded with its own motion (a
        stream with ``motion``; their pixels carry mask bit 16).
    """

    index: int
    cycle: int
    frame_ids: np.ndarray
    timestamps_s: np.ndarray
    arrays: dict
    latency_s: float
    saturated_pixels: int = 0
    frames: np.ndarray | None = None
    white_gains: np.ndarray | None = None
    motion: object = None
    layers: list | None = None


class Sink:
    """A consumer of results: :meth:`write` is called on the sink thread for each result in order, :meth:`close`
    once at the end. A sink that is slower than the stream makes the frame ring's policy act (backpressure).

    Attributes
    ----------
    optional : bool
        A sink the stream can do without (snapshots, a preview, a view): when it fails the stream reports it in
        one line, stops that sink and keeps going. A failing sink that is not optional (a recording, a caller's
        callback) stops the capture; the sequences already captured still reach the other sinks.
    label : str or None
        The sink's name in those reports (default: its class name).
    """

    optional: bool = False
    label: str | None = None

    def write(self, result: StreamResult) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        """Flush and release what the sink holds."""


def sink_label(sink) -> str:
    """The name a stream gives ``sink`` in its reports: its ``label``, else its class name."""
    return getattr(sink, "label", None) or type(sink).__name__


class CallbackSink(Sink):
    """Calls ``fn(result)`` for each result (the arrays are valid during the call only)."""

    def __init__(self, fn):
        if not callable(fn):
            raise TypeError(f"CallbackSink needs a callable, got {type(fn).__name__}")
        self.fn = fn

    def write(self, result):
        self.fn(result)


class ResultsRing(Sink):
    """A bounded ring of result copies for a consumer that polls (a GUI, a controller).

    Parameters
    ----------
    capacity : int
        Results kept, >= 1.
    outputs : sequence of str, optional
        Which arrays to keep (default all).
    policy : {"drop_oldest", "drop_newest", "block"}
        When full: discard the oldest unread result (a live view wants the newest), skip the new one without
        copying it (a viewer that takes a result when it can draw one: the stream pays for no copy it would
        not show), or wait for the consumer (backpressure up to the frame ring).
    optional : bool
        The stream can do without it (a live view): see :class:`Sink`.
    label : str, optional
        Its name in the stream's reports.

    Attributes
    ----------
    dropped : int
        Results discarded unread (``drop_oldest``) or skipped (``drop_newest``).
    """

    def __init__(self, capacity: int = 8, outputs=None, policy: str = "drop_oldest", *, optional: bool = False,
                 label: str | None = None):
        if int(capacity) < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if policy not in ("drop_oldest", "drop_newest", "block"):
            raise ValueError(f"unknown results ring policy {policy!r}; valid policies: drop_oldest, drop_newest, "
                             "block")
        self.capacity, self.policy = int(capacity), policy
        self.optional, self.label = bool(optional), label
        self.outputs = None if outputs is None else tuple(outputs)
        self._items: deque = deque()
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0
        self.written = 0

    def write(self, result):
        if self.policy == "drop_newest":
            with self._cond:
                if len(self._items) >= self.capacity:  # full: skip it before paying for the copy
                    self.dropped += 1
                    return
        keep = {k: v.copy() for k, v in result.arrays.items() if self.outputs is None or k in self.outputs}
        copy = StreamResult(result.index, result.cycle, result.frame_ids.copy(), result.timestamps_s.copy(), keep,
                            result.latency_s, white_gains=None if result.white_gains is None
                            else result.white_gains.copy())
        with self._cond:
            while len(self._items) >= self.capacity:
                if self.policy == "drop_oldest":
                    self._items.popleft()
                    self.dropped += 1
                elif self._closed:  # nobody will read any more: count it, never block the stream's shutdown
                    self.dropped += 1
                    return
                else:
                    self._cond.wait()
            self._items.append(copy)
            self.written += 1
            self._cond.notify_all()

    def get(self, timeout: float | None = None) -> StreamResult | None:
        """The oldest kept result (owned by the caller), or None on timeout or when closed and empty."""
        with self._cond:
            if not wait_for_items(self._cond, lambda: self._items, lambda: self._closed, timeout):
                return None
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def __len__(self):
        with self._cond:
            return len(self._items)

    def close(self):
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class ExrSequenceWriter(Sink):
    """Every ``every``-th result as OpenEXR files through :mod:`specgpu.io.exr`: ``cube-<index>.exr`` (spectral
    layout), ``XYZ-`` / ``Lab-`` / ``dE-<index>.exr`` maps, and every other output as a map of named channels
    (:meth:`channels`). EXR encoding costs milliseconds per map, so a writer that must keep every sequence of a long
    recording is :class:`specgpu.io.recording.ZarrRecorder`. Snapshots are optional to a stream (:class:`Sink`).

    Parameters
    ----------
    directory : path
    wavelengths : array_like, optional
        Band centres of the cube (needed to write ``cube``).
    every : int
        Write one result in ``every``.
    dE_kind : str
        Map kind of the dE channel (``"dE2000"``, ``"dE94"``, ``"dE76"``).
    metadata : mapping, optional
    output_labels : sequence of str, optional
        The plan's output labels, which name the ``sigma`` map's channels (``sigma_<label>``, then ``sigma_rms``).
    """

    optional = True
    label = "EXR snapshots"

    def __init__(self, directory: str | os.PathLike[str], *, wavelengths: ArrayLike | None = None, every: int = 1,
                 dE_kind: str = "dE2000", metadata: dict | None = None,
                 output_labels=None):
        if int(every) < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.wavelengths = None if wavelengths is None else np.asarray(wavelengths, np.float64)
        self.every, self.dE_kind, self.metadata = int(every), dE_kind, dict(metadata or {})
        self.output_labels = None if output_labels is None else [str(v) for v in output_labels]
        self.files: list[Path] = []

    def channels(self, name: str, arr) -> tuple[str, ...]:
        """The channel names of output ``name``'s map ``arr``: a map of one channel (H, W) is that channel, named
        after the output (``dE_sigma``, ``sigma_rms``); ``coefficients`` are ``c0``, ``c1``...; ``sigma`` is
        ``sigma_<label>`` per plan output (``sigma_<i>`` without the labels), then ``sigma_rms``; any other
        ``<name>_<i>``."""
        if arr.ndim == 2:
            return (name,)
        n = arr.shape[-1]
        if name == "coefficients":
            return tuple(f"c{i}" for i in range(n))
        if name == "sigma":
            labels = self.output_labels if self.output_labels and len(self.output_labels) == n - 1 else range(n - 1)
            return (*(f"sigma_{label}" for label in labels), "sigma_rms")
        return tuple(f"{name}_{i}" for i in range(n))

    def write(self, result):
        if result.index % self.every:
            return
        meta = {**self.metadata, "frame_ids": [int(i) for i in result.frame_ids], "cycle": result.cycle}
        tag = f"{result.index:06d}"
        for name, arr in result.arrays.items():
            path = self.directory / f"{name}-{tag}.exr"
            if name == "cube":
                if self.wavelengths is None:
                    raise ValueError("ExrSequenceWriter: writing the cube needs its wavelengths")
                self.files.append(io.write_cube(path, arr, self.wavelengths, half=arr.dtype == np.float16,
                                                metadata=meta))
            elif name in ("XYZ", "Lab"):
                self.files.append(io.write_map(path, arr, name, metadata=meta))
            elif name == "dE":
                self.files.append(io.write_map(path, arr, self.dE_kind, metadata=meta))
            else:
                self.files.append(io.write_map(path, arr, self.channels(name, arr), metadata=meta))


class PreviewSink(Sink):
    """A live preview: the latest XYZ as 8-bit sRGB (``image``), refreshed at most every ``interval_s``, and
    written as a PNG (atomically, through :func:`specgpu.io.previews.write_sRGB_preview`) when ``path`` is given.

    The rendering (a colour transform of every pixel and a PNG encode: 50-150 ms for 640 x 480 on a loaded CPU)
    runs on a thread of its own, so it never holds up the sinks after it (a recording): :meth:`write` only
    copies the XYZ map for it. Latest wins: an XYZ map handed over while the previous one is still rendering
    replaces any map waiting, and :meth:`close` renders the last one handed over before it returns.

    Parameters
    ----------
    path : path, optional
        PNG to refresh.
    interval_s : float
        Shortest time between two renderings, s (a preview at camera rate would cost more than the stream).
    illuminant : str
        The illuminant the XYZ is relative to (the stream's): its white is adapted (CAT02) to sRGB's D65 white, so
        a white under illuminant A previews white, not orange.
    observer : str
        The observer the XYZ is for (the stream's): the illuminant's white is looked up for it.
    background : bool
        Render on the preview's own thread (default); False renders inside :meth:`write`.
    white : array_like, (3,), optional
        The white XYZ the XYZ is relative to (the stream decoder's, of the plan's grid: a perfect white previews
        as 255); None: :func:`specgpu.core.spectra.white_point_XYZ` of ``illuminant`` and ``observer``.

    A preview is optional to a stream (:class:`Sink`): one that fails is stopped, the stream goes on.
    """

    optional = True
    label = "preview"

    def __init__(self, path: str | os.PathLike[str] | None = None, interval_s: float = 0.5, illuminant: str = "D65",
                 background: bool = True, *,
                 observer: str = DEFAULT_CMFS, white=None):

        self.path = None if path is None else Path(path)
        if self.path is not None and self.path.suffix.lower() != ".png":
            raise ValueError(f"{self.path}: the preview is a PNG; give a .png path")
        self.interval_s = float(interval_s)
        self.illuminant = str(illuminant)
        self.observer = str(observer)
        self.background = bool(background)
        white = white_point_XYZ(self.illuminant if white is None else white, self.observer)
        white_xy = np.asarray(colour.XYZ_to_xy(white), np.float64)
        # XYZ under the illuminant -> linear sRGB, the CAT02 adaptation to D65 folded in (rows: the image of X, Y, Z)
        self._M = np.asarray(colour.XYZ_to_RGB(np.eye(3), colour.models.RGB_COLOURSPACE_sRGB, illuminant=white_xy,
                                               chromatic_adaptation_transform="CAT02", apply_cctf_encoding=False),
                             np.float32).T
        self.image: np.ndarray | None = None
        self.updates = 0
        self._last = -np.inf
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._pending: np.ndarray | None = None
        self._closing = False
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def write(self, result):
        if self._error is not None:
            raise self._error
        now = time.perf_counter()
        if now - self._last < self.interval_s:
            return
        XYZ = result.arrays.get("XYZ")
        if XYZ is None:
            raise ValueError("PreviewSink needs the XYZ output of the stream")
        self._last = now
        if not self.background:
            self._render(XYZ)
            return
        XYZ = np.array(XYZ, copy=True)  # the result's buffers go back to the stream once the sinks return
        with self._lock:
            self._pending = XYZ
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="specgpu-stream-preview", daemon=True)
            self._thread.start()
        self._wake.set()

    _tables: np.ndarray | None = None

    @classmethod
    def _srgb_table(cls):
        """The 8-bit sRGB code of each of 65536 linear levels: with the instance's XYZ -> linear sRGB matrix,
        colour-science's XYZ_to_sRGB as one matrix product and a table look-up (within one code value of it, ~10x
        faster)."""
        if cls._tables is None:

            codes = colour.models.eotf_inverse_sRGB(np.linspace(0.0, 1.0, 65536))
            cls._tables = (np.clip(codes, 0, 1) * 255 + 0.5).astype(np.uint8)
        return cls._tables

    def _render(self, XYZ):
        lut = self._srgb_table()
        with np.errstate(invalid="ignore"):
            linear = np.nan_to_num(np.clip(np.asarray(XYZ, np.float32), 0, None)) @ self._M.T
        self.image = lut[(np.clip(linear, 0, 1) * 65535 + 0.5).astype(np.uint16)]
        if self.path is not None:  # the image rendered once: the PNG is this image (written atomically)
            write_png(self.path, self.image, {"specgpu:exposure_EV": repr(0.0), "illuminant": self.illuminant,
                                                  "observer": self.observer,
                                                  "ImageDescription": "sRGB preview of XYZ, exposure +0.000 EV"})
        self.updates += 1

    def _run(self):
        while True:
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                XYZ, self._pending = self._pending, None
                closing = self._closing
            if XYZ is not None and self._error is None:
                try:
                    self._render(XYZ)
                except BaseException as exc:  # noqa: BLE001 (raised by the next write or by close)
                    self._error = exc
            if closing:
                with self._lock:
                    if self._pending is None:
                        return
                self._wake.set()

    def close(self):
        """Render the last XYZ map handed over, stop the preview's thread; a rendering's error is raised here."""
        if self._thread is not None:
            with self._lock:
                self._closing = True
            self._wake.set()
            self._thread.join()
            self._thread = None
        if self._error is not None:
            raise self._error


