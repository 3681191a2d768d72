"""The streaming pipeline: driver -> ring buffer -> assembler -> device buffers -> kernels -> sinks, at camera speed.

Three threads, one job each, joined by bounded buffers so every overload shows up as a counted drop somewhere
explicit, never as unbounded memory::

    producer thread        driver.fill(slot) into the frame ring      (capture.ringbuffer.run_producer)
    device thread          ring -> SequenceAssembler -> upload -> kernels -> readback events (``in_flight`` deep)
    sink thread            completed results -> sinks (callback, results ring, file writer, preview)

Each sequence in flight holds one of ``result_buffers`` tokens from upload until every sink has returned. A slow
sink keeps its tokens, the device thread waits for one, the frame ring fills and its policy acts
(``drop_newest`` by default: the camera never waits, a lost frame is a frame-id gap the assembler counts, and no
sequence is ever built across it). The counters of the ring, the assembler and the stream say where each frame
went (:meth:`StreamReport.accounting`).

Device work per sequence is enqueued without blocking on one in-order queue: the upload of the K frames, the
linear kernel (basis coefficients or the full cube), the fused XYZ -> Lab -> dE kernel against a reference, and the
readbacks; the thread goes back to assembling while the device works, and waits on a sequence's events only when
``in_flight`` sequences are pending. Readback is by mapping the output buffers (``readback="map"``, zero copy on
CPU devices: the map is the buffer) or by copying into host arrays (``"copy"``, what a discrete GPU wants).

Shutdown (:meth:`Stream.stop`, ``KeyboardInterrupt`` in :meth:`Stream.run`, the time limit or the end of the
driver's stream) stops the producer; every frame already in the ring is still assembled, every complete sequence
still computed and handed to the sinks, and the frames left in an unfinished sequence are reported in the
assembler's ``frames_unused`` / ``sequences_discarded``.
"""

from __future__ import annotations

import queue as queue_module
import resource
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu import engine
from specgpu.capture.assemble import AssemblyStats, SequenceAssembler
from specgpu.capture.driver import CameraDriver, FrameInfo, StreamEnd
from specgpu.capture.ringbuffer import POLICIES, RingBuffer, RingStats, run_producer, wait_for_items
from specgpu.engine.colorimetry import DELTA_E_METHODS
from specgpu.engine.runtime import get_allocator, get_queue
from specgpu.core.spectra import DEFAULT_CMFS, white_point_XYZ
from specgpu.engine.transfer import pinned_empty
from specgpu.io.previews import write_png
from specgpu.core.validate import validate_method

__all__ = [
    "STREAM_OUTPUTS",
    "CallbackSink",
    "ExrSequenceWriter",
    "LatencyHistogram",
    "PreviewSink",
    "ResultsRing",
    "Sink",
    "Stream",
    "StreamDecoder",
    "StreamReport",
    "StreamResult",
    "current_rss_bytes",
    "peak_rss_bytes",
    "peak_rss_reset",
]

#: What a stream can compute per sequence, and the channel count / dtype of each map.
STREAM_OUTPUTS = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma", "sigma_rms", "dE_sigma")
READBACKS = ("auto", "map", "copy", "pinned")
UPLOADS = ("auto", "host_ptr", "pinned", "copy")


# ------------------------------------------------------------------------------------------------- the decoder

#: Host-corrected frames (StreamDecoder.prepare_frames) mark a saturated sample with _PRECORRECT_MARK, far above
#: any corrected signal, and the kernels flag samples at or above _PRECORRECT_SATURATION.
_PRECORRECT_MARK = np.float32(3.0e38)
_PRECORRECT_SATURATION = 1.0e38


