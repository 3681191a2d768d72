"""Batch re-processing on Dask distributed: the raw frames of a recording (or a sequence folder) through a plan.

``specgpu batch REC.zarr --plan PLAN --out OUT.zarr`` runs one task per sequence on a Dask ``LocalCluster`` (or on
any ``dask.distributed`` scheduler given by address). Each task reads one sequence's frames, recovers it exactly
as ``specgpu recover SEQ --sequence i`` does (:func:`specgpu.pipeline.recover`, then ``to_XYZ`` / ``to_Lab`` /
``delta_E`` when asked) and writes its chunk of the output recording, then marks the chunk done in the ``done``
array. Workers keep their state between tasks (:func:`_worker_state`): the plan, calibration, OpenCL context and
queue (with its built programs), the source and output handles are made once per worker process and reused.

Resuming: an output that exists and was made by the same source, plan and outputs is continued: chunks marked
done are never recomputed. A worker lost mid-run costs only its own chunks: the scheduler gives its tasks to
other workers (each chunk is written whole before it is marked done, and writing it again gives the same bytes).

The output is a zarr v3 group laid out like a recording (:mod:`specgpu.recording`): ``cube`` / ``XYZ`` /
``Lab`` / ``dE`` along ``time`` with one chunk per sequence, ``wavelength``, ``time`` and ``frame_id``, plus
``done`` (time,) uint8.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .recording import _CHANNELS, _codecs, _DirectIO, consolidate, open_recording, patterns_hash, write_sequence_chunk

__all__ = ["BATCH_FORMAT", "BATCH_OUTPUTS", "BatchJob", "BatchReport", "prepare_batch", "run_batch"]

BATCH_FORMAT = "specgpu.batch"
BATCH_VERSION = 1
BATCH_OUTPUTS = ("cube", "XYZ", "Lab", "dE")


# ---------------------------------------------------------------------------------------------------- sources


class _RecordingSource:
    """Raw frames of a zarr recording (``specgpu stream --frames``)."""

    def __init__(self, path):
        self.path = Path(path)
        self.rec = open_recording(path)
        if not self.rec.attrs.get("frames") or "frames" not in self.rec.group:
            raise ValueError(f"{self.path}: the recording has no raw frames to re-process "
                             "(record them with specgpu stream --frames)")
        self.sequences = self.rec.sequences
        self.K = self.rec.K
        shape = self.rec.group["frames"].shape
        self.height, self.width = int(shape[2]), int(shape[3])
        self.patterns_hash = self.rec.attrs.get("patterns_hash")
        self.plan_hash = self.rec.attrs.get("plan_hash")
        self.default_calibration = self.path / "calibration.npz"

    def frames(self, i: int) -> np.ndarray:
        return self.rec.read("frames", i)

    def frame_ids(self) -> np.ndarray:
        return self.rec.read("frame_id", slice(0, self.sequences))

    def times(self) -> np.ndarray:
        return self.rec.read("time", slice(0, self.sequences))


class _FolderSource:
    """The sequences of a sequence folder (``specgpu capture``), read and checked once per process."""

    def __init__(self, path):
        from .pipeline import read_capture

        self.path = Path(path)
        self.folder = read_capture(path)
        self.sequences = self.folder.sequences
        self.K = self.folder.plan.K
        self.height, self.width = (int(s) for s in self.folder.frames.shape[2:])
        self.patterns_hash = patterns_hash(self.folder.plan)
        self.plan_hash = self.folder.plan.hash
        self.default_calibration = self.path / "calibration.npz"

    def frames(self, i: int) -> np.ndarray:
        return self.folder.frames[i]

    def frame_ids(self) -> np.ndarray:
        return np.array([r["frame_id"] for r in self.folder.records], np.int64).reshape(self.sequences, self.K)

    def times(self) -> np.ndarray:
        return np.array([r["timestamp_s"] for r in self.folder.records], np.float64)[::self.K]


def open_source(path):
    """A zarr recording with raw frames, or a sequence folder; one-line errors naming the path."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no recording or sequence folder there")
    if (path / "sequence.json").is_file():
        return _FolderSource(path)
    if (path / "zarr.json").is_file():
        return _RecordingSource(path)
    raise ValueError(f"{path}: neither a zarr recording (zarr.json) nor a sequence folder (sequence.json)")


