"""Batch re-processing on Dask distributed: the raw frames of a recording (or a sequence folder) through a plan.

``specgpu batch REC.zarr --plan PLAN --out OUT.zarr`` runs its sequences as Dask tasks of up to 8 consecutive
sequences (a task costs ~13 ms of its own) on a Dask ``LocalCluster`` (or on any ``dask.distributed`` scheduler
given by address). Each sequence's frames are computed in one device pass as the stream computes them
(:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder`, device-resident: the cube by the plan's decoder, XYZ,
Lab and dE fused from the same frames, the calibration's corrections applied as ``specgpu recover`` applies them; on
a CPU device the frames are the device buffer and the results are mapped, no copy), equal to ``specgpu recover SEQ
--sequence i`` and its ``to_XYZ`` / ``to_Lab`` / ``delta_E`` to float rounding. Each output's chunk is written while
the task's next sequence is computed, and the sequence is marked done in the ``done`` array once all of its chunks
are written. Workers keep their state between tasks (:func:`_worker_state`): the plan, calibration, OpenCL context
and queue (with its built programs and the decoder's device maps), the source and output handles are made once per
worker process and reused.

Resuming: an output that exists and was made by the same batch is continued: chunks marked done are never
recomputed. "The same batch" is its identity, stored in the output's attributes: the source's path and content
(a recording's ``recording_id`` with the CRC32C checksum of every committed frames chunk; a sequence folder's frame
checksums from ``sequence.json``), the plan, the calibration and every option that changes a result (outputs,
illuminant, observer, dE method and reference). Any difference is refused in one line naming the option and both
values; a source replaced by another recording at the same path is another source. A worker lost mid-run costs only its
own chunks: the scheduler gives its tasks to other workers (each chunk is written whole before it is marked done,
and writing it again gives the same bytes).

Everything that can be checked before work is checked before the output is created and the cluster started: the
source against the plan and calibration (frame size included), every committed frames chunk (or listed frame
file) present. The output is created complete under a temporary name and renamed into place, so a batch killed
at any moment leaves either no output or one it can resume; resuming removes the ``*.partial`` chunks a killed
writer left. A sequence that fails on a worker (a corrupt chunk, a full disk) stops the batch with one line
naming it; what was done stays done.

The output is a zarr v3 group laid out like a recording (:mod:`specgpu.io.recording`; made and read back by
:mod:`specgpu.pipeline.batch_output`): ``cube`` / ``XYZ`` / ``Lab`` / ``dE`` and the uncertainty outputs ``sigma``
/ ``sigma_rms`` / ``dE_sigma`` (those of ``specgpu stream``, from the same decoder, so ``--motion``, ``--denoise``
and ``--white-roi`` compose with them as in the stream) along ``time`` with one chunk per sequence, ``mask`` (the
decoder's bits: why a pixel is NaN), ``wavelength``, ``time`` and ``frame_id``, plus ``done`` (time,) uint8.

A scene that moved during each sequence (``--motion global|affine``) is decoded one sequence at a time exactly as
``specgpu recover --motion`` decodes it (the same decoder's motion mode: the displacements
estimated within the sequence on the host, one warped device pass, pixels seen outside the field or whose frames
disagree NaN); the mode is part of the output's identity.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from numpy.typing import ArrayLike
from tqdm import tqdm

from specgpu.core.locks import OutputLocked, output_lock
from specgpu.core.mask import Mask
from specgpu.core.spectra import DEFAULT_CMFS, resolve_integration
from specgpu.engine.runtime import get_allocator, get_queue
from specgpu.io.chunks import DirectIO, write_sequence_chunk
from specgpu.io.recording import consolidate, patterns_hash, remove_partial_chunks
from specgpu.pipeline.batch_output import (
    BATCH_FORMAT,
    BATCH_OUTPUTS,
    BATCH_VERSION,
    COLOUR_OUTPUTS,
    create_output,
    done_flags,
    remove_dead_creations,
    unfinished_creation,
)
from specgpu.pipeline.batch_source import (
    _identity_mismatch,
    _RecordingSource,
    _reference_hash,
    open_source,
    reference_label,
)
from specgpu.pipeline.decoder_outputs import outputs_for
from specgpu.pipeline.moving_decode import check_motion_options
from specgpu.pipeline.sequence_decoder import WHITE_MOVES, SequenceDecoder
from specgpu.planning.correction import WhiteReference

if TYPE_CHECKING:
    from specgpu.calibration.bundle import CalibrationBundle
    from specgpu.planning.plans import Plan

__all__ = ["BATCH_FORMAT", "BATCH_OUTPUTS", "BatchJob", "BatchReport", "prepare_batch", "run_batch"]


@dataclass
class BatchJob:
    """Everything a worker needs, sent to each worker once (scattered); ``key`` names its cached state."""

    source: str
    out: str
    plan: object
    calibration: object
    outputs: tuple
    illuminant: str = "D65"
    method: str = "CIE 2000"
    reference: np.ndarray | None = None
    device: str | None = None
    source_id: str = ""
    observer: str = DEFAULT_CMFS
    sequences: int = 0  # the source's committed sequences when the batch started (a recording may still grow)
    denoise: tuple | None = None  # (radius, eps) of the guided filter of the linear outputs, or None
    motion: str = "none"  # "global" / "affine": each sequence decoded motion-compensated, as recover --motion
    integration: str = "rectangle"  # how reflectance is integrated to XYZ (and the white of Lab and dE)
    white: tuple | None = None  # (ROI, reflectance, where it moves) of a reference white in the field, or None
    mask: bool = True  # the output has a mask array (one made before the mask was written has none)

    @property
    def key(self) -> tuple:
        # the source's content id: a worker that outlives a batch (``--scheduler``) never reuses the handles of a
        # recording since replaced at the same path
        return (self.source, self.source_id, self.out, self.plan.hash, self.calibration.hash, self.outputs,
                self.illuminant, self.observer, self.method, self.device, self.denoise, self.motion,
                self.integration, self.white, self.mask)


_STATE: dict = {}
_STATE_LOCK = threading.Lock()
_STATES_KEPT = 4  # a long-lived worker keeps the states of its last few batches, not of every batch it ran
_DIRECT = DirectIO()  # whether the output's file system takes direct I/O (found on the first large chunk)
_POOL: list = []


def _writer_pool():
    """This process's chunk writer threads (made on first use)."""
    with _STATE_LOCK:
        if not _POOL:

            _POOL.append(ThreadPoolExecutor(max_workers=4, thread_name_prefix="specgpu-batch-writer"))
        return _POOL[0]