class StreamDecoder:
    """The host-side planning of a stream: matrices, dark and gain maps and the reference, on the device once.

    Parameters
    ----------
    plan : specgpu.planning.plans.Plan
        Decoder A (B x K) and what it outputs (reflectance or XYZ).
    calibration : specgpu.calibration.bundle.CalibrationBundle
        Dark frame at the plan's exposure and flat field (the same ones ``specgpu recover`` applies).
    outputs : sequence of str
        Any of :data:`STREAM_OUTPUTS`. ``"coefficients"``: the m basis coefficients of each pixel in the plan's
        output basis U (B x m, orthonormal columns from the SVD of A; ``cube = coefficients @ U.T``).
        ``"cube"``: the B outputs of the plan. ``"XYZ"``, ``"Lab"``, ``"dE"``: the fused colorimetric pass.
        ``"sigma"``: the standard deviation of each of the B outputs and their RMS (B + 1 channels, as
        ``specgpu recover --sigma``): the variance is linear in the frames' sample variances plus a constant
        (:func:`specgpu.planning.uncertainty.sigma_map`), so the linear kernel computes it with ``A o A / g`` as the
        matrix, each sample squared first for the light's fluctuation, and takes the square root of it plus the
        constant. ``"sigma_rms"``: the RMS channel alone (one
        row of the same map: B times fewer bytes written than ``"sigma"``). ``"dE_sigma"``: the first-order dE2000
        standard deviation (as ``recover --delta-e-sigma``): the XYZ covariance's six entries by the linear
        kernel, then a small kernel propagating them with XYZ to dE2000 (as
        :func:`specgpu.planning.uncertainty.delta_E_sigma`). Both need the plan's noise model, which ``specgpu plan`` records
        (given ``--rig`` for a calibration made on a custom rig).
    reference : array_like, optional
        CIELAB reference of ``"dE"``: one colour (3,) or a per-pixel (H, W, 3) image. Required for ``"dE"``.
    method : str
        Colour difference, a name of ``DELTA_E_METHODS`` (default ``"CIE 2000"``).
    illuminant : str, optional
        Illuminant of XYZ (Y = 1 for the perfect white), Lab and dE; default the plan's own for a tristimulus or
        camera plan, D65 otherwise (:meth:`specgpu.planning.plans.Plan.resolve_illuminant`, which refuses another than a
        tristimulus plan measures under).
    observer : str, optional
        Observer of XYZ, Lab and dE (its white); default the plan's own for a tristimulus plan, the CIE 1931 2
        degree observer otherwise (:meth:`specgpu.planning.plans.Plan.resolve_observer`, which refuses another than a
        tristimulus plan's).
    cube_dtype : float16 or float32
        Storage of the cube (float16 halves the memory traffic of the widest output).
    frame_shape : (int, int)
        (H, W) of the frames.
    queue : pyopencl.CommandQueue
    white_roi : str or (x, y, w, h), optional
        A reference white in the field (``specgpu recover --white-roi``): each sequence's decoder is rescaled for
        the light's drift since calibration (:class:`specgpu.planning.correction.WhiteReference`), and every launch of
        the sequence gets its matrix from the corrected decoder (:meth:`matrices`).
    white_reflectance : float or path, optional
        The white's reflectance (0.99 by default); only with ``white_roi``.
    """

    def __init__(self, plan, calibration, outputs, *, frame_shape, queue, reference=None, method="CIE 2000",
                 illuminant=None, observer: str | None = None, cube_dtype=np.float16, white_roi=None,
                 white_reflectance=None):
        # canonical names (the check is case-insensitive), each once
        outputs = tuple(dict.fromkeys(validate_method(name, {k: k for k in STREAM_OUTPUTS}, "stream output")
                                      for name in outputs))
        if not outputs:
            raise ValueError(f"a stream needs at least one output of {', '.join(STREAM_OUTPUTS)}")
        self.outputs = outputs
        self.plan = plan
        self.queue = queue
        self.height, self.width = (int(s) for s in frame_shape)
        self.n = self.height * self.width
        self.K = plan.K
        A = np.asarray(plan.A, np.float64)
        self.cube_dtype = np.dtype(cube_dtype)
        if self.cube_dtype not in (np.dtype(np.float16), np.dtype(np.float32)):
            raise ValueError(f"cube_dtype must be float16 or float32, got {self.cube_dtype}")
        self.method = validate_method(method, DELTA_E_METHODS) if "dE" in outputs else method
        self.illuminant = illuminant = plan.resolve_illuminant(illuminant)
        self.observer = observer = plan.resolve_observer(observer)
        dark = calibration.dark_at(plan.exposure_s)
        gain = calibration.flat_field
        if tuple(np.shape(dark)) != (self.height, self.width):
            raise ValueError(f"calibration maps are {np.shape(dark)} but the frames are {self.height} x {self.width}")
        # a sample at the sensor's maximum code has no valid measurement: its pixel's outputs become NaN, as
        # pipeline.recover makes them (flagged by the first kernel of a sequence, applied on the host)
        self.saturation = float(calibration.max_code)
        self._prepared: dict = {}
        # corrections recover applies to the frames before the linear map: the sensor's linearisation, the
        # wavelength-dependent flat field (per pattern) and a plan's ambient frame (subtracted instead of the
        # dark level). None of them is linear in one per-pixel map, so they run on the host (prepare_frames),
        # the dark level subtracted there too, and the kernels take float32 frames with no dark
        from specgpu.planning.correction import ambient_index

        self._calibration = calibration
        self._ratio = calibration.flat_ratio(plan.patterns)
        self._ambient = ambient_index(plan)
        self._linearize = calibration.reports.get("linearity_c_per_dn2", 0.0) > 0
        self._dark_host = np.asarray(dark, np.float32)
        self.precorrect = self._ratio is not None or self._ambient is not None or self._linearize
        if self.precorrect:
            dark = np.zeros_like(self._dark_host)
            self.saturation = _PRECORRECT_SATURATION  # saturated samples are marked by prepare_frames
        self.dark = engine.to_device(queue, np.asarray(dark, np.float32).reshape(-1))
        self.gain = engine.to_device(queue, np.asarray(gain, np.float32).reshape(-1))
        self.A = A
        self.basis = None
        self.A_coefficients = None
        if "coefficients" in outputs:
            # Coefficients in the plan's own output basis: A = U S Vt has rank m (a basis plan), so the m rows of
            # S Vt decode the coefficients and U rebuilds the cube exactly.
            U, s, Vt = np.linalg.svd(A, full_matrices=False)
            m = int(plan.params.get("m", np.sum(s > s[0] * 1e-9)))
            self.basis = U[:, :m]
            self.A_coefficients = s[:m, None] * Vt[:m]
        colour = {"XYZ", "Lab", "dE", "dE_sigma"} & set(outputs)
        self.M = None
        self.to_XYZ = None
        self.white = None
        self.reference = None
        self.reference_single = True
        if colour:
            self.to_XYZ = plan.outputs_to_XYZ(illuminant, observer)
            self.M = self.to_XYZ @ A
            self.white = white_point_XYZ(illuminant, observer)
        # the white reference: parsed and checked now (an ROI outside the frame is refused before any streaming)
        if white_reflectance is not None and white_roi is None:
            raise ValueError("--white-reflectance needs --white-roi")
        self.white_reference = None
        if white_roi is not None:
            from specgpu.planning.correction import WhiteReference

            self.white_reference = WhiteReference(plan, calibration, white_roi, white_reflectance,
                                                  frame_shape=(self.height, self.width))
        # the uncertainty outputs: the noise model's dark and gain maps (estimators._noise_products)
        self.noise = None
        if {"sigma", "sigma_rms", "dE_sigma"} & set(outputs):
            from specgpu.planning import NoiseModel, constant_covariance

            if "noise" not in plan.params:
                raise ValueError(f"the {plan.method} plan records no noise model, so it has no sigma; re-plan it "
                                 "with specgpu plan --rig RIG.toml (the rig the calibration was made on) to record one")
            self.noise = NoiseModel.from_params(plan.params["noise"])
            g_e = self.noise.gain_e_per_dn
            self.dark_var = engine.to_device(queue, (np.asarray(dark, np.float32) - np.float32(
                g_e * self.noise.read_var_dn2)).reshape(-1))
            self.gain2 = engine.to_device(queue, (np.asarray(gain, np.float32) ** 2).reshape(-1))
            # the light's fluctuation at each frame's own signal (squared samples); a white reference's per-sequence
            # gains divide it out, as recover --white-roi's uncertainty does. With an ambient frame the frames
            # arrive above it (prepare_frames) and its plane holds its own variance sample (never squared).
            self.square = (self.noise.light_square() if self.white_reference is None and self.noise.light_rms > 0
                           else None)
            if self._ambient is not None:
                self.dark_var = None
                self.square = None if self.square is None else (self.square[0], 0.0, self._ambient)
            const = constant_covariance(plan)
            cv = np.diag(const).astype(np.float32)
            self.sigma_offsets = np.append(cv, np.float32(np.mean(cv, dtype=np.float64)))
            self.cov_pairs = [(i, j) for i in range(3) for j in range(i, 3)]
            if "dE_sigma" in outputs:
                self.cov_constant = self.to_XYZ @ const @ self.to_XYZ.T  # (3, 3) what no frame shows
        if "dE" in outputs:
            if reference is None:
                raise ValueError("the dE output needs a reference (an L,a,b colour or a per-pixel Lab image)")
            ref = np.asarray(reference, np.float32)
            if ref.shape == (3,):
                self.reference_single = True
            elif ref.shape == (self.height, self.width, 3):
                self.reference_single = False
            else:
                raise ValueError(f"the dE reference must be (3,) or ({self.height}, {self.width}, 3), got {ref.shape}")
            self.reference = engine.to_device(queue, ref.reshape(-1))
        elif reference is not None:
            raise ValueError("a reference was given but dE is not among the outputs")

    def shapes(self) -> dict[str, tuple[tuple, np.dtype]]:
        """Per output: its (H, W, C) or (H, W) shape and dtype; plus ``mask`` (H, W) uint8, bit 1 = saturated."""
        h, w = self.height, self.width
        out = {}
        for name in self.outputs:
            if name == "coefficients":
                out[name] = ((h, w, self.A_coefficients.shape[0]), np.dtype(np.float32))
            elif name == "cube":
                out[name] = ((h, w, self.A.shape[0]), self.cube_dtype)
            elif name in ("XYZ", "Lab"):
                out[name] = ((h, w, 3), np.dtype(np.float32))
            elif name == "sigma":
                out[name] = ((h, w, self.A.shape[0] + 1), np.dtype(np.float32))
            else:
                out[name] = ((h, w), np.dtype(np.float32))
        out["mask"] = ((h, w), np.dtype(np.uint8))
        return out

    def device_shapes(self) -> dict[str, tuple[tuple, np.dtype]]:
        """The maps read back from the device (:meth:`shapes`); :meth:`enqueue` may return more buffers (those
        ``dE_sigma`` is computed from), which stay on the device."""
        return self.shapes()

    def matrices(self, A) -> list[np.ndarray]:
        """The float32 matrix argument of each launch (in :meth:`_launches`' order) for the decoder ``A`` (B x K):
        what a per-sequence decoder (the white reference's) writes into the launches' matrix buffers."""
        return [engine.linear_matrix(*make(np.asarray(A, np.float64))) for make, _ in self._matrix_makers()]

    def _matrix_makers(self) -> list:
        """Per launch, in order: (a function of A giving (matrix, square-root offsets or None), launch kind)."""
        from specgpu.planning import variance_rows

        makers = []
        if "coefficients" in self.outputs:
            # U^T A: S Vt for the plan's own A; for a corrected decoder (A times a K x K map) its coefficients in
            # the same basis, whose columns span the corrected decoder's outputs too
            makers.append((lambda A: (self.basis.T @ A, None), "coefficients"))
        if "cube" in self.outputs:
            makers.append((lambda A: (A, None), "cube"))
        if "sigma" in self.outputs:
            g_e = self.noise.gain_e_per_dn

            def sigma_rows(A):
                sq = variance_rows(A, A, self._ambient)
                return np.vstack([sq, sq.mean(axis=0)]) / g_e, self.sigma_offsets
            makers.append((sigma_rows, "sigma"))
        if "sigma_rms" in self.outputs:
            g_e = self.noise.gain_e_per_dn
            makers.append((lambda A: (variance_rows(A, A, self._ambient).mean(axis=0, keepdims=True) / g_e,
                                      self.sigma_offsets[-1:]), "sigma_rms"))
        if "dE_sigma" in self.outputs:
            g_e = self.noise.gain_e_per_dn

            def cov_rows(A):
                MA = self.to_XYZ @ A
                left = np.stack([MA[i] for i, _ in self.cov_pairs])
                right = np.stack([MA[j] for _, j in self.cov_pairs])
                return variance_rows(left, right, self._ambient) / g_e, None
            makers.append((cov_rows, "XYZ_cov"))
        if self.M is not None:
            makers.append((lambda A: (self.to_XYZ @ A, None), "colour"))
        return makers

    @property
    def frames_dtype(self):
        """What the kernels read: the raw frames, or float32 when :meth:`prepare_frames` corrects them first."""
        return np.dtype(np.float32) if self.precorrect else None

    def prepare_frames(self, raw) -> np.ndarray:
        """(K, H, W) float32 frames for the kernels when the calibration or plan needs host-side corrections
        (``precorrect``): the dark level (or the plan's ambient frame) subtracted, linearised and scaled by the
        per-pattern flat ratio exactly as :func:`specgpu.pipeline.recovery.recover` does; a sample at the sensor's maximum
        code is set to a marker the kernels flag as saturated."""
        from specgpu.pipeline.recovery import corrected_signal

        raw = np.asarray(raw)
        dark = raw[self._ambient].astype(np.float32) if self._ambient is not None else self._dark_host
        f = corrected_signal(raw, dark, self._ratio, self._calibration)
        if self._ambient is not None and self.noise is not None:
            # the ambient frame's plane (a zero column of the decoder) carries its own variance sample for the
            # uncertainty launches (estimators.frame_variance)
            from specgpu.planning import ambient_variance

            f[self._ambient] = ambient_variance(dark, self._dark_host, self.noise)
        f[raw >= self._calibration.max_code] = _PRECORRECT_MARK
        return f

    def warm_up(self, dtype=np.uint16) -> None:
        """Build every kernel and prime the memory pool on a blank sequence, so the clock of a stream never pays
        for a program build."""
        blank = cla.zeros(self.queue, (self.K * self.n,), np.dtype(dtype), allocator=get_allocator(self.queue))
        outs = self.enqueue(blank)
        self.queue.finish()
        del outs

    def _launches(self, dtype) -> list:
        """The stream's kernels for frames of ``dtype`` as prepared launches (built on first use, then reused:
        a sequence costs a few argument sets and enqueues, not the per-call planning of the engine's functions),
        each with the map from its outputs to the stream's output names."""
        launches = self._prepared.get(dtype)
        if launches is not None:
            return launches
        q, n = self.queue, self.n
        launches = []
        sat = {"want_mask": True, "saturation": self.saturation}  # asked of the first kernel only
        for make, kind in self._matrix_makers():
            if kind == "coefficients":
                launches.append((engine.prepare_linear(q, dtype, self.A_coefficients, n=n, dark=self.dark,
                                                       gain=self.gain, out_layout=1, **sat),
                                 {"out": "coefficients", "mask": "mask"}))
            elif kind == "cube":
                launches.append((engine.prepare_linear(q, dtype, self.A, n=n, dark=self.dark, gain=self.gain,
                                                       out_dtype=self.cube_dtype, out_layout=1, **sat),
                                 {"out": "cube", "mask": "mask"}))
            elif kind in ("sigma", "sigma_rms", "XYZ_cov"):
                rows, offsets = make(self.A)
                launches.append((engine.prepare_linear(q, dtype, rows, n=n, dark=self.dark_var, gain=self.gain2,
                                                       out_layout=1, sqrt_offsets=offsets, square=self.square,
                                                       **sat),
                                 {"out": kind, "mask": "mask"}))
            else:
                launches.append((engine.prepare_frames_to_delta_E(
                    q, dtype, self.M, self.white, self.reference, n=n, method=self.method if "dE" in self.outputs
                    else "CIE 2000", reference_single=self.reference_single, dark=self.dark, gain=self.gain,
                    write_XYZ="XYZ" in self.outputs or "dE_sigma" in self.outputs, write_Lab="Lab" in self.outputs,
                    **sat), {"XYZ": "XYZ", "Lab": "Lab", "delta_E": "dE", "mask": "mask"}))
            sat = {}
        if "dE_sigma" in self.outputs:  # on the XYZ and XYZ_cov buffers of the launches above
            launches.append((engine.prepare_delta_E_sigma(q, self.white, self.cov_constant, n=n),
                             {"dE_sigma": "dE_sigma"}))
        self._prepared[dtype] = launches
        return launches

    def enqueue(self, frames: cla.Array, matrices=None) -> dict:
        """Enqueue every kernel on the K frames (flat device array); returns the flat device output buffers (pooled
        :class:`pyopencl.Buffer` objects) by output name and ``mask`` (bit 1: a frame at the saturation level).

        ``matrices``: a device buffer per launch holding :meth:`matrices` of this sequence's decoder (written
        before, on the same in-order queue), used instead of the plan's."""
        out = {}
        for i, (launch, names) in enumerate(self._launches(np.dtype(frames.dtype))):
            if "dE_sigma" in names:  # the last launch: XYZ and its covariance in, no matrix
                made = launch.enqueue(out["XYZ"], inputs={1: out["XYZ_cov"]})
            else:
                made = launch.enqueue(frames.data, None if matrices is None else matrices[i])
            for key, buf in made.items():
                out[names[key]] = buf
        return out


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