# ------------------------------------------------------------------------------------------------------- job


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

    @property
    def key(self) -> tuple:
        return (self.source, self.out, self.plan.hash, self.calibration.hash, self.outputs, self.illuminant,
                self.method, self.device)


_STATE: dict = {}
_STATE_LOCK = threading.Lock()
_DIRECT = _DirectIO()  # whether the output's file system takes direct I/O (found on the first large chunk)
_POOL: list = []


def _writer_pool():
    """This process's chunk writer threads (made on first use)."""
    with _STATE_LOCK:
        if not _POOL:
            from concurrent.futures import ThreadPoolExecutor

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

    from .runtime import get_queue

    with _STATE_LOCK:
        state = _STATE.get(job.key)
        if state is not None:
            return state, False
        state = _WorkerState(queue=get_queue(job.device), source=open_source(job.source),
                             out=zarr.open_group(job.out, mode="r+", zarr_format=3))
        _STATE[job.key] = state
        return state, True


def process_sequence(job: BatchJob, i: int) -> dict:
    """Recover sequence ``i`` of the job's source and write its chunk of every output, then mark it done."""
    from .colorimetry import delta_E
    from .pipeline import SequenceFolder, recover, to_Lab, to_XYZ

    state, built = _worker_state(job)
    handles = state.__dict__.setdefault("_arrays", {})  # zarr handles of the output, opened once per worker
    for name in (*job.outputs, "done"):
        if name not in handles:
            handles[name] = state.out[name]
    # each output's chunk goes to its file as soon as it is computed (written as the recorder writes: zarr's bytes,
    # large chunks with direct I/O) while the next output is computed; done is marked once every write returned
    writes = []

    def put(name, value):
        if name in job.outputs:
            writes.append(_writer_pool().submit(write_sequence_chunk, handles[name], int(i), value, direct=_DIRECT))
        return value

    frames = state.source.frames(int(i))
    folder = SequenceFolder(Path(job.source), frames[None], job.plan, job.calibration, [], {})
    try:
        cube = put("cube", recover(folder, sequence=0, device=state.queue))
        if {"XYZ", "Lab", "dE"} & set(job.outputs):
            XYZ = put("XYZ", to_XYZ(cube, job.plan, job.illuminant, device=state.queue))
            Lab = put("Lab", to_Lab(XYZ, job.illuminant, device=state.queue))
            if "dE" in job.outputs:
                put("dE", delta_E(job.reference, Lab, job.method, device=state.queue))
    finally:
        for write in writes:  # every write waited for (a failed one re-raises) before the chunk counts as done
            write.result()
    write_sequence_chunk(handles["done"], int(i), 1)  # after every chunk of the sequence is written
    return {"index": int(i), "pid": state.pid, "built": built}


# ------------------------------------------------------------------------------------------------ the driver


@dataclass
class BatchReport:
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