@dataclass
class _WorkerState:
    queue: object
    source: object
    out: object
    builds: int = 1
    pid: int = field(default_factory=os.getpid)


def _worker_state(job: BatchJob) -> tuple[_WorkerState, bool]:
    """This process's state for ``job``: built on the first task, reused by every later one."""
    import zarr

    with _STATE_LOCK:
        state = _STATE.get(job.key)
        if state is not None:
            return state, False
        source = open_source(job.source)
        if job.sequences and isinstance(source, _RecordingSource) and source.sequences > job.sequences:
            source.sequences = job.sequences  # a recording still being written: its content as the batch saw it
        if job.source_id and source.content_id != job.source_id:
            raise ValueError(f"{job.source}: changed since the batch started (another recording or capture at "
                             "that path); run the batch again")
        state = _WorkerState(queue=get_queue(job.device), source=source,
                             out=zarr.open_group(job.out, mode="r+", zarr_format=3))
        while len(_STATE) >= _STATES_KEPT:
            _STATE.pop(next(iter(_STATE)))
        _STATE[job.key] = state
        return state, True


def process_sequence(job: BatchJob, i: int) -> dict:
    """Recover sequence ``i`` of the job's source and write its chunk of every output, then mark it done.

    A failure is returned as ``error`` (one line naming the sequence), not raised: the driver stops the batch
    with that line, and no worker prints a traceback."""
    return process_sequences(job, [i])[0]