class Sink:
    """A consumer of results: :meth:`write` is called on the sink thread for each result in order, :meth:`close`
    once at the end. A sink that is slower than the stream makes the frame ring's policy act (backpressure)."""

    def write(self, result: StreamResult) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        """Flush and release what the sink holds."""


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
    policy : {"drop_oldest", "block"}
        When full: discard the oldest unread result (a live view wants the newest), or wait for the consumer
        (backpressure up to the frame ring).

    Attributes
    ----------
    dropped : int
        Results discarded unread (``drop_oldest``).
    """

    def __init__(self, capacity: int = 8, outputs=None, policy: str = "drop_oldest"):
        if int(capacity) < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if policy not in ("drop_oldest", "block"):
            raise ValueError(f"unknown results ring policy {policy!r}; valid policies: drop_oldest, block")
        self.capacity, self.policy = int(capacity), policy
        self.outputs = None if outputs is None else tuple(outputs)
        self._items: deque = deque()
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0
        self.written = 0

    def write(self, result):
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
    """Every ``every``-th result as OpenEXR files through :mod:`specgpu.io.cube`: ``cube-<index>.exr`` (spectral
    layout), ``XYZ-`` / ``Lab-`` / ``dE-<index>.exr`` maps. EXR encoding costs milliseconds per map, so a writer
    that must keep every sequence of a long recording is :class:`specgpu.io.recording.ZarrRecorder`.

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
    """

    def __init__(self, directory, *, wavelengths=None, every: int = 1, dE_kind: str = "dE2000", metadata=None):
        if int(every) < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.wavelengths = None if wavelengths is None else np.asarray(wavelengths, np.float64)
        self.every, self.dE_kind, self.metadata = int(every), dE_kind, dict(metadata or {})
        self.files: list[Path] = []

    def write(self, result):
        from specgpu import io

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
                self.files.append(io.write_map(path, arr, tuple(f"c{i}" for i in range(arr.shape[-1])),
                                               metadata=meta))


class PreviewSink(Sink):
    """A live preview: the latest XYZ as 8-bit sRGB (:attr:`image`), refreshed at most every ``interval_s``, and
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
    """

    def __init__(self, path=None, interval_s: float = 0.5, illuminant: str = "D65", background: bool = True, *,
                 observer: str = DEFAULT_CMFS):
        import colour

        self.path = None if path is None else Path(path)
        if self.path is not None and self.path.suffix.lower() != ".png":
            raise ValueError(f"{self.path}: the preview is a PNG; give a .png path")
        self.interval_s = float(interval_s)
        self.illuminant = str(illuminant)
        self.observer = str(observer)
        self.background = bool(background)
        white_xy = np.asarray(colour.XYZ_to_xy(white_point_XYZ(self.illuminant, self.observer)), np.float64)
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
            import colour

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


# ------------------------------------------------------------------------------------------------------ report


@dataclass
class StreamReport:
    """Counters and timings of a finished stream.

    Attributes
    ----------
    frames_in : int
        Frames the driver delivered (into the ring or refused by it).
    sequences_out : int
        Results handed to the sinks.
    ring, assembly : RingStats, AssemblyStats
        The frame ring's and the assembler's exact counters.
    end : StreamEnd
        The driver's last exposure.
    seconds : float
        Wall time from the first frame requested to the last result written.
    latency : LatencyHistogram
        Per result, arrival of the last frame -> result ready (see :class:`StreamResult`): exact count, mean,
        min and max, quantiles to 0.6 % (a bounded histogram: a day's stream holds no list of latencies).
    cpu_s : float
        Process CPU time (user + system) over the run, s.
    peak_rss_bytes : int or None
        Peak resident memory during the run (``VmHWM`` after a reset, else the process's lifetime peak).
    interrupted : bool
        The run ended by :meth:`Stream.stop` or Ctrl-C rather than by time or the end of the driver's stream.
    sink_errors : list of str
        Exceptions raised by sinks (the stream stops at the first one).
    rss_start_bytes : int or None
        Resident memory when the stream started (what the process held before: the peak minus this is the
        stream's own).
    """

    frames_in: int
    sequences_out: int
    ring: RingStats
    assembly: AssemblyStats
    end: StreamEnd
    seconds: float
    latency: "LatencyHistogram"
    cpu_s: float
    peak_rss_bytes: int | None
    interrupted: bool
    sink_errors: list = field(default_factory=list)
    rss_start_bytes: int | None = None

    @property
    def frames_per_s(self) -> float:
        return self.frames_in / self.seconds if self.seconds > 0 else 0.0

    @property
    def sequences_per_s(self) -> float:
        return self.sequences_out / self.seconds if self.seconds > 0 else 0.0

    def latency_ms(self, q: float) -> float:
        return self.latency.quantile(q / 100.0) * 1e3

    def accounting(self) -> dict:
        """Where every frame went; ``balanced`` is True when the identities hold exactly:

        - frames in = into the ring + refused by a full ring;
        - into the ring = handed to the assembler + discarded unread by the ring (drop_oldest);
        - handed to the assembler = K x sequences + duplicates + out of order + unused (incomplete sequences);
        - sequences out = sequences complete.
        """
        r, a = self.ring, self.assembly
        k = None
        if a.sequences_complete:
            k = (a.frames_received - a.duplicates - a.out_of_order - a.frames_unused) / a.sequences_complete
        checks = [
            self.frames_in == r.finalized + r.dropped_newest,
            r.finalized == r.delivered + r.dropped_oldest + r.pending,
            r.pending == 0,
            a.frames_received == r.delivered,
            self.sequences_out == a.sequences_complete,
        ]
        return {"frames_in": self.frames_in, "ring_dropped": r.dropped, "assembler_dropped": a.dropped,
                "frames_in_sequences": a.frames_received - a.duplicates - a.out_of_order - a.frames_unused,
                "frames_per_sequence": k, "frames_unused": a.frames_unused, "duplicates": a.duplicates,
                "missed_triggers": a.missed_triggers, "sequences_discarded": a.sequences_discarded,
                "sequences_out": self.sequences_out, "balanced": all(checks)}

    def as_dict(self) -> dict:
        return {"frames_in": self.frames_in, "sequences_out": self.sequences_out, "seconds": self.seconds,
                "frames_per_s": self.frames_per_s, "sequences_per_s": self.sequences_per_s,
                "latency_ms_median": self.latency_ms(50), "latency_ms_p99": self.latency_ms(99),
                "latency_ms_max": self.latency.max * 1e3 if self.latency.count else float("nan"),
                "latencies_counted": self.latency.count,
                "cpu_s": self.cpu_s, "cpu_cores": self.cpu_s / self.seconds if self.seconds else 0.0,
                "peak_rss_bytes": self.peak_rss_bytes, "rss_start_bytes": self.rss_start_bytes,
                "interrupted": self.interrupted,
                "ring": {**{k: getattr(self.ring, k) for k in self.ring.__dataclass_fields__},
                         "dropped": self.ring.dropped},
                "assembly": self.assembly.as_dict(), "accounting": self.accounting(),
                "sink_errors": list(self.sink_errors)}


class LatencyHistogram:
    """Latencies of a stream of any length in fixed memory: exact count, sum, min and max, a histogram on
    logarithmic bins (``bins_per_decade`` from ``low_s`` to ``high_s``; values beyond go to the end bins) for
    quantiles, and the latest ``recent`` values for a live status. A quantile is the geometric centre of its
    bin, clamped to [min, max]: within ``10 ** (0.5 / bins_per_decade) - 1`` (0.6 % at 200) of the exact one.
    """

    def __init__(self, low_s: float = 1e-6, high_s: float = 1e3, bins_per_decade: int = 200, recent: int = 64):
        self.low, self.per_decade = float(low_s), int(bins_per_decade)
        self.bins = int(np.ceil(np.log10(high_s / low_s) * self.per_decade))
        self.counts = np.zeros(self.bins, np.int64)
        self.count = 0
        self.total = 0.0
        self.min = float("inf")
        self.max = float("-inf")
        self.recent: deque = deque(maxlen=int(recent))

    def add(self, value_s: float) -> None:
        v = float(value_s)
        i = int(np.floor(np.log10(max(v, self.low) / self.low) * self.per_decade))
        self.counts[min(max(i, 0), self.bins - 1)] += 1
        self.count += 1
        self.total += v
        self.min = min(self.min, v)
        self.max = max(self.max, v)
        self.recent.append(v)

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else float("nan")

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0 <= q <= 1) in seconds (NaN when empty)."""
        if not self.count:
            return float("nan")
        if q <= 0:
            return self.min
        if q >= 1:
            return self.max
        i = int(np.searchsorted(np.cumsum(self.counts), q * self.count, side="left"))
        centre = self.low * 10 ** ((i + 0.5) / self.per_decade)
        return float(min(max(centre, self.min), self.max))

    @property
    def nbytes(self) -> int:
        """Memory the structure holds, bytes (fixed: independent of the count)."""
        return int(self.counts.nbytes + 8 * self.recent.maxlen)


def peak_rss_reset() -> bool:
    """Reset the kernel's peak-RSS mark of this process (Linux ``clear_refs`` 5); False where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _status_kib(field_name: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field_name + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def current_rss_bytes() -> int | None:
    """Resident set size of this process now, bytes (None where /proc is absent)."""
    return _status_kib("VmRSS")


def peak_rss_bytes() -> int | None:
    """Peak resident set size of this process since start or the last :func:`peak_rss_reset`, bytes."""
    peak = _status_kib("VmHWM")
    return peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


# ------------------------------------------------------------------------------------------------------ stream


class _ArrivalDriver(CameraDriver):
    """Wraps the stream's driver: stamps each delivered frame's arrival (perf_counter) by frame id, for latency,
    and ends the stream at a sequence boundary once ``stop`` is set.

    After a stop request the camera keeps being read until the light has shown the sequence's last pattern, so
    the sequence being exposed is completed rather than cut (at most K more frames: with missed triggers the last
    pattern may never come, and the partial sequence is then reported by the assembler).
    """

    def __init__(self, inner: CameraDriver, n_patterns: int, stop: threading.Event):
        self.inner = inner
        self.k = n_patterns
        self.stop_event = stop
        self.arrivals: dict[int, float] = {}
        self.delivered = 0
        self._last_pattern = n_patterns - 1
        self._after_stop = 0

    frame_shape = property(lambda self: self.inner.frame_shape)
    dtype = property(lambda self: self.inner.dtype)
    light = property(lambda self: self.inner.light)
    running = property(lambda self: self.inner.running)

    def start(self):
        self.delivered = 0
        self._last_pattern = self.k - 1
        self._after_stop = 0
        self.arrivals.clear()
        self.inner.start()

    def stop(self) -> StreamEnd:
        return self.inner.stop()

    def fill(self, out) -> FrameInfo | None:
        if self.stop_event.is_set():
            if self._last_pattern == self.k - 1 or self._after_stop >= self.k:
                return None
            self._after_stop += 1
        info = self.inner.fill(out)
        if info is not None:
            self.delivered += 1
            self._last_pattern = int(info.pattern_index)
            if out is not None:
                self.arrivals[info.frame_id] = time.perf_counter()
        return info


@dataclass
class _InFlight:
    index: int
    seq: object
    t_arrival: float
    device_out: dict
    host: dict
    events: list
    keep: list
    pinned: object = None
    host_set: object = None
    matrix_set: object = None
    white_gains: object = None


class Stream:
    """A driver streamed through ring buffer, assembler, device and sinks (see the module docstring).

    Parameters
    ----------
    driver : CameraDriver
        Not yet started; :meth:`run` starts and stops it.
    plan, calibration
        The plan (K patterns, decoder A) and the calibration it was made from (checked).
    outputs : sequence of str
        Of :data:`STREAM_OUTPUTS`; default basis coefficients, XYZ and dE.
    sinks : sequence of Sink or callables
        Called in order for each result: any object with ``write(result)`` (and optionally ``close()``), or a
        callable (wrapped in :class:`CallbackSink`).
    reference, method, illuminant, observer, cube_dtype
        As :class:`StreamDecoder`.
    n_slots : int, optional
        Frames the ring holds (default 4 K, at least 16: room for jitter without adding latency at saturation).
    policy : str
        Frame ring policy when full: ``"drop_newest"`` (default: the camera never waits), ``"drop_oldest"`` or
        ``"block"`` (the driver waits: for replayed or simulated frames, measures the pipeline's own rate).
    in_flight : int
        Sequences enqueued on the device before the device thread waits for the oldest.
    result_buffers : int
        Sequences between upload and the end of the sinks (>= in_flight); the bound on result memory.
    readback : {"auto", "map", "copy", "pinned"}
        Results read by mapping the device outputs (zero copy on CPU devices), copied into fresh host arrays, or
        copied by DMA into pinned host arrays (``ALLOC_HOST_PTR``, mapped once, one set per result buffer and
        reused: no page faults, no per-sequence map); ``"auto"``: map on CPU devices, pinned elsewhere.
    upload : {"auto", "host_ptr", "pinned", "copy"}
        Frames wrapped as a ``USE_HOST_PTR`` buffer (zero copy on CPU devices: the assembled sequence is the device
        buffer), copied into pinned staging (``ALLOC_HOST_PTR`` buffers mapped once, one per result buffer) and
        from there by a non-blocking DMA into a pooled device buffer (what a discrete GPU wants: no map, no wait on
        the queue), or copied by ``enqueue_copy`` straight from the sequence into a pooled device buffer;
        ``"auto"``: host_ptr on CPU devices, pinned elsewhere.
        Measured on PoCL (2 cores), 640 x 480, coefficients + XYZ + dE2000, best of 3 interleaved rounds
        (``python tools/stream_transfers.py --seconds 4 --rounds 3``): host_ptr + map 1028 frames/s, copy + map
        965, host_ptr + copy 936, pinned + map 913, copy + copy 854, pinned + copy 833; mapping the outputs is
        worth ~10 %, and ALLOC_HOST_PTR staging buys nothing on a CPU device (it adds a host copy). The device
        alone needs 7.4 ms per sequence (1219 frames/s), 6.3 ms of it the dE2000 pass.
    align : str
        Assembler alignment, ``"index"`` or ``"sync"`` (then ``sync_max_dn`` is required).
    device : optional
        OpenCL device selector (see :mod:`specgpu.engine.runtime`).
    white_roi, white_reflectance : optional
        A reference white in the field (as :class:`StreamDecoder`): each sequence's gains are measured on its
        host frames, its decoder corrected (:class:`specgpu.planning.correction.WhiteReference`) and the launches' matrices
        written by non-blocking copies into one set of small device buffers per result token (reused only after
        that sequence has left the sinks: no wait on the queue). The gains are in
        :attr:`StreamResult.white_gains`. A saturated or dark white stops the stream with a one-line error.
    """

    def __init__(self, driver: CameraDriver, plan, calibration, *, outputs=("coefficients", "XYZ", "dE"),
                 sinks=(), reference=None, method: str = "CIE 2000", illuminant: str | None = None,
                 observer: str | None = None, cube_dtype=np.float16, n_slots: int | None = None,
                 policy: str = "drop_newest", in_flight: int = 3, result_buffers: int = 6, readback: str = "auto",
                 upload: str = "auto", align: str = "index", sync_max_dn: float | None = None, device=None,
                 white_roi=None, white_reflectance=None):
        plan.check_calibration(calibration, name="stream plan")
        if policy not in POLICIES:
            raise ValueError(f"unknown ring policy {policy!r}; valid policies: {', '.join(POLICIES)}")
        if readback not in READBACKS:
            raise ValueError(f"unknown readback {readback!r}; valid: {', '.join(READBACKS)}")
        if upload not in UPLOADS:
            raise ValueError(f"unknown upload {upload!r}; valid: {', '.join(UPLOADS)}")
        if int(in_flight) < 1 or int(result_buffers) < int(in_flight):
            raise ValueError(f"need 1 <= in_flight <= result_buffers, got {in_flight} and {result_buffers}")
        self._stop = threading.Event()
        self.driver = _ArrivalDriver(driver, plan.K, self._stop)
        self.plan = plan
        self.queue = get_queue(device)
        self.decoder = StreamDecoder(plan, calibration, outputs, frame_shape=driver.frame_shape, queue=self.queue,
                                     reference=reference, method=method, illuminant=illuminant,
                                     observer=observer, cube_dtype=cube_dtype, white_roi=white_roi,
                                     white_reflectance=white_reflectance)
        self.sinks = [s if callable(getattr(s, "write", None)) else CallbackSink(s) for s in sinks]
        self.n_slots = max(4 * plan.K, 16) if n_slots is None else int(n_slots)
        self.policy = policy
        self.in_flight, self.result_buffers = int(in_flight), int(result_buffers)
        on_cpu = bool(self.queue.device.type & cl.device_type.CPU)
        self.readback = ("map" if on_cpu else "pinned") if readback == "auto" else readback
        self.upload = ("host_ptr" if on_cpu else "pinned") if upload == "auto" else upload
        self.align, self.sync_max_dn = align, sync_max_dn
        self._interrupted = False
        self._status_lock = threading.Lock()
        self.ring: RingBuffer | None = None
        self.assembler: SequenceAssembler | None = None
        self.sequences_out = 0
        self.latency = LatencyHistogram()

    # ---- control ---------------------------------------------------------------------------------------------
    def stop(self) -> None:
        """Ask the stream to end: the producer stops, everything already captured is still processed."""
        self._interrupted = True
        self._stop.set()

    def status(self) -> dict:
        """A live snapshot: frames in, sequences out, drops, latency of the latest results (thread-safe)."""
        ring = self.ring.stats() if self.ring is not None else None
        with self._status_lock:
            lat = list(self.latency.recent)
            out = self.sequences_out
        a = self.assembler.stats if self.assembler is not None else AssemblyStats()
        return {"frames_in": self.driver.delivered, "sequences_out": out,
                "ring_dropped": ring.dropped if ring else 0, "assembler_dropped": a.dropped,
                "discarded": a.sequences_discarded, "pending": ring.pending if ring else 0,
                "latency_ms": float(np.median(lat) * 1e3) if lat else float("nan")}

    # ---- the run ---------------------------------------------------------------------------------------------
    def run(self, seconds: float | None = None, *, on_status=None, status_interval_s: float = 0.5) -> StreamReport:
        """Stream until ``seconds`` have passed, the driver's stream ends, :meth:`stop` is called or Ctrl-C.

        Parameters
        ----------
        seconds : float, optional
            Capture time limit (the frames captured by then are still processed).
        on_status : callable, optional
            Given :meth:`status` every ``status_interval_s`` from the calling thread (a live status line).

        Returns
        -------
        StreamReport
        """
        shape = tuple(self.driver.frame_shape)
        if shape != (self.decoder.height, self.decoder.width):
            raise ValueError(f"driver frames are {shape}, the decoder was set up for "
                             f"{(self.decoder.height, self.decoder.width)}")
        self.ring = ring = RingBuffer(self.n_slots, shape, self.driver.dtype, self.policy)
        self.assembler = SequenceAssembler(self.plan.K, align=self.align, sync_max_dn=self.sync_max_dn)
        self._stop.clear()
        self._interrupted = False
        self.sequences_out = 0
        self.latency = LatencyHistogram()
        self._errors: list[BaseException] = []
        self._sink_errors: list[str] = []
        self._tokens = threading.Semaphore(self.result_buffers)
        self._done: queue_module.Queue = queue_module.Queue()
        self._recycle: deque = deque()
        frames_dtype = self.decoder.frames_dtype or np.dtype(self.driver.dtype)  # float32 when host-corrected
        nbytes = self.plan.K * self.decoder.n * frames_dtype.itemsize
        # pinned staging (upload) and pinned result sets (readback), one per result token, mapped once
        self._pinned: deque = deque(
            pinned_empty(self.queue, (nbytes,), np.uint8)
            for _ in range(self.result_buffers if self.upload == "pinned" else 0))
        self._host_sets: deque = deque(
            {name: pinned_empty(self.queue, shape, dtype)
             for name, (shape, dtype) in self.decoder.device_shapes().items()}
            for _ in range(self.result_buffers if self.readback == "pinned" else 0))
        # the white reference's per-sequence decoder: one set of matrix buffers per result token (device buffer and
        # the host array its non-blocking write reads, both reused only once that sequence has left the sinks)
        self._matrix_sets: deque = deque(
            [(cl.Buffer(self.queue.context, cl.mem_flags.READ_ONLY, m.nbytes), np.empty_like(m))
             for m in self.decoder.matrices(self.plan.A)]
            for _ in range(self.result_buffers if self.decoder.white_reference is not None else 0))
        self._ended = threading.Event()
        self.decoder.warm_up(frames_dtype)
        peak_rss_reset()
        rss_start = current_rss_bytes()
        usage0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        self.driver.start()
        producer = threading.Thread(target=self._produce, name="specgpu-stream-capture", daemon=True)
        device = threading.Thread(target=self._device_loop, name="specgpu-stream-device", daemon=True)
        sinks = threading.Thread(target=self._sink_loop, name="specgpu-stream-sinks", daemon=True)
        for t in (producer, device, sinks):
            t.start()
        deadline = None if seconds is None else t0 + float(seconds)
        next_status = t0 + status_interval_s
        # Waits use the sink thread's Event, never Thread.join: a KeyboardInterrupt landing inside join() can
        # leave CPython 3.11 believing a live thread has ended, and the drain would be cut short.
        try:
            while not self._ended.is_set():
                now = time.perf_counter()
                if deadline is not None and now >= deadline:
                    self._stop.set()
                    deadline = None
                if on_status is not None and now >= next_status:
                    on_status(self.status())
                    next_status = now + status_interval_s
                self._ended.wait(0.05)
        except KeyboardInterrupt:
            self.stop()  # drain: the threads finish what was captured (a second Ctrl-C abandons the drain)
        finally:
            self._stop.set()
            while not self._ended.wait(0.1):
                pass
            for t in (producer, device, sinks):
                t.join()
            self._recycle_done()  # the last results' maps, now that no thread uses the queue
            ring.close()
            get_allocator(self.queue).free_held()  # the stream's buffers go back to the system, not to the pool
        end = self.driver.stop()
        seconds_run = time.perf_counter() - t0
        usage1 = resource.getrusage(resource.RUSAGE_SELF)
        if self._errors:
            raise self._errors[0]
        stats = self.assembler.finish(end)
        if on_status is not None:
            on_status(self.status())
        return StreamReport(
            frames_in=self.driver.delivered, sequences_out=self.sequences_out, ring=ring.stats(), assembly=stats,
            end=end, seconds=seconds_run, latency=self.latency,
            cpu_s=(usage1.ru_utime + usage1.ru_stime) - (usage0.ru_utime + usage0.ru_stime),
            peak_rss_bytes=peak_rss_bytes(), interrupted=self._interrupted, sink_errors=self._sink_errors,
            rss_start_bytes=rss_start)

    def _produce(self):
        try:
            run_producer(self.driver, self.ring)  # ends at a sequence boundary after stop
        except BaseException as exc:  # noqa: BLE001 (surfaced by run(), in the caller's thread)
            self._errors.append(exc)
            self._stop.set()
            self.ring.close()

    # ---- device thread ---------------------------------------------------------------------------------------
    def _device_loop(self):
        pending: deque[_InFlight] = deque()
        index = 0
        try:
            while True:
                self._recycle_done()
                slot = self.ring.get(timeout=0.002 if pending else 0.05)
                if slot is None:
                    if pending:  # idle: finish what the device holds rather than sit on it
                        self._complete(pending.popleft())
                        continue
                    if self.ring.closed and self.ring.stats().pending == 0:
                        break
                    continue
                try:
                    seq = self.assembler.push(slot.array, slot.info)
                finally:
                    self.ring.release(slot)
                arrivals = self.driver.arrivals
                arrival = arrivals.pop(slot.info.frame_id, None)
                if len(arrivals) > 2 * self.n_slots:
                    # stamps of frames the ring discarded unread (drop_oldest) would pile up over a long run
                    for fid in [f for f in list(arrivals) if f < slot.info.frame_id]:
                        arrivals.pop(fid, None)
                if seq is None:
                    continue
                pending.append(self._submit(index, seq, arrival))
                index += 1
                while len(pending) > self.in_flight:
                    self._complete(pending.popleft())
                while pending and _finished(pending[0].events):
                    self._complete(pending.popleft())
            while pending:
                self._complete(pending.popleft())
        except BaseException as exc:  # noqa: BLE001 (surfaced by run(), in the caller's thread)
            self._errors.append(exc)
            self._stop.set()
            self.ring.close()
        finally:
            self._done.put(None)

    def _acquire_token(self):
        while not self._tokens.acquire(timeout=0.05):
            self._recycle_done()
            if self._errors:
                raise RuntimeError("stream: stopped on an error while waiting for a result buffer")

    def _submit(self, index: int, seq, arrival) -> _InFlight:
        self._acquire_token()  # a slow sink holds every buffer: wait here, and the frame ring's policy acts
        q, dec = self.queue, self.decoder
        keep = [seq]
        host_frames = dec.prepare_frames(seq.frames) if dec.precorrect else seq.frames
        flat = host_frames.reshape(-1)
        if dec.precorrect:
            keep.append(host_frames)
        if self.upload == "host_ptr":
            buf = cl.Buffer(q.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=flat)
            frames = cla.Array(q, flat.shape, flat.dtype, data=buf)
            keep.append(buf)
        elif self.upload == "pinned":
            pinned = self._pinned.popleft()  # one per result token: never empty here
            staging = pinned.view(flat.dtype)
            np.copyto(staging, flat)
            frames = cla.empty(q, flat.shape, flat.dtype, allocator=get_allocator(q))
            cl.enqueue_copy(q, frames.data, staging, is_blocking=False)  # DMA; free again once the sequence is
            keep.append(pinned)
        else:
            frames = cla.empty(q, flat.shape, flat.dtype, allocator=get_allocator(q))
            cl.enqueue_copy(q, frames.data, flat, is_blocking=False)
        keep.append(frames)
        matrix_set = gains = None
        if dec.white_reference is not None:
            # this sequence's decoder from its white patch (host frames, ~1 ms), written by small non-blocking
            # copies into this token's matrix buffers: the in-order queue runs them before the kernels
            gains = (dec.white_reference.gains(host_frames, dark=np.zeros(host_frames.shape[1:], np.float32))
                     if dec.precorrect else dec.white_reference.gains(seq.frames))
            matrix_set = self._matrix_sets.popleft()  # one per result token: never empty here
            for (buf, host), values in zip(matrix_set, dec.matrices(dec.white_reference.decoder(gains))):
                host[...] = values
                cl.enqueue_copy(q, buf, host, is_blocking=False)
        outs = dec.enqueue(frames, None if matrix_set is None else [buf for buf, _ in matrix_set])
        shapes = dec.device_shapes()
        host, events = {}, []
        host_set = self._host_sets.popleft() if self.readback == "pinned" else None  # one per result token
        for name, dev in outs.items():
            if name not in shapes:  # a buffer another launch read (dE_sigma's inputs): it stays on the device
                continue
            shape, dtype = shapes[name]
            if host_set is not None:
                arr = host_set[name]
                ev = cl.enqueue_copy(q, arr, dev, is_blocking=False)
            elif self.readback == "map":
                # READ | WRITE: saturated pixels are set to NaN in place on the host
                arr, ev = cl.enqueue_map_buffer(q, dev, cl.map_flags.READ | cl.map_flags.WRITE, 0, shape, dtype,
                                                is_blocking=False)
            else:
                arr = np.empty(shape, dtype)
                ev = cl.enqueue_copy(q, arr, dev, is_blocking=False)
            host[name] = arr
            events.append(ev)
        q.flush()  # start the device now, not at the next blocking call
        return _InFlight(index, seq, arrival if arrival is not None else time.perf_counter(), outs, host, events,
                         keep, host_set=host_set, matrix_set=matrix_set, white_gains=gains)

    def _complete(self, item: _InFlight):
        cl.wait_for_events(item.events)
        t = time.perf_counter()
        # the result's own dict: the sinks' view may drop or add maps, the mapped ones are all unmapped later
        result = StreamResult(item.index, item.seq.cycle, item.seq.frame_ids, item.seq.timestamps_s, dict(item.host),
                              t - item.t_arrival, frames=item.seq.frames, white_gains=item.white_gains)
        if self.upload == "pinned":
            item.pinned = item.keep[1]
        item.keep = [item.seq]  # frames and their device buffer are no longer needed
        self._done.put((item, result))

    def _recycle_done(self):
        # Unmaps and frees run on the device thread: the queue and the memory pool are used from one thread.
        while self._recycle:
            item = self._recycle.popleft()
            if self.readback == "map":
                for arr in item.host.values():
                    arr.base.release(self.queue)
            if self.upload == "pinned":
                self._pinned.append(item.pinned)
            if self.readback == "pinned":
                self._host_sets.append(item.host_set)
            if item.matrix_set is not None:
                self._matrix_sets.append(item.matrix_set)
            item.host = item.device_out = item.keep = None
            self._tokens.release()

    # ---- sink thread -----------------------------------------------------------------------------------------
    def _sink_loop(self):
        try:
            while True:
                entry = self._done.get()
                if entry is None:
                    break
                item, result = entry
                mask = result.arrays.pop("mask")
                saturated = (mask & 1).astype(bool) if mask.any() else None
                if saturated is not None:  # no valid measurement there: NaN, as the offline recovery
                    for arr in result.arrays.values():
                        arr[saturated] = np.nan
                    result.saturated_pixels = int(np.count_nonzero(saturated))
                try:
                    if not self._sink_errors:
                        for sink in self.sinks:
                            sink.write(result)
                except Exception as exc:  # noqa: BLE001 (reported; the stream stops and drains)
                    self._sink_errors.append(f"{type(exc).__name__}: {exc}")
                    self._stop.set()
                with self._status_lock:
                    self.sequences_out += 1
                    self.latency.add(result.latency_s)
                self._recycle.append(item)
        finally:
            for sink in self.sinks:
                try:
                    getattr(sink, "close", lambda: None)()
                except Exception as exc:  # noqa: BLE001
                    self._sink_errors.append(f"{type(exc).__name__} closing {type(sink).__name__}: {exc}")
            self._ended.set()


def _finished(events) -> bool:
    return all(ev.command_execution_status == cl.command_execution_status.COMPLETE for ev in events)