def prepare_batch(source_path, plan, calibration, out, *, outputs=("cube",), illuminant="D65",
                  method="CIE 2000", reference=None, device=None) -> tuple[BatchJob, np.ndarray]:
    """Check the source against the plan, create (or reopen, to resume) the output; returns the job and the
    indices of the sequences still to compute. Every refusal is one line naming the file."""
    import zarr

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
    if "dE" in outputs and reference is None:
        raise ValueError("the dE output needs a reference (--delta-e-ref)")
    if {"XYZ", "Lab", "dE"} & set(outputs):
        plan.outputs_to_XYZ(illuminant)  # a plan whose outputs have no XYZ: refused here, not on every worker
    n, h, w = source.sequences, source.height, source.width
    if n == 0:
        raise ValueError(f"{source.path}: holds no committed sequence")
    out = Path(out)
    identity = {"format": BATCH_FORMAT, "version": BATCH_VERSION, "source": str(Path(source_path).resolve()),
                "source_plan_hash": source.plan_hash, "plan_hash": plan.hash, "calibration": calibration.hash,
                "outputs": list(outputs), "sequences": n, "illuminant": illuminant, "method": method}
    job = BatchJob(str(source_path), str(out), plan, calibration, outputs, illuminant, method,
                   None if reference is None else np.asarray(reference, np.float32), device)
    if out.exists():
        try:
            group = zarr.open_group(str(out), mode="r", zarr_format=3)
            attrs = dict(group.attrs)
            done = group["done"][:]
        except Exception as exc:  # noqa: BLE001
            raise ValueError(f"{out}: exists and is not a batch output to resume ({type(exc).__name__}); "
                             "choose a new --out") from None
        mismatch = [k for k, v in identity.items() if attrs.get(k) != v]
        if mismatch:
            raise ValueError(f"{out}: holds a batch of another {'/'.join(mismatch)}; resume only the same batch, "
                             "or choose a new --out")
        return job, np.flatnonzero(done == 0)
    group = zarr.open_group(str(out), mode="w-", zarr_format=3)
    group.attrs.update({**identity, "plan_method": plan.method, "status": "running"})

    def make(name, tail, dtype, dims, fill, attrs=None):
        group.create_array(name, shape=(n, *tail), chunks=(1, *tail), dtype=dtype, compressors=_codecs(),
                           fill_value=fill, dimension_names=("time", *dims), attributes=attrs or {},
                           config={"write_empty_chunks": True})

    B = plan.A.shape[0]
    reflectance = plan.output == "reflectance"
    for name in outputs:
        if name == "cube":
            dim = "wavelength" if reflectance else "output"
            make(name, (h, w, B), "float32", ("y", "x", dim), np.nan,
                 {"wavelength_units": "nm"} if reflectance else {"channels": list(map(str, plan.output_labels))})
        elif name in _CHANNELS:
            make(name, (h, w, 3), "float32", ("y", "x", f"{name}_channel"), np.nan, {"channels": list(_CHANNELS[name])})
        else:
            make(name, (h, w), "float32", ("y", "x"), np.nan, {"method": method})
    if "cube" in outputs and reflectance:
        group.create_array("wavelength", data=np.asarray(plan.output_wavelengths, np.float64),
                           dimension_names=("wavelength",), attributes={"units": "nm"}, compressors=_codecs())
    group.create_array("frame_id", data=source.frame_ids(), chunks=(1, source.K), dimension_names=("time", "pattern"),
                       compressors=_codecs())
    group.create_array("time", data=source.times(), chunks=(1,), dimension_names=("time",), attributes={"units": "s"},
                       compressors=_codecs())
    group.create_array("done", shape=(n,), chunks=(1,), dtype="uint8", fill_value=0, dimension_names=("time",),
                       compressors=_codecs(), config={"write_empty_chunks": True})
    return job, np.arange(n)


def run_batch(source_path, plan, calibration, out, *, outputs=("cube",), illuminant="D65", method="CIE 2000",
              reference=None, scheduler=None, workers: int = 1, client=None, progress: bool = True,
              on_done=None, device=None) -> BatchReport:
    """Re-process every sequence of ``source_path`` with ``plan`` into ``out`` on Dask (see the module docstring).

    Parameters
    ----------
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler; default a ``LocalCluster`` of ``workers`` processes
        with one thread each.
    client : distributed.Client, optional
        Use this client (and its cluster) instead.
    on_done : callable, optional
        Given each finished task's record (``index``, ``pid``, ``built``) on the calling thread.
    """
    import time

    from distributed import Client, LocalCluster, as_completed
    from tqdm import tqdm

    job, todo = prepare_batch(source_path, plan, calibration, out, outputs=outputs, illuminant=illuminant,
                              method=method, reference=reference, device=device)
    t0 = time.perf_counter()
    cluster = own = None
    try:
        if client is None:
            if scheduler:
                client = own = Client(scheduler)
            else:
                cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                       dashboard_address=":0")
                client = own = Client(cluster)
        pids: dict = {}
        built = 0
        if len(todo):
            [shared] = client.scatter([job], broadcast=True)
            t0 = time.perf_counter()  # the cluster's start is not the batch's time
            futures = [client.submit(process_sequence, shared, int(i), key=f"specgpu-batch-{i}-{job.plan.hash[:8]}",
                                     pure=False) for i in todo]
            with tqdm(total=len(todo), desc="batch", unit="seq", disable=not progress, leave=False) as bar:
                for future in as_completed(futures):
                    record = future.result()
                    pids[record["pid"]] = pids.get(record["pid"], 0) + 1
                    built += bool(record["built"])
                    future.release()
                    bar.update()
                    if on_done is not None:
                        on_done(record)
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
    done = int(np.count_nonzero(group["done"][:]))
    group.attrs["status"] = "complete" if done == total else "running"
    consolidate(out)
    return BatchReport(sequences=total, computed=len(todo), skipped=total - len(todo), seconds=seconds,
                       workers=n_workers, contexts_built=built, pids=pids)