def process_sequences(job: BatchJob, indices) -> list[dict]:
    """:func:`process_sequence` of several sequences in one task (a Dask task costs ~13 ms of its own), each
    sequence written and marked done on its own as before: the writes of one sequence run while the next is
    computed, and its ``done`` is marked once they returned. The records in order; the first failure ends the
    list (its record carries ``error``), the sequences before it stay done."""
    records, pending = [], None
    for i in indices:
        i = int(i)
        try:
            started = _start_sequence(job, i)
        except Exception as exc:  # noqa: BLE001 (reported to the driver as one line)
            started = _error_record(job, i, exc)
        if pending is not None:
            records.append(_finish_or_record(job, pending))
            if records[-1].get("error"):
                if isinstance(started, _Pending):
                    _release(started)  # its writes are waited for, never marked done
                return records
        if isinstance(started, dict):
            records.append(started)
            return records
        pending = started
    if pending is not None:
        records.append(_finish_or_record(job, pending))
    return records


def _error_record(job: BatchJob, i: int, exc: BaseException) -> dict:
    text = str(exc).strip()
    line = text.splitlines()[0] if text else type(exc).__name__
    if not isinstance(exc, (ValueError, OSError)):
        line = f"{type(exc).__name__}: {line}"
    if f"sequence {int(i)}" not in line:
        line = f"{job.source}: sequence {int(i)}: {line}"
    return {"index": int(i), "pid": os.getpid(), "built": False, "error": line}


def _finish_or_record(job: BatchJob, pending) -> dict:
    try:
        return _finish_sequence(job, pending)
    except Exception as exc:  # noqa: BLE001
        return _error_record(job, pending.index, exc)


@dataclass
class _Pending:
    """A sequence computed and its chunks being written: waited for, unmapped and marked done by
    :func:`_finish_sequence`."""

    index: int
    state: object
    built: bool
    writes: list
    mapped: list
    buffers: dict  # the device buffers (pooled) the mapped results are views of: never reused while written


def _decoder(job: BatchJob, state):
    """This worker's decoder of the job (:class:`specgpu.pipeline.sequence_decoder.SequenceDecoder`, made once;
    device-resident, or in the job's motion mode): the plan's A, the calibration's dark, flat field and saturation
    level and, for colour outputs, the matrix to XYZ of the plan's outputs with the white and the dE reference, on
    the device. The cube comes from one linear pass over
    the frames and XYZ, Lab and dE from one fused pass over the same frames (never from the cube read back), as
    the stream computes them; the host-side corrections recover applies (linearisation, per-pattern flat field,
    an ambient frame) are applied to the frames first exactly as recover does (``prepare_frames``)."""
    dec = state.__dict__.get("_decoder")
    if dec is None:
        dec = SequenceDecoder(job.plan, job.calibration, job.outputs,
                              frame_shape=(state.source.height, state.source.width), device=state.queue,
                              reference=job.reference if "dE" in job.outputs else None, method=job.method,
                              illuminant=job.illuminant, observer=job.observer, cube_dtype=np.float32,
                              denoise=job.denoise, integration=job.integration, motion=job.motion,
                              **dict(zip(("white_roi", "white_reflectance", "white_moves"), job.white or ())))
        # on a CPU device the frames are the device buffer and the results are mapped (no copy either way)
        state._zero_copy = bool(state.queue.device.type & cl.device_type.CPU)
        state._decoder = dec
    return dec


