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
went (:meth:`specgpu.pipeline.stream_report.StreamReport.accounting`).

Device work per sequence is enqueued without blocking on one in-order queue: the upload of the K frames, the
linear kernel (basis coefficients or the full cube), the fused XYZ -> Lab -> dE kernel against a reference, and the
readbacks; the thread goes back to assembling while the device works, and waits on a sequence's events only when
``in_flight`` sequences are pending. Readback is by mapping the output buffers (``readback="map"``, zero copy on
CPU devices: the map is the buffer) or by copying into host arrays (``"copy"``, what a discrete GPU wants).

Shutdown (:meth:`Stream.stop`, ``KeyboardInterrupt`` in :meth:`Stream.run`, the time limit or the end of the
driver's stream) stops the producer; every frame already in the ring is still assembled, every complete sequence
still computed and handed to the sinks, and the frames left in an unfinished sequence are reported in the
assembler's ``frames_unused`` / ``sequences_discarded``.

A scene that moves during each sequence (``motion="global"`` or ``"affine"``) is decoded one sequence at a time as
``specgpu recover --motion`` decodes it (the motion mode of the stream's
:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder`): the device thread
hands each complete sequence to :data:`MOTION_THREADS` decoding threads, one per core up to 8 (the estimate on the
host is most of the cost, and much of it runs outside the GIL: two threads decode about 1.5 times as many
sequences per second on 2 cores) and takes their maps, host arrays (no map, no pinned set), in the sequences'
order.

This module is the runner (:class:`Stream`: the threads and the loop); the decoding of a sequence is
:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder` (its device-resident mode: the fused launches of
:mod:`specgpu.pipeline.decoder_outputs`), the consumers of its results are in
:mod:`specgpu.pipeline.sinks`, and what a finished stream reports is in :mod:`specgpu.pipeline.stream_report`.
"""

from __future__ import annotations

import os
import queue as queue_module
import resource
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from numpy.typing import DTypeLike

from specgpu.capture.assemble import AssemblyStats, SequenceAssembler
from specgpu.capture.driver import CameraDriver, FrameInfo, StreamEnd
from specgpu.capture.ringbuffer import POLICIES, RingBuffer, run_producer
from specgpu.core.mask import Mask
from specgpu.core.text import one_line
from specgpu.engine.runtime import get_allocator, get_queue
from specgpu.engine.transfer import pinned_empty
from specgpu.pipeline.decoder_outputs import STREAM_OUTPUTS
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.pipeline.sinks import CallbackSink, StreamResult, sink_label
from specgpu.pipeline.stream_report import (
    BEHIND,
    LatencyHistogram,
    StreamReport,
    current_rss_bytes,
    peak_rss_bytes,
    peak_rss_reset,
)

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan

__all__ = ["STREAM_OUTPUTS", "Stream"]

READBACKS = ("auto", "map", "copy", "pinned")
#: Threads decoding the sequences of a moving scene at once (each holds one sequence's frames and maps): one per
#: core up to 8 (the estimate's FFTs and array arithmetic run outside the GIL; a GPU machine's 16 cores decode
#: several sequences at once while its device does the rest).
MOTION_THREADS = max(1, min(8, os.cpu_count() or 1))
UPLOADS = ("auto", "host_ptr", "pinned", "copy")
#: Frames over which the live status measures the rate the source delivers at.
RATE_WINDOW = 64
#: The longest reason a report of a failed sink gives, characters.
SINK_REASON_CHARS = 160


# ------------------------------------------------------------------------------------------------------ stream


class _ArrivalDriver(CameraDriver):
    """Wraps the stream's driver: stamps each delivered frame's arrival (perf_counter) by frame id, for latency,
    and ends the stream at a sequence boundary once ``stop`` is set; keeps the (frame id, arrival) of the first, the
    last and the latest :data:`RATE_WINDOW` frames, the rate the source delivers at.

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
        self.first = self.last = None
        self.recent: deque = deque(maxlen=RATE_WINDOW)

    frame_shape = property(lambda self: self.inner.frame_shape)
    dtype = property(lambda self: self.inner.dtype)
    light = property(lambda self: self.inner.light)
    running = property(lambda self: self.inner.running)

    def start(self):
        self.delivered = 0
        self._last_pattern = self.k - 1
        self._after_stop = 0
        self.arrivals.clear()
        self.first = self.last = None
        self.recent.clear()
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
            now = time.perf_counter()
            self.delivered += 1
            self._last_pattern = int(info.pattern_index)
            if out is not None:
                self.arrivals[info.frame_id] = now
            self.last = (int(info.frame_id), now)
            if self.first is None:
                self.first = self.last
            self.recent.append(self.last)
        return info


def frame_rate(first, last, least_frames: int = 2) -> float | None:
    """Frames per second between two (frame id, arrival s) stamps, by frame id: a frame the source lost on the
    way is a drop the assembler counts, not a slower source; None with fewer than ``least_frames`` between."""
    if first is None or last is None or last[0] - first[0] < least_frames - 1 or last[1] <= first[1]:
        return None
    return (last[0] - first[0]) / (last[1] - first[1])


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
    motion: object = None
    layers: list | None = None
    decoding: object = None  # a moving scene's sequence: the future of its maps


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
    reference, method, illuminant, observer, integration, cube_dtype
        As :func:`specgpu.pipeline.decoder_outputs.outputs_for`.
    n_slots : int, optional
        Frames the ring holds (default 4 K, at least 16: room for jitter without adding latency at saturation).
    policy : str
        Frame ring policy when full: ``"drop_newest"`` (default: the camera never waits), ``"drop_oldest"`` or
        ``"block"`` (the driver waits: for replayed or simulated frames, measures the pipeline's own rate).
    in_flight : int
        Sequences enqueued on the device before the device thread waits for the oldest (with ``motion``, at least
        :data:`MOTION_THREADS`: one for each decoding thread).
    result_buffers : int
        Sequences between upload and the end of the sinks (>= in_flight); the bound on result memory (with
        ``motion``, at least the sequences in flight: up to :data:`MOTION_THREADS`, 8 on a machine of 8 cores or
        more, each holding a sequence's maps: 134 MB for 8 float32 outputs at 2048 x 2048).
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
        (``python tools/benchmarks/stream_transfers.py --seconds 4 --rounds 3``): host_ptr + map 1028 frames/s, copy
        + map
        965, host_ptr + copy 936, pinned + map 913, copy + copy 854, pinned + copy 833; mapping the outputs is
        worth ~10 %, and ALLOC_HOST_PTR staging buys nothing on a CPU device (it adds a host copy). The device
        alone needs 7.4 ms per sequence (1219 frames/s), 6.3 ms of it the dE2000 pass.
    align : str
        Assembler alignment, ``"index"`` or ``"sync"`` (then ``sync_max_dn`` is required).
    device : optional
        OpenCL device selector (see :mod:`specgpu.engine.runtime`).
    white_moves : {"scene", "camera"}
        With ``motion`` and ``white_roi``: the white moves with the scene or is fixed in the field.
    white_roi, white_reflectance : optional
        A reference white in the field (as :class:`~specgpu.pipeline.sequence_decoder.SequenceDecoder`): each
        sequence's gains are measured on its host frames, its decoder corrected
        (:class:`specgpu.planning.correction.WhiteReference`) and the launches' matrices written by non-blocking
        copies into one set of small device buffers per result token (reused only after that sequence has left
        the sinks: no wait on the queue). The gains are in :attr:`StreamResult.white_gains`. A saturated or dark
        white stops the stream with a one-line error.
    denoise : (radius, eps), optional
        Denoise the coefficients, cube and XYZ outputs with the guided filter of ``recover --denoise``
        (:func:`specgpu.pipeline.denoise.stream_denoise`; other outputs are refused with it).
    motion : {"none", "global", "affine", "flow"}
        Compensate a scene that moves during each sequence, as ``recover --motion``: each sequence's
        displacements estimated within it and its frames decoded through the warped kernel; outputs of
        :data:`specgpu.pipeline.moving_decode.MOTION_OUTPUTS` only (``denoise`` guided by the warped frames' sum,
        ``white_roi`` measured as ``white_moves`` says; the decoder's motion mode). Each result's
        :attr:`StreamResult.motion` holds the sequence's estimate.
    frame_rate_hz : float, optional
        The rate the plan's frames are meant to come at (default: the plan's shortest frame period's); a source
        that delivers slower (a twin that cannot render that fast, a pipeline that holds a blocking ring back)
        is said in :meth:`status` and in the report, with both rates.

    A sink that fails is stopped and reported in one line naming it: an optional one (:class:`Sink` ``optional``:
    EXR snapshots, a preview, a view) in :attr:`StreamReport.sinks_stopped`, the stream going on; any other in
    :attr:`StreamReport.sink_errors`, the capture stopping at the next sequence boundary while the sequences
    already captured still reach every sink that has not failed.
    """

    def __init__(self, driver: CameraDriver, plan: Plan, calibration: CalibrationBundle, *,
                 outputs=("coefficients", "XYZ", "dE"),
                 sinks=(), reference=None, method: str = "CIE 2000", illuminant: str | None = None,
                 observer: str | None = None, cube_dtype: DTypeLike = np.float16, n_slots: int | None = None,
                 policy: str = "drop_newest", in_flight: int = 3, result_buffers: int = 6, readback: str = "auto",
                 upload: str = "auto", align: str = "index", sync_max_dn: float | None = None, device=None,
                 white_roi=None, white_reflectance=None, white_moves: str = "scene", denoise=None,
                 motion: str = "none",
                 integration: str = "rectangle", frame_rate_hz: float | None = None):
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
        self.decoder = SequenceDecoder(plan, calibration, outputs, frame_shape=driver.frame_shape, device=self.queue,
                                       reference=reference, method=method, illuminant=illuminant,
                                       observer=observer, cube_dtype=cube_dtype, white_roi=white_roi,
                                       white_reflectance=white_reflectance, white_moves=white_moves,
                                       denoise=denoise,
                                       integration=integration, motion=motion)
        if self.decoder.motion != "none":
            readback = upload = "copy"  # the maps are made on the host: no mapped or pinned sets to recycle
            # a sequence in flight for each decoding thread, and a result buffer for each
            in_flight = max(int(in_flight), MOTION_THREADS)
            result_buffers = max(int(result_buffers), in_flight)
        self.sinks = [s if callable(getattr(s, "write", None)) else CallbackSink(s) for s in sinks]
        self.n_slots = max(4 * plan.K, 16) if n_slots is None else int(n_slots)
        self.policy = policy
        self.in_flight, self.result_buffers = int(in_flight), int(result_buffers)
        on_cpu = bool(self.queue.device.type & cl.device_type.CPU)
        self.readback = ("map" if on_cpu else "pinned") if readback == "auto" else readback
        self.upload = ("host_ptr" if on_cpu else "pinned") if upload == "auto" else upload
        self.align, self.sync_max_dn = align, sync_max_dn
        self.frame_rate_hz = float(1.0 / plan.frame_period_s if frame_rate_hz is None else frame_rate_hz)
        if not (np.isfinite(self.frame_rate_hz) and self.frame_rate_hz > 0):
            raise ValueError(f"frame_rate_hz must be a positive number, got {frame_rate_hz!r}")
        self._sinks_stopped: list[str] = []
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
        """A live snapshot: frames in, sequences out, drops, latency of the latest results, the rate the source
        delivers at over its latest :data:`RATE_WINDOW` frames beside the plan's, and the sinks stopped
        (thread-safe)."""
        ring = self.ring.stats() if self.ring is not None else None
        with self._status_lock:
            lat = list(self.latency.recent)
            out = self.sequences_out
        a = self.assembler.stats if self.assembler is not None else AssemblyStats()
        recent = tuple(self.driver.recent)
        rate = frame_rate(recent[0], recent[-1], least_frames=RATE_WINDOW // 4) if recent else None
        return {"frames_in": self.driver.delivered, "sequences_out": out,
                "ring_dropped": ring.dropped if ring else 0, "assembler_dropped": a.dropped,
                "discarded": a.sequences_discarded, "pending": ring.pending if ring else 0,
                "latency_ms": float(np.median(lat) * 1e3) if lat else float("nan"),
                "frame_rate_hz": rate, "plan_frame_rate_hz": self.frame_rate_hz,
                "behind": rate is not None and rate < BEHIND * self.frame_rate_hz,
                "sinks_stopped": list(self._sinks_stopped)}

    # ---- the run ---------------------------------------------------------------------------------------------
    def run(self, seconds: float | None = None, *, on_status=None, status_interval_s: float = 0.5,
            on_sink_stopped=None) -> StreamReport:
        """Stream until ``seconds`` have passed, the driver's stream ends, :meth:`stop` is called or Ctrl-C.

        Parameters
        ----------
        seconds : float, optional
            Capture time limit (the frames captured by then are still processed).
        on_status : callable, optional
            Given :meth:`status` every ``status_interval_s`` from the calling thread (a live status line).
        on_sink_stopped : callable, optional
            Given the one-line report of each optional sink the stream stopped, from the calling thread, soon after.

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
        self._sinks_stopped = []
        told = 0  # stopped sinks reported to on_sink_stopped
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
        self._motion_pool = (ThreadPoolExecutor(MOTION_THREADS, thread_name_prefix="specgpu-stream-motion")
                             if self.decoder.motion != "none" else None)
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
                told = _tell(on_sink_stopped, self._sinks_stopped, told)
                self._ended.wait(0.05)
        except KeyboardInterrupt:
            self.stop()  # drain: the threads finish what was captured (a second Ctrl-C abandons the drain)
        finally:
            self._stop.set()
            while not self._ended.wait(0.1):
                pass
            for t in (producer, device, sinks):
                t.join()
            if self._motion_pool is not None:  # every sequence handed to it was taken, or the stream failed
                self._motion_pool.shutdown(wait=True, cancel_futures=True)
            self._recycle_done()  # the last results' maps, now that no thread uses the queue
            ring.close()
            get_allocator(self.queue).free_held()  # the stream's buffers go back to the system, not to the pool
        end = self.driver.stop()
        seconds_run = time.perf_counter() - t0
        usage1 = resource.getrusage(resource.RUSAGE_SELF)
        _tell(on_sink_stopped, self._sinks_stopped, told)
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
            rss_start_bytes=rss_start, sinks_stopped=list(self._sinks_stopped),
            frame_rate_hz=frame_rate(self.driver.first, self.driver.last), plan_frame_rate_hz=self.frame_rate_hz)

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
                info = slot.info  # read before the release: the driver's thread may refill the slot at once
                try:
                    seq = self.assembler.push(slot.array, info)
                finally:
                    self.ring.release(slot)
                arrivals = self.driver.arrivals
                arrival = arrivals.pop(info.frame_id, None)
                if len(arrivals) > 2 * self.n_slots:
                    # stamps of frames the ring discarded unread (drop_oldest) would pile up over a long run
                    for fid in [f for f in list(arrivals) if f < info.frame_id]:
                        arrivals.pop(fid, None)
                if seq is None:
                    continue
                pending.append(self._submit(index, seq, arrival, pending))
                index += 1
                while len(pending) > self.in_flight:
                    self._complete(pending.popleft())
                while pending and (pending[0].decoding.done() if pending[0].decoding is not None
                                   else _finished(pending[0].events)):
                    self._complete(pending.popleft())
            while pending:
                self._complete(pending.popleft())
        except BaseException as exc:  # noqa: BLE001 (surfaced by run(), in the caller's thread)
            self._errors.append(exc)
            self._stop.set()
            self.ring.close()
        finally:
            self._done.put(None)

    def _acquire_token(self, pending):
        """A result buffer for the next sequence. The tokens come back only once the sinks have a result, so while
        none is free the results still on the device (``pending``, oldest first) are completed and handed to them:
        a sequence assembled from frames already waiting in the ring, before the previous one's events finished,
        would otherwise wait for a token that only that previous result frees (with one result buffer, a hang)."""
        while True:
            self._recycle_done()  # the tokens of results the sinks are done with
            if self._tokens.acquire(timeout=0.0 if pending else 0.05):
                return
            if pending:
                self._complete(pending.popleft())
                continue
            if self._errors:
                raise RuntimeError("stream: stopped on an error while waiting for a result buffer")

    def _submit(self, index: int, seq, arrival, pending) -> _InFlight:
        self._acquire_token(pending)  # a slow sink holds every buffer: wait here, and the frame ring's policy acts
        if self.decoder.motion != "none":  # estimated and decoded now: the maps come back as host arrays
            return _InFlight(index, seq, arrival if arrival is not None else time.perf_counter(), {}, {}, [],
                             [seq], decoding=self._motion_pool.submit(self.decoder.maps, seq.frames))
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
        if item.decoding is not None:
            item.host = item.decoding.result()  # a decoding error is raised here, on the device thread
            item.motion = item.host.pop("estimate")
            item.layers = item.host.pop("layers")
            item.white_gains = item.host.pop("white_gains", None)
        if item.events:
            cl.wait_for_events(item.events)
        t = time.perf_counter()
        # the result's own dict: the sinks' view may drop or add maps, the mapped ones are all unmapped later
        result = StreamResult(item.index, item.seq.cycle, item.seq.frame_ids, item.seq.timestamps_s, dict(item.host),
                              t - item.t_arrival, frames=item.seq.frames, white_gains=item.white_gains,
                              motion=item.motion, layers=item.layers)
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
        active = list(self.sinks)  # the sinks still written to: a failed one leaves it
        try:
            while True:
                entry = self._done.get()
                if entry is None:
                    break
                item, result = entry
                mask = result.arrays.pop("mask")
                saturated = (mask & Mask.SATURATED).astype(bool) if mask.any() else None
                if saturated is not None:  # no valid measurement there: NaN, as the offline recovery
                    for arr in result.arrays.values():
                        arr[saturated] = np.nan
                    result.saturated_pixels = int(np.count_nonzero(saturated))
                for sink in list(active):
                    try:
                        sink.write(result)
                    except Exception as exc:  # noqa: BLE001 (reported; see _sink_failed)
                        active.remove(sink)
                        self._sink_failed(sink, exc)
                with self._status_lock:
                    self.sequences_out += 1
                    self.latency.add(result.latency_s)
                self._recycle.append(item)
        finally:
            for sink in self.sinks:  # every one, a failed one too (a recording then says it failed)
                try:
                    getattr(sink, "close", lambda: None)()
                except Exception as exc:  # noqa: BLE001
                    if any(sink is a for a in active):  # a failed sink's close repeats the error reported
                        self._sink_failed(sink, exc, closing=True)
            self._ended.set()

    def _sink_failed(self, sink, exc, *, closing: bool = False) -> None:
        """Report a sink that raised, in one short line naming it: an optional one is stopped and the stream goes
        on; any other stops the capture (what was captured still reaches the sinks that have not failed)."""
        reason = one_line(f"{type(exc).__name__}: {exc}", SINK_REASON_CHARS)
        where = " closing" if closing else ""
        if getattr(sink, "optional", False):
            self._sinks_stopped.append(f"{sink_label(sink)} stopped{where}: {reason}")
        else:
            self._sink_errors.append(f"{sink_label(sink)}{where}: {reason}")
            self._stop.set()


def _tell(callback, messages: list, told: int) -> int:
    """Hand ``messages[told:]`` to ``callback`` (when given); returns how many have been handed."""
    n = len(messages)
    if callback is not None:
        for message in messages[told:n]:
            callback(message)
    return n


def _finished(events) -> bool:
    return all(ev.command_execution_status == cl.command_execution_status.COMPLETE for ev in events)