def _start_sequence(job: BatchJob, i: int) -> _Pending:
    """Compute sequence ``i`` in one device pass and start writing each output's chunk (written as the recorder
    writes: zarr's bytes, large chunks with direct I/O)."""
    state, built = _worker_state(job)
    handles = state.__dict__.setdefault("_arrays", {})  # zarr handles of the output, opened once per worker
    for name in (*job.outputs, *(("mask",) if job.mask else ()), "done"):
        if name not in handles:
            handles[name] = state.out[name]
    if job.motion != "none":
        return _start_moving(job, i, state, built, handles)
    dec = _decoder(job, state)
    q = state.queue
    raw = state.source.frames(i)
    if tuple(raw.shape) != (dec.K, dec.height, dec.width):
        raise ValueError(f"{job.source}: sequence {i}: frames of shape {tuple(raw.shape)}, the batch needs "
                         f"({dec.K}, {dec.height}, {dec.width})")
    host = dec.prepare_frames(raw) if dec.precorrect else raw
    flat = np.ascontiguousarray(host).reshape(-1)
    zero_copy = state._zero_copy
    if zero_copy:
        buf = cl.Buffer(q.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=flat)
        frames = cla.Array(q, flat.shape, flat.dtype, data=buf)
    else:
        frames = cla.to_device(q, flat, allocator=get_allocator(q))
    white = dec.white_matrices(raw, host)  # a reference white: this sequence's decoder, as the stream's
    outs = dec.enqueue(frames, None if white is None else [cla.to_device(q, m).data for m in white])
    shapes = dec.shapes()
    arrays, mapped, events = {}, [], []
    for name, dev in outs.items():
        if name not in shapes:  # a buffer the decoder computes from and keeps on the device (a denoised Lab's XYZ)
            continue
        shape, dtype = shapes[name]
        if zero_copy:  # READ | WRITE: saturated pixels are set to NaN in place
            arr, ev = cl.enqueue_map_buffer(q, dev, cl.map_flags.READ | cl.map_flags.WRITE, 0, shape, dtype,
                                            is_blocking=False)
            mapped.append(arr)
        else:
            arr = np.empty(shape, dtype)
            ev = cl.enqueue_copy(q, arr, dev, is_blocking=False)
        arrays[name] = arr
        events.append(ev)
    pending = _Pending(i, state, built, [], mapped, outs)
    try:
        cl.wait_for_events(events)
        mask = arrays["mask"] if job.mask else arrays.pop("mask")
        if mask.any():  # a sample at the sensor's maximum code: no valid measurement, NaN as recover makes it
            saturated = (mask & Mask.SATURATED).astype(bool)
            for name in job.outputs:
                arrays[name][saturated] = np.nan
        _write_chunks(job, i, pending, handles, arrays)
    except BaseException:
        _release(pending)
        raise
    del frames
    return pending


def _start_moving(job: BatchJob, i: int, state, built: bool, handles: dict) -> _Pending:
    """Sequence ``i`` decoded motion-compensated on the host and device as ``recover --motion`` decodes it
    (:func:`_decoder`'s motion mode, made once per worker), its chunks written as
    :func:`_start_sequence` writes them."""
    dec = _decoder(job, state)
    raw = state.source.frames(i)
    h, w = state.source.height, state.source.width
    if tuple(raw.shape) != (job.plan.K, h, w):
        raise ValueError(f"{job.source}: sequence {i}: frames of shape {tuple(raw.shape)}, the batch needs "
                         f"({job.plan.K}, {h}, {w})")
    pending = _Pending(i, state, built, [], [], {})
    _write_chunks(job, i, pending, handles, dec.maps(raw))
    return pending


def _write_chunks(job: BatchJob, i: int, pending: _Pending, handles: dict, arrays: dict) -> None:
    """Start writing sequence ``i``'s chunk of every output (and of the mask, where the output has one) on the
    writer threads, as the recorder writes them (zarr's bytes, large chunks with direct I/O)."""
    for name in (*job.outputs, *(("mask",) if job.mask else ())):
        pending.writes.append((name, _writer_pool().submit(write_sequence_chunk, handles[name], i, arrays[name],
                                                           direct=_DIRECT)))


def _release(pending: _Pending) -> None:
    """Wait for every write of ``pending``, then unmap its results."""
    for _, write in pending.writes:
        write.exception()
    for arr in pending.mapped:
        arr.base.release(pending.state.queue)
    pending.mapped, pending.buffers = [], {}  # unmapped: the buffers go back to the pool


def _finish_sequence(job: BatchJob, pending: _Pending) -> dict:
    """Wait for the chunks of a started sequence, then mark it done (after every chunk is written)."""
    i = pending.index
    _release(pending)  # every write waited for before the chunk counts as done, or before failing
    for name, write in pending.writes:
        if write.exception() is not None:
            raise _write_error(job, name, i, write.exception())
    try:
        # through zarr (a temporary renamed into place): a kill leaves the mark absent or whole, never an empty file
        pending.state.__dict__["_arrays"]["done"][i] = 1
    except Exception as exc:  # noqa: BLE001
        raise _write_error(job, "done", i, exc) from None
    return {"index": i, "pid": pending.state.pid, "built": pending.built}


def _write_error(job: BatchJob, name: str, i: int, exc: BaseException) -> OSError:
    """A failed chunk write (a full disk) as one line naming the output array and the sequence, never the file
    the writer was writing."""
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else \
        (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    return OSError(f"{job.out}/{name}: writing sequence {i} failed ({reason})")


# ------------------------------------------------------------------------------------------------ the driver


@dataclass
class BatchReport:
    """What a batch did: the sequences it saw, computed and skipped (already in the output)."""

    sequences: int
    computed: int
    skipped: int
    seconds: float
    workers: int
    contexts_built: int
    pids: dict

    @property
    def sequences_per_s(self) -> float:
        return self.computed / self.seconds if self.seconds > 0 else 0.0


def prepare_batch(source_path: str | os.PathLike[str], plan: Plan, calibration: CalibrationBundle,
                  out: str | os.PathLike[str], *, outputs=("cube",), illuminant=None, observer=None,
                  method: str = "CIE 2000", reference=None, device=None, denoise=None, motion: str = "none",
                  integration: str = "rectangle", white=None) -> tuple[BatchJob, np.ndarray]:
    """Check the source against the plan, create (or reopen, to resume) the output; returns the job and the
    indices of the sequences still to compute. Every refusal is one line naming the file, found before the
    output is created. ``illuminant``: of XYZ, Lab and dE, recorded in the output; default the plan's own for a
    tristimulus or camera plan, else D65 (:meth:`specgpu.planning.plans.Plan.resolve_illuminant`); ``observer`` likewise
    (:meth:`specgpu.planning.plans.Plan.resolve_observer`: a tristimulus plan's own, else the 2 degree observer);
    ``integration``: of reflectance to XYZ and of the white (:meth:`specgpu.planning.plans.Plan.white_XYZ`),
    recorded too. ``white``: (ROI, reflectance, ``"scene"`` or ``"camera"``) of a reference white in the field
    (``--white-roi``, ``--white-reflectance``, ``--white-roi-moves``), each sequence's decoder corrected by it as
    recover corrects it; in the identity."""
    import zarr

    illuminant = plan.resolve_illuminant(illuminant, name="the batch plan")
    observer = plan.resolve_observer(observer, name="the batch plan")
    _remove_dead_writers_partials(source_path)
    source = open_source(source_path)
    outputs = tuple(dict.fromkeys(outputs))
    unknown = [o for o in outputs if o not in BATCH_OUTPUTS]
    if unknown or not outputs:
        raise ValueError(f"unknown batch output {unknown[0] if unknown else '(none)'!r}; valid outputs: "
                         f"{', '.join(BATCH_OUTPUTS)}")
    if plan.K != source.K or patterns_hash(plan) != source.patterns_hash:
        raise ValueError(f"{source.path}: recorded with plan {str(source.plan_hash)[:12]} ({source.K} patterns), "
                         f"whose illumination sequence is not the given plan's ({plan.hash[:12]}, {plan.K} "
                         "patterns); re-process frames only with a plan of the same patterns")
    plan.check_calibration(calibration, name="the batch plan")
    if tuple(calibration.frame_shape) != (source.height, source.width):
        raise ValueError(f"{source.path}: frames are {source.height} x {source.width} pixels but the calibration "
                         f"{calibration.hash[:12]} is for {calibration.frame_shape[0]} x "
                         f"{calibration.frame_shape[1]}; re-process with the calibration of the capture")
    if "dE" in outputs and reference is None:
        raise ValueError("the dE output needs a reference (--delta-e-ref)")
    if reference is not None and "dE" not in outputs:
        reference = None  # no result uses it
    if reference is not None:
        ref = np.asarray(reference, np.float32)
        if ref.shape not in ((3,), (source.height, source.width, 3)):
            raise ValueError(f"the dE reference must be one L,a,b or a {source.height} x {source.width} x 3 map, "
                             f"got shape {ref.shape}")
    # the outputs as every worker's decoder will decide them, refused here, not on every worker: a plan with no
    # XYZ or a grid the integration has no table for, a sigma of a plan with no noise model, outputs the filter
    # cannot carry
    outputs_for(plan, outputs, frame_shape=(source.height, source.width), reference=reference, method=method,
                illuminant=illuminant, observer=observer, integration=integration, denoise=denoise)
    motion = check_motion_options(motion, plan, outputs=outputs)  # before any work
    if denoise is not None:
        denoise = (int(denoise[0]), float(denoise[1]))
    n, h, w = source.sequences, source.height, source.width
    if white is not None:  # the ROI and reflectance checked now, not on every worker
        white = (str(white[0]), None if white[1] is None else str(white[1]), str(white[2] or "scene").lower())
        if white[2] not in WHITE_MOVES:
            raise ValueError(f"--white-roi-moves must be one of {', '.join(WHITE_MOVES)}, got {white[2]!r}")
        WhiteReference(plan, calibration, white[0], white[1], frame_shape=(h, w))
    if n == 0:
        raise ValueError(f"{source.path}: holds no committed sequence")
    out = Path(out)
    colour = bool(set(COLOUR_OUTPUTS) & set(outputs))  # XYZ's illuminant, observer and integration matter
    identity = {"format": BATCH_FORMAT, "version": BATCH_VERSION, "source": str(Path(source_path).resolve()),
                "source_id": source.content_id, "source_plan_hash": source.plan_hash, "plan_hash": plan.hash,
                "calibration": calibration.hash, "outputs": list(outputs), "sequences": n,
                "illuminant": illuminant if colour else None, "observer": observer if colour else None,
                "integration": resolve_integration(integration) if colour else None,
                "method": method if "dE" in outputs else None,
                "reference_sha256": _reference_hash(reference), "delta_e_ref": reference_label(reference),
                "denoise": None if denoise is None else list(denoise),
                "motion": None if motion == "none" else motion,
                **dict(zip(("white_roi", "white_reflectance", "white_roi_moves"),
                           (None,) * 3 if white is None else (*white[:2], None if motion == "none" else white[2])))}
    job = BatchJob(str(source_path), str(out), plan, calibration, outputs, illuminant, method,
                   None if reference is None else np.asarray(reference, np.float32), device, identity["source_id"],
                   observer, n, denoise, motion, resolve_integration(integration), white)
    remove_dead_creations(out)
    if out.exists() and unfinished_creation(out):
        shutil.rmtree(out)  # made by an older specgpu killed before its first sequence: nothing in it to keep
    if out.exists():
        try:
            group = zarr.open_group(str(out), mode="r", zarr_format=3)
            attrs = dict(group.attrs)
            done = done_flags(group["done"])
            job.mask = "mask" in group  # an output made before the mask was written is resumed without one
        except Exception as exc:  # noqa: BLE001
            raise ValueError(f"{out}: exists and is not a batch output to resume ({type(exc).__name__}); "
                             "choose a new --out") from None
        mismatch = _identity_mismatch(out, attrs, identity)
        if mismatch:
            raise ValueError(mismatch)
        remove_partial_chunks(out)  # half-written chunks of a killed run (no writer runs on it now)
        return job, np.flatnonzero(done == 0)
    create_output(out, identity, plan, method, outputs, source, n, h, w)
    return job, np.arange(n)


def _remove_dead_writers_partials(source_path) -> None:
    """The ``*.partial`` chunks a recorder killed by ``kill -9`` left in a recording (5 MB each for raw frames):
    removed when no live writer holds the recording's lock (a recording is never written again, so nothing
    else would); a live writer's, or a recording we cannot lock (read-only), are left alone."""
    path = Path(source_path)
    if not (path / "zarr.json").is_file() or not any(path.rglob("*.partial")):
        return
    try:
        with output_lock(path):  # a recorder used from Python holds no lock: its metadata renames are left alone
            remove_partial_chunks(path, chunks_only=True)
    except (OutputLocked, OSError):
        pass


#: Sequences per Dask task at most: a task costs ~13 ms of its own, a sequence ~40 ms on 2 cores; more per task
#: would leave workers idle at the end of a batch, and a killed worker's unfinished task is rerun whole (the
#: sequences it had marked done are written again, the same bytes).
_TASK_SEQUENCES = 8


def _task_groups(todo, workers: int) -> list[list[int]]:
    """``todo`` split into consecutive groups, one Dask task each: up to :data:`_TASK_SEQUENCES` sequences, and
    at least 4 tasks per worker so that every worker has work to the end."""
    todo = [int(i) for i in todo]
    size = max(1, min(_TASK_SEQUENCES, len(todo) // (4 * max(1, int(workers)))))
    return [todo[k:k + size] for k in range(0, len(todo), size)]


def run_batch(source_path: str | os.PathLike[str], plan: Plan, calibration: CalibrationBundle,
              out: str | os.PathLike[str], *, outputs=("cube",), illuminant=None, observer=None,
              method: str = "CIE 2000", reference=None, scheduler: str | None = None, workers: int = 1, client=None,
              progress: bool = True, on_done=None, device=None, denoise: ArrayLike | None = None, motion: str = "none",
              integration: str = "rectangle", white=None) -> BatchReport:
    """Re-process every sequence of ``source_path`` with ``plan`` into ``out`` on Dask (see the module docstring).

    Parameters
    ----------
    outputs : sequence of str
        Of ``BATCH_OUTPUTS``: ``cube``, ``XYZ``, ``Lab``, ``dE`` (with ``reference``), and the uncertainty
        outputs of the stream, decided by its decoder (``decoder_outputs.outputs_for``): ``sigma`` (each
        output's standard deviation, then their RMS), ``sigma_rms`` (that RMS alone), ``dE_sigma`` (the
        first-order CIEDE2000 standard deviation); the sigmas need the plan's noise model.
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler; default Dask's own setting, ``scheduler-address``
        (the environment's ``DASK_SCHEDULER_ADDRESS``), where it is set, else a ``LocalCluster`` of ``workers``
        processes with one thread each.
    client : distributed.Client, optional
        Use this client (and its cluster) instead.
    on_done : callable, optional
        Given each finished task's record (``index``, ``pid``, ``built``) on the calling thread.
    denoise : (radius, eps), optional
        Denoise the cube and XYZ with the guided filter of ``recover --denoise`` (recorded in the output's
        identity: a resumed batch must ask the same).
    motion : {"none", "global", "affine", "flow"}
        Decode each sequence motion-compensated exactly as ``recover --motion`` (the displacements estimated
        within the sequence; pixels seen outside the field or inconsistent are NaN); in the output's identity.
    integration : {"rectangle", "ASTM E308"}
        How reflectance outputs are integrated to XYZ, and the white of Lab and dE with them; in the identity.
    white : (roi, reflectance, moves), optional
        A reference white in the field, as ``recover --white-roi`` (with ``motion``, measured on the warped
        samples, ``"scene"``, or on the raw pixels, ``"camera"``); in the identity.
    """
    with output_lock(out, make_parents=True):  # one batch per output: resuming, cleaning and writing are its own
        return _run_locked(source_path, plan, calibration, out, outputs=outputs, illuminant=illuminant,
                           observer=observer, method=method, reference=reference, scheduler=scheduler,
                           workers=workers, client=client, progress=progress, on_done=on_done, device=device,
                           denoise=denoise, motion=motion, integration=integration, white=white)


def _run_locked(source_path, plan, calibration, out, *, outputs, illuminant, observer, method, reference, scheduler,
                workers, client, progress, on_done, device, denoise=None, motion="none",
                integration="rectangle", white=None) -> BatchReport:

    import dask
    from distributed import Client, LocalCluster, as_completed

    if scheduler is None and client is None:  # the scheduler Dask is configured with, as Client() connects to
        scheduler = dask.config.get("scheduler-address", None)

    job, todo = prepare_batch(source_path, plan, calibration, out, outputs=outputs, illuminant=illuminant,
                              observer=observer, method=method, reference=reference, device=device,
                              denoise=denoise, motion=motion, integration=integration, white=white)
    t0 = time.perf_counter()
    cluster = own = None
    failure = None
    try:
        if client is None:
            if scheduler:
                client = own = Client(scheduler)
            else:  # the workers' log lines (a worker restarted, ...) stay out of the command's output
                cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                       dashboard_address=":0", silence_logs=logging.ERROR)
                client = own = Client(cluster)
        pids: dict = {}
        built = 0
        if len(todo):
            [shared] = client.scatter([job], broadcast=True)
            t0 = time.perf_counter()  # the cluster's start is not the batch's time
            run = uuid.uuid4().hex[:12]  # this run's task keys: never another batch's result on a shared scheduler
            futures = [client.submit(process_sequences, shared, group, key=f"specgpu-batch-{group[0]}-{run}",
                                     pure=False)
                       for group in _task_groups(todo, len(client.scheduler_info().get("workers", {})) or 1)]
            with tqdm(total=len(todo), desc="batch", unit="seq", disable=not progress, leave=False) as bar:
                for future in as_completed(futures):
                    records = future.result()
                    future.release()
                    for record in records:
                        if record.get("error"):
                            failure = record["error"]
                            break
                        pids[record["pid"]] = pids.get(record["pid"], 0) + 1
                        built += bool(record["built"])
                        bar.update()
                        if on_done is not None:
                            on_done(record)
                    if failure is not None:
                        client.cancel(futures)
                        break
        seconds = time.perf_counter() - t0
        n_workers = len(client.scheduler_info().get("workers", {}))
    finally:
        if own is not None:
            own.close()
        if cluster is not None:
            cluster.close()
    import zarr

    group = zarr.open_group(str(out), mode="r+", zarr_format=3)
    total = group["done"].shape[0]
    done = int(np.count_nonzero(done_flags(group["done"])))
    group.attrs["status"] = "complete" if done == total else "running"
    consolidate(out)
    if failure is not None:
        raise ValueError(f"{failure} ({done} of {total} sequences done in {out}; run the batch again to resume)")
    return BatchReport(sequences=total, computed=len(todo), skipped=total - len(todo), seconds=seconds,
                       workers=n_workers, contexts_built=built, pids=pids)
