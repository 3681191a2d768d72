"""Recordings: a stream's results (and raw frames when asked) as a zarr v3 group that xarray and Dask open directly.

Layout of ``REC.zarr`` (format ``specgpu.io.recording``, version 1)::

    attributes     format, version, recording_id, plan_hash, plan_method, calibration, patterns_hash, K, height,
                   width, outputs, frames, sequences_committed, status ("recording" | "complete" | "failed"),
                   error (why a failed recording stopped), metadata, compression (per array: the codec chosen and
                   what it measured; see Writing below)
    time           (time,)                     float64, s: exposure start of each sequence's first frame
    frame_id       (time, pattern)             int64, the K frame ids of each sequence
    timestamp_s    (time, pattern)             float64, s: exposure start of each frame
    cycle          (time,)                     int64, the assembler's cycle
    cube           (time, y, x, wavelength)    the plan's outputs; ``wavelength`` (nm) is a coordinate array
    coefficients   (time, y, x, component)     basis coefficients; the basis is the ``basis`` array (basis_wavelength,
                                               component), and for a reflectance plan ``basis_wavelength`` (nm) is
                                               its coordinate array: ``cube = coefficients @ basis.T``
    XYZ, Lab       (time, y, x, channel)       channel names in the array's ``channels`` attribute
    dE             (time, y, x)
    sigma          (time, y, x, sigma_channel) standard deviation of each plan output, then their RMS (channel names
                                               in ``channels``: ``sigma_<output label>``..., ``sigma_rms``)
    sigma_rms      (time, y, x)                the RMS channel of ``sigma`` alone
    dE_sigma       (time, y, x)                first-order dE2000 standard deviation
    white_gains    (time, pattern)             float64: the reference white's measured / predicted output per
                                               pattern that corrected each sequence's decoder (``--white-roi``)
    frames         (time, pattern, y, x)       uint16 raw frames (DN), when recorded
    pattern        (pattern,)                  0 ... K - 1

Every array along ``time`` has one chunk per sequence and names its dimensions (zarr v3 ``dimension_names``), so
``xarray.open_zarr(REC)`` gives named dimensions with ``time`` and ``wavelength`` as coordinates, and
``dask.array.from_zarr(REC, component="XYZ")`` gives one Dask chunk per sequence. Chunks carry a CRC32C checksum,
so a corrupt chunk is an error, never silently wrong values.

Writing: each chunk is encoded by the recorder itself (little-endian bytes, optionally a Blosc compressor, the
CRC32C) and written straight to its file by a pool of threads, the chunks of one sequence in parallel: the same
bytes zarr would write, at about a third of zarr's memory traffic per chunk (zarr fills a new chunk, copies the data
in and copies it again to append the checksum), with no temporary file and no sync per chunk. Chunks of 1 MiB and
more are written with direct I/O where the file system has it (as 8 MiB slices in flight at once): the page
cache's copy and write-back cost more CPU than the whole stream on a small machine, and a killed process loses
nothing it has written. Compression is chosen per array by measurement on the first sequence
when the disk's write rate is known (:func:`probe_write_rate`): a codec is used only where the time it costs to
encode is less than the disk time it saves (the 10-bit raw frames shrink about 4x for a few ms; noisy float maps
shrink about 1.2x for more CPU than the disk time saved on a fast disk); the choice and its figures are in the
``compression`` attribute. :func:`check_write_rate` refuses, before a stream starts, a recording the disk cannot
keep up with.

Commit rule: a sequence's chunks are all written before the group's ``sequences_committed`` is raised to include
it. Arrays grow by blocks of sequences (``grow``) and are cut to the committed count when the recording closes,
normally or on an error; a recording cut by ``kill -9`` may show up to a block of fill values (NaN, ids -1) past
the commit to a reader that ignores it. :func:`open_recording` trusts ``sequences_committed``: a recording cut by
a crash or a full disk keeps every committed sequence readable and loses at most the one being written. A
recording is never appended to: a new recording into an existing folder is refused.

``recording_id`` is a random identifier written once when the recording is created: two recordings at the same path
(one replaced by another) never share it, so whatever was derived from a recording (a ``specgpu batch`` output)
knows whether its source is still the same one.

Reading it with another tool (xarray, zarr, Dask): check it the way :meth:`Recording.read` does, because zarr
itself returns the fill value (0, NaN) for a chunk that is not on disk, never an error:

1. use only the first ``sequences_committed`` entries along ``time`` (``status`` "complete" also says the
   writer closed it; "recording" means it was cut by a crash and may hold fill values past the commit)::

       ds = xarray.open_zarr(REC)
       ds = ds.isel(time=slice(0, ds.attrs["sequences_committed"]))

2. every committed sequence must have its chunk of every array on disk: the chunk of sequence ``i`` of array
   ``NAME`` is the file ``REC/NAME/c/i/0/.../0`` (zarr v3's default chunk key, one chunk per sequence), so::

       arr = zarr.open_group(REC, mode="r")[NAME]
       n = arr.nchunks_initialized  # chunks on disk; must equal sequences_committed (closed recordings are cut
                                    # to the commit; a crashed one may also hold chunks past it)

   or :func:`missing_sequences` (``specgpu.io.recording.missing_sequences(REC, NAME)``) names the committed
   sequences whose chunk is absent. A missing chunk of a committed sequence is damage: report it, never use
   the fill values it reads as.

A writer killed by ``kill -9`` may leave the chunk it was writing half written: the recorder writes each chunk
straight to its own name (no temporary, no rename: see Writing), past ``sequences_committed``, where no specgpu
reader looks; a reader that ignores the commit gets a checksum error there, not data. Metadata, ``done`` marks
and chunks written through zarr itself go to a ``*.partial`` temporary that is renamed into place; such leftovers
are never read, and :func:`remove_partial_chunks` deletes them (``specgpu batch`` does so in its output before
resuming it, and in the chunk folders of a source recording that no live writer holds).
"""

from __future__ import annotations

import hashlib
import itertools
import math
import os
import shutil
import time
import uuid
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from specgpu.io.chunks import (
    _COMPRESS_MIN_BYTES,
    _COMPRESS_SAMPLE_BYTES,
    COMPRESSIONS,
    DirectIO,
    _blosc,
    _chunk_bytes,
    checksum_codecs,
    encode_chunk,
    probe_write_rate,
    write_chunk,
)

__all__ = ["RECORDING_FORMAT", "RECORDING_VERSION", "ZarrRecorder", "Recording", "open_recording", "open_zarr_group",
           "patterns_hash", "sequence_bytes", "check_free_space", "refuse_existing", "missing_sequences",
           "remove_partial_chunks", "probe_write_rate", "check_write_rate", "COMPRESSIONS"]

RECORDING_FORMAT = "specgpu.recording"
RECORDING_VERSION = 1

#: What a recording may hold along time besides the raw frames (specgpu.pipeline.decoder_outputs.STREAM_OUTPUTS).
_OUTPUTS = ("coefficients", "cube", "XYZ", "Lab", "dE", "sigma", "sigma_rms", "dE_sigma")
#: Channel dimension and channel names of each output.
CHANNELS = {"XYZ": ("X", "Y", "Z"), "Lab": ("L", "a", "b")}


def patterns_hash(plan) -> str:
    """SHA-256 of a plan's DMD patterns: two plans with the same patterns light the same frames (a new estimator
    may re-process a recording; other patterns may not)."""
    n = np.ascontiguousarray(np.asarray(plan.patterns, np.int64))
    return hashlib.sha256(repr(n.shape).encode() + n.tobytes()).hexdigest()





def write_buffer_bytes() -> int:
    """Bytes of writes the operating system holds in memory before it makes writers wait for the disk (Linux: the
    dirty-page background threshold); 0 where unknown."""
    try:
        background = int(Path("/proc/sys/vm/dirty_background_bytes").read_text())
        if background > 0:
            return background
        ratio = int(Path("/proc/sys/vm/dirty_background_ratio").read_text())
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024 * ratio // 100
    except (OSError, ValueError):
        pass
    return 0


def check_write_rate(path, bytes_per_s: float, seconds: float, *, what: str = "the recording", rate=None,
                     buffer_bytes=None) -> float:
    """Refuse (one line, with the figures) a recording of ``bytes_per_s`` for ``seconds`` that the disk holding
    ``path`` cannot keep up with: its measured write rate (``rate``, else :func:`probe_write_rate`) is below the
    need and the backlog over the recording outgrows what can wait in memory (``buffer_bytes``: for the recorder's
    direct-I/O writes, what the stream itself buffers; else :func:`write_buffer_bytes`, the system's write buffer
    a buffered writer has), so the stream would drop frames. Returns the measured rate (bytes/s)."""
    rate = probe_write_rate(path) if rate is None else float(rate)
    if rate >= bytes_per_s:
        return rate
    buffered = write_buffer_bytes() if buffer_bytes is None else int(buffer_bytes)
    backlog = (bytes_per_s - rate) * float(seconds)
    if backlog > buffered:
        raise OSError(f"{path}: the disk cannot keep up: {what} needs {bytes_per_s / 1e6:.0f} MB/s but a write "
                      f"probe measured {rate / 1e6:.0f} MB/s, so {backlog / 1e9:.2f} GB would pile up over "
                      f"{float(seconds):g} s where {buffered / 1e9:.2f} GB can wait in memory, and frames would be "
                      "dropped; record fewer outputs, fewer seconds or to a faster disk (or --no-disk-check)")
    return rate


def refuse_existing(path) -> Path:
    """A recording is written into a new folder only: one line naming ``path`` when it exists."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: already exists; a recording is never appended to or mixed with another run "
                              "(choose a new --out)")
    return path


def sequence_bytes(shapes: dict, *, frames_shape=None) -> int:
    """Bytes one sequence takes in a recording: ``shapes`` maps output -> ((H, W[, C]), dtype) (as
    :meth:`specgpu.pipeline.sequence_decoder.SequenceDecoder.shapes`); ``frames_shape`` (K, H, W) adds the raw
    uint16 frames."""
    total = 0
    for name, (shape, dtype) in shapes.items():
        if name != "mask":
            total += int(np.prod(shape)) * np.dtype(dtype).itemsize
    if frames_shape is not None:
        total += int(np.prod(frames_shape)) * 2
    return total + 4096  # ids, timestamps, checksums and metadata


def check_free_space(path, nbytes: int, *, what: str = "the recording") -> int:
    """Refuse (one line, with the figures) when the file system that will hold ``path`` has less than ``nbytes``
    free; returns the free bytes."""
    path = Path(path)
    probe = path
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if nbytes > free:
        raise OSError(f"{path}: {what} needs about {nbytes / 1e9:.2f} GB but only {free / 1e9:.2f} GB are free "
                      f"on {probe}; free some space or record less")
    return free


class ZarrRecorder:
    """A stream sink that records every result into a zarr v3 group (see the module docstring).

    Parameters
    ----------
    path : path
        The recording folder to create (``REC.zarr``); refused when it exists.
    plan : specgpu.planning.plans.Plan
        The plan streamed: its hash, calibration hash, patterns hash and output wavelengths are recorded.
    outputs : sequence of str, optional
        Which of the stream's outputs to record (default all).
    frames : bool
        Also record the raw frames of each sequence (what ``specgpu batch`` re-processes).
    basis : numpy.ndarray, optional
        (B, m) output basis of the ``coefficients`` output (``cube = coefficients @ basis.T``).
    metadata : mapping, optional
        JSON values stored under the ``metadata`` attribute.
    disk_rate : float, optional
        Bytes/s the disk takes (:func:`probe_write_rate`). With it each array's compression is chosen on the first
        sequence by measurement: per chunk, the encode time plus the encoded bytes at ``disk_rate``, least of none
        and :data:`COMPRESSIONS`. Without it (and without ``compression``) chunks are stored uncompressed.
    compression : str, optional
        ``"none"`` or a label of :data:`COMPRESSIONS`: that codec for every array of at least 256 KiB a chunk,
        with no measurement.
    threads : int
        Writer threads (the chunks of a sequence are encoded and written in parallel).
    direct : bool
        Write chunks of 1 MiB or more with direct I/O where the file system has it (:func:`write_chunk`).

    Attributes
    ----------
    label : str
        Its name in a stream's reports.
    committed : int
        Sequences whose every chunk is written (what a reader sees).
    failed : str or None
        The error that stopped the recording.
    """

    label = "recording"

    def __init__(self, path: str | os.PathLike[str], plan, *, outputs=None, frames: bool = False, basis=None,
                 metadata: dict | None = None, grow: int = 64, disk_rate: float | None = None,
                 compression: str | None = None, threads: int = 4, direct: bool = True):

        import zarr

        if compression is not None and compression != "none" and compression not in COMPRESSIONS:
            raise ValueError(f"compression must be none or one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        if disk_rate is not None and not (math.isfinite(float(disk_rate)) and float(disk_rate) > 0):
            raise ValueError(f"disk_rate must be a positive number of bytes/s, got {disk_rate!r}")
        self.grow = max(1, int(grow))
        self.disk_rate = None if disk_rate is None else float(disk_rate)
        self.compression = compression
        self.compression_report: dict = {}
        self._encoders: dict = {}
        self._paths: dict = {}
        self._direct = DirectIO(direct)
        self._pool = ThreadPoolExecutor(max_workers=max(1, int(threads)), thread_name_prefix="specgpu-recorder")

        self.path = refuse_existing(path)
        self.plan = plan
        self.outputs = None if outputs is None else tuple(outputs)
        self.record_frames = bool(frames)
        self.basis = None if basis is None else np.asarray(basis, np.float64)
        self.committed = 0
        self.failed: str | None = None
        self._arrays: dict = {}
        self.recording_id = uuid.uuid4().hex  # tells this recording from any other later put at the same path
        # the group is created with its attributes, and every later change is one write of zarr.json
        # (update_attributes): zarr's attrs.update writes the file once per key, and a crash between two of those
        # writes left a recording with some of its attributes (sequences_committed missing: unreadable)
        self.group = zarr.open_group(str(self.path), mode="w-", zarr_format=3, attributes={
            "format": RECORDING_FORMAT, "version": RECORDING_VERSION, "recording_id": self.recording_id,
            "plan_hash": plan.hash,
            "plan_method": plan.method, "calibration": plan.calibration, "patterns_hash": patterns_hash(plan),
            "K": int(plan.K), "outputs": [], "frames": self.record_frames, "sequences_committed": 0,
            "status": "recording", "metadata": dict(metadata or {})})

    # ---- layout ----------------------------------------------------------------------------------------------
    def _create(self, result) -> None:
        g, K = self.group, int(self.plan.K)
        arrays = {k: v for k, v in result.arrays.items() if self.outputs is None or k in self.outputs}
        h, w = next(iter(arrays.values())).shape[:2] if arrays else result.frames.shape[1:]

        def make(name, tail, dtype, dims, fill, attrs=None):
            sample = sample_of.get(name)
            encoder, codec = self._choose_compression(name, sample, dtype) if sample is not None else (None, None)
            self._encoders[name] = encoder
            self._arrays[name] = g.create_array(
                name, shape=(0, *tail), chunks=(1, *tail), dtype=dtype,
                compressors=([codec] if codec is not None else []) + checksum_codecs(), fill_value=fill,
                dimension_names=("time", *dims), attributes=attrs or {}, config={"write_empty_chunks": True})

        sample_of = dict(arrays)
        if self.record_frames and result.frames is not None:
            sample_of["frames"] = result.frames

        make("time", (), "float64", (), np.nan, {"units": "s", "long_name": "exposure start of the first frame"})
        make("cycle", (), "int64", (), -1)
        make("frame_id", (K,), "int64", ("pattern",), -1)
        make("timestamp_s", (K,), "float64", ("pattern",), np.nan, {"units": "s"})
        g.create_array("pattern", data=np.arange(K, dtype=np.int64), dimension_names=("pattern",),
                       compressors=checksum_codecs())
        for name, arr in arrays.items():
            fill = np.nan if np.issubdtype(arr.dtype, np.floating) else 0
            if name == "cube":
                wl = np.asarray(self.plan.output_wavelengths, np.float64)
                if self.plan.output == "reflectance" and wl.size == arr.shape[-1]:
                    dim = "wavelength"
                    g.create_array("wavelength", data=wl, dimension_names=("wavelength",),
                                   compressors=checksum_codecs(), attributes={"units": "nm"})
                    attrs = {"quantity": "reflectance", "wavelength_units": "nm"}
                else:
                    dim, attrs = "output", {"channels": [str(s) for s in self.plan.output_labels]}
                make(name, arr.shape, arr.dtype, ("y", "x", dim), fill, attrs)
            elif name == "coefficients":
                make(name, arr.shape, arr.dtype, ("y", "x", "component"), fill,
                     {"long_name": "coefficients in the output basis (cube = coefficients @ basis.T)"})
                if self.basis is not None:
                    g.create_array("basis", data=self.basis, compressors=checksum_codecs(),
                                   dimension_names=("basis_wavelength", "component"))
                    wl = np.asarray(self.plan.output_wavelengths, np.float64)
                    if self.plan.output == "reflectance" and wl.shape == self.basis.shape[:1]:
                        # the basis's wavelengths: the coefficients make a reflectance cube without the plan
                        g.create_array("basis_wavelength", data=wl, dimension_names=("basis_wavelength",),
                                       compressors=checksum_codecs(), attributes={"units": "nm"})
            elif name == "sigma":
                make(name, arr.shape, arr.dtype, ("y", "x", "sigma_channel"), fill,
                     {"channels": [f"sigma_{label}" for label in self.plan.output_labels] + ["sigma_rms"],
                      "long_name": "standard deviation of each output, then their RMS"})
            elif name in CHANNELS:
                make(name, arr.shape, arr.dtype, ("y", "x", f"{name}_channel"), fill,
                     {"channels": list(CHANNELS[name])})
            else:
                make(name, arr.shape, arr.dtype, ("y", "x", *(f"{name}_channel",) * (arr.ndim - 2)), fill)
        if getattr(result, "white_gains", None) is not None:
            make("white_gains", (K,), "float64", ("pattern",), np.nan,
                 {"long_name": "reference white: measured / predicted output per pattern (decoder correction)"})
        if self.record_frames:
            if result.frames is None:
                raise ValueError(f"{self.path}: raw frames were asked for but the stream passes none")
            make("frames", tuple(result.frames.shape), "uint16", ("pattern", "y", "x"), 0, {"units": "DN"})
        g.update_attributes({"outputs": sorted(arrays), "height": int(h), "width": int(w),
                             "compression": self.compression_report})
        # each chunk's file: the array's folder and its chunk key around the sequence index (joined per write, so
        # a folder name with braces is taken as it is)
        for name, arr in self._arrays.items():
            key = arr.metadata.encode_chunk_key((0,) * arr.ndim)
            parts = key.split("/")
            assert parts[1] == "0", key  # "c/<time>/0/..." (the default chunk key encoding)
            self._paths[name] = (os.path.join(str(self.path), name, *parts[:1]), tuple(parts[2:]))

    def _choose_compression(self, name, sample, dtype):
        """(encoder, zarr codec) of array ``name`` from its first chunk ``sample``; (None, None) for none."""
        nbytes = int(np.asarray(sample).nbytes)
        measured = self.compression is None and self.disk_rate is not None
        if nbytes < _COMPRESS_MIN_BYTES or not (measured or self.compression in COMPRESSIONS):
            return None, None
        typesize = np.dtype(dtype).itemsize
        if self.compression is not None:
            self.compression_report[name] = {"codec": self.compression}
            return _blosc(self.compression, typesize)
        # measured on a 1 MiB slice of the chunk (scaled to the chunk): the measurement runs while the stream
        # does, so it must cost a few ms, not a compression of the whole chunk with each codec
        raw = _chunk_bytes(sample, dtype)
        part = raw[:max(typesize, (_COMPRESS_SAMPLE_BYTES // typesize) * typesize)]
        scale = nbytes / part.size
        costs = {"none": (nbytes / self.disk_rate, 1.0, None)}
        for label in COMPRESSIONS:
            encoder, _ = _blosc(label, typesize)
            seconds = []
            for _ in range(2):  # the first call pays for warming up
                t0 = time.perf_counter()
                size = len(encoder.encode(part))
                seconds.append(time.perf_counter() - t0)
            encode_s = min(seconds) * scale
            costs[label] = (encode_s + size * scale / self.disk_rate, part.size / size, encode_s)
        best = min(costs, key=lambda k: costs[k][0])
        self.compression_report[name] = {
            "codec": best, "disk_MB_s": round(self.disk_rate / 1e6, 1),
            **{f"{label}_ms": round(c[0] * 1e3, 2) for label, c in costs.items()},
            **{f"{label}_ratio": round(c[1], 3) for label, c in costs.items() if label != "none"}}
        return (None, None) if best == "none" else _blosc(best, typesize)

    # ---- the sink --------------------------------------------------------------------------------------------
    def write(self, result) -> None:
        if self.failed:
            raise OSError(f"{self.path}: the recording stopped on an earlier error ({self.failed})")
        try:
            if not self._arrays:
                self._create(result)
            i = self.committed
            values = {"time": float(result.timestamps_s[0]), "cycle": int(result.cycle),
                      "frame_id": np.asarray(result.frame_ids, np.int64),
                      "timestamp_s": np.asarray(result.timestamps_s, np.float64)}
            for name in self._arrays:
                if name in result.arrays:
                    values[name] = result.arrays[name]
            if self.record_frames:
                values["frames"] = result.frames
            if "white_gains" in self._arrays:
                if getattr(result, "white_gains", None) is None:
                    raise ValueError(f"{self.path}: a sequence came without the white gains its recording holds")
                values["white_gains"] = np.asarray(result.white_gains, np.float64)
            for name, arr in self._arrays.items():  # room for a block of sequences (a resize costs ~8 ms)
                if arr.shape[0] <= i:
                    arr.resize((i + self.grow, *arr.shape[1:]))
            # the chunks of one sequence are encoded and written concurrently, straight to their files;
            # list() waits for every one and re-raises the first error
            list(self._pool.map(lambda name: self._write_chunk(name, i, values[name]), self._arrays))
            self.committed = i + 1
            self.group.attrs["sequences_committed"] = self.committed  # the commit
        except Exception as exc:
            self.failed = f"{type(exc).__name__}: {exc}"
            self._trim()
            raise

    def _write_chunk(self, name: str, i: int, value) -> None:
        arr = self._arrays[name]
        value = np.asarray(value)
        if value.shape != arr.shape[1:]:
            raise ValueError(f"{self.path}/{name}: a sequence's chunk is {value.shape}, the recording holds "
                             f"{arr.shape[1:]}")
        head, tail = self._paths[name]
        write_chunk(os.path.join(head, str(int(i)), *tail), encode_chunk(value, arr.dtype, self._encoders.get(name)),
                    direct=self._direct)

    def _trim(self) -> None:
        """Drop a partly written sequence (best effort: the commit count already excludes it)."""
        for arr in self._arrays.values():
            try:
                if arr.shape[0] != self.committed:
                    arr.resize((self.committed, *arr.shape[1:]))
            except Exception:  # noqa: BLE001 (a full disk may refuse even this; readers trust the commit count)
                pass

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        self._trim()
        self.group.update_attributes({"status": "failed" if self.failed else "complete",
                                      "sequences_committed": self.committed,
                                      **({"error": self.failed} if self.failed else {})})
        consolidate(self.path)

    def mark_failed(self, reason: str) -> None:
        """The run that fed this recording failed (even after its sinks were closed, or before its first
        sequence): the recording says ``failed`` with the reason, never ``complete``; its committed sequences
        stay readable."""
        self.failed = self.failed or (str(reason).strip().splitlines() or ["failed"])[0]
        self._pool.shutdown(wait=True)
        self.group.update_attributes({"status": "failed", "error": self.failed,
                                      "sequences_committed": self.committed})
        consolidate(self.path)


def native(a):
    """``a`` in native byte order (zarr hands out explicit little-endian dtypes, which OpenImageIO refuses)."""
    a = np.asarray(a)
    if a.dtype.byteorder in ("=", "|"):
        return a
    native_dtype = a.dtype.newbyteorder("=")
    return a.view(native_dtype) if a.dtype == native_dtype else a.astype(native_dtype)


def consolidate(path) -> None:
    """Consolidate a group's metadata into its root document (xarray then opens it from one read)."""
    import zarr

    with warnings.catch_warnings():  # zarr notes that consolidation is not (yet) in the v3 specification
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(str(path))


# ---------------------------------------------------------------------------------------------------- reading


@dataclass
class Recording:
    """A recording opened and checked; arrays are zarr arrays cut to the committed sequences."""

    path: Path
    attrs: dict
    group: object

    @property
    def sequences(self) -> int:
        return int(self.attrs["sequences_committed"])

    @property
    def K(self) -> int:
        return int(self.attrs["K"])

    def array(self, name: str):
        """The zarr array ``name`` (all of its sequences, committed or not: index below :attr:`sequences`)."""
        if name not in self.group:
            have = ", ".join(sorted(self.attrs.get("outputs", [])) + (["frames"] if self.attrs.get("frames") else []))
            raise ValueError(f"{self.path}: the recording has no {name!r} array (it holds {have or 'nothing'})")
        return self.group[name]

    def read(self, name: str, index) -> np.ndarray:
        """Committed sequence(s) ``index`` of array ``name``; a corrupt chunk, or a missing chunk of a committed
        sequence (zarr would read it as fill values), is a one-line error naming the recording, array and
        sequence."""
        arr = self.array(name)
        if _along_time(arr):
            first = index[0] if isinstance(index, tuple) else index
            try:
                wanted = range(arr.shape[0])[first]
            except (TypeError, IndexError):  # an index zarr itself will refuse or a fancy one: every sequence
                wanted = range(arr.shape[0])
            wanted = [i for i in ([wanted] if isinstance(wanted, int) else wanted) if i < self.sequences]
            missing = _missing_chunks(arr, wanted)
            if missing:
                more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
                raise ValueError(f"{self.path}/{name}: sequence {missing[0]}{more} is committed but its chunk "
                                 f"{chunk_keys(arr, missing[0])[0]} is missing; the recording is damaged there")
        try:
            return native(arr[index])
        except Exception as exc:  # noqa: BLE001 (zarr raises codec-specific errors)
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            # zarr's checksum error quotes both checksums as raw bytes, which say nothing to a reader
            why = ("its CRC32C checksum does not match its bytes" if "checksum" in detail.lower()
                   else f"{type(exc).__name__}: {detail}")
            raise ValueError(f"{self.path}/{name}: corrupt or unreadable chunk at sequence {index} ({why})") from None

    def missing(self, name: str) -> list[int]:
        """The committed sequences whose chunk of array ``name`` is not on disk (empty when it is whole)."""
        arr = self.array(name)
        return _missing_chunks(arr, range(min(self.sequences, arr.shape[0]))) if _along_time(arr) else []


def _along_time(arr) -> bool:
    names = getattr(arr.metadata, "dimension_names", None) or ()
    return bool(names) and names[0] == "time" and arr.chunks[0] == 1


def chunk_keys(arr, i: int) -> list[str]:
    """The store keys of sequence ``i``'s chunks of ``arr`` (one chunk along time per sequence)."""
    grid = [range(math.ceil(n / c)) for n, c in zip(arr.shape[1:], arr.chunks[1:])]
    return [arr.metadata.encode_chunk_key((i, *rest)) for rest in itertools.product(*grid)]


def _missing_chunks(arr, sequences) -> list[int]:
    """Which of ``sequences`` lack a chunk of ``arr`` in its store."""
    from zarr.core.sync import sync

    sequences = list(sequences)
    if not sequences:
        return []
    store, prefix = arr.store, f"{arr.path}/" if arr.path else ""
    if len(sequences) <= 4:
        present = {key for i in sequences for key in chunk_keys(arr, i)
                   if sync(store.exists(prefix + key))}
    else:  # one listing of the array's chunks, not one request per chunk

        async def listed():
            return {key[len(prefix):] async for key in store.list_prefix(prefix + "c")}

        present = sync(listed())
    return [i for i in sequences if not all(key in present for key in chunk_keys(arr, i))]


def missing_sequences(path, name: str) -> list[int]:
    """The committed sequences of recording ``path`` whose chunk of array ``name`` is not on disk (a reader that
    does not use :func:`open_recording` checks this before trusting the values; zarr reads a missing chunk as
    fill values)."""
    return open_recording(path).missing(name)


def remove_partial_chunks(path, *, chunks_only: bool = False) -> list[Path]:
    """Delete the ``*.partial`` files a writer killed mid-write left in the zarr group at ``path`` (zarr writes
    each file to such a temporary name and renames it; a leftover is never read and never completed). Call it only
    while no writer is running on ``path``; ``chunks_only`` keeps to the chunk folders (``ARRAY/c/...``), never the
    metadata a live writer may be renaming into place. Returns the files removed."""
    removed = []
    root = Path(path)
    for leftover in root.rglob("*.partial"):
        if chunks_only and "c" not in leftover.relative_to(root).parts[:-1]:
            continue
        if leftover.is_file():
            try:
                leftover.unlink()
                removed.append(leftover)
            except FileNotFoundError:
                pass
    return removed


def open_zarr_group(path, what: str, format_id: str, version: int):
    """Open a zarr v3 group read-only and check its format id and version.

    Parameters
    ----------
    path : path-like
        The group's folder.
    what : str
        What the group is, for the messages (``"recording"``, ``"batch output"``).
    format_id, version : str, int
        The ``format`` and ``version`` attributes the group must carry.

    Returns
    -------
    (zarr.Group, dict)
        The group and a copy of its attributes.

    Raises
    ------
    FileNotFoundError, ValueError
        One line naming the folder: it does not exist; not a zarr v3 group, another format or another version.
    """
    import zarr

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: {what} not found")
    try:
        group = zarr.open_group(str(path), mode="r", zarr_format=3)
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"{path}: not a zarr v3 {what} ({type(exc).__name__})") from None
    attrs = dict(group.attrs)
    if attrs.get("format") != format_id:
        raise ValueError(f"{path}: not a specgpu {what} (format {str(attrs.get('format'))[:40]!r})")
    if type(attrs.get("version")) is not int or attrs["version"] != version:
        raise ValueError(f"{path}: {what} version {str(attrs.get('version'))[:20]} is not supported "
                         f"(this specgpu reads {version})")
    return group, attrs


def open_recording(path: str | os.PathLike[str]) -> Recording:
    """Open a recording written by :class:`ZarrRecorder` and check its attributes and arrays.

    Parameters
    ----------
    path : str or os.PathLike
        The recording folder (``REC.zarr``).

    Returns
    -------
    Recording
        Its attributes (``attrs``), the number of committed sequences (``sequences``), the patterns per sequence
        (``K``); :meth:`Recording.read` gives the committed sequences of an array, checked chunk by chunk.

    Raises
    ------
    FileNotFoundError
        The folder does not exist.
    ValueError
        One line naming the folder: not a zarr v3 group, not a specgpu recording or of another version, bad
        attributes, an array missing or shorter than the committed sequences.

    Examples
    --------
    >>> import pathlib, tempfile, types
    >>> import numpy as np
    >>> from specgpu.io import ZarrRecorder, open_recording
    >>> plan = types.SimpleNamespace(hash="ab" * 32, method="symmetric", calibration="cd" * 32, K=4,
    ...                              patterns=np.eye(4, 3, dtype=int), output="reflectance",
    ...                              output_wavelengths=np.linspace(400.0, 700.0, 5),
    ...                              output_labels=("400", "475", "550", "625", "700"))
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "rec.zarr"
    >>> ZarrRecorder(path, plan, metadata={"scene": "demo"}).close()
    >>> recording = open_recording(path)
    >>> recording.sequences, recording.K, recording.attrs["status"], recording.attrs["metadata"]
    (0, 4, 'complete', {'scene': 'demo'})
    """
    path = Path(path)
    group, attrs = open_zarr_group(path, "recording", RECORDING_FORMAT, RECORDING_VERSION)
    n = attrs.get("sequences_committed")
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise ValueError(f"{path}: sequences_committed must be an integer >= 0, got {n!r}")
    outputs = attrs.get("outputs", [])
    if not isinstance(outputs, list) or not all(isinstance(o, str) and o in _OUTPUTS for o in outputs):
        raise ValueError(f"{path}: outputs must be a list of {', '.join(_OUTPUTS)}, got {str(outputs)[:80]}")
    if not isinstance(attrs.get("frames", False), bool):
        raise ValueError(f"{path}: frames must be true or false, got {str(attrs.get('frames'))[:40]}")
    K = attrs.get("K")
    if not isinstance(K, int) or isinstance(K, bool) or K < 1:
        raise ValueError(f"{path}: K must be an integer >= 1, got {str(K)[:40]}")
    for name in (*outputs, *(("frames",) if attrs.get("frames") else ())):
        if name not in group:
            if n == 0:  # arrays are made with the first sequence: a recording that stopped before has none
                continue
            raise ValueError(f"{path}: the {name!r} array is missing")
        if group[name].shape[0] < n:
            raise ValueError(f"{path}/{name}: holds {group[name].shape[0]} sequences but {n} are committed")
    return Recording(path, attrs, group)


def expected_sequences(seconds: float, frame_rate_hz: float, K: int) -> int:
    """Sequences a paced stream of ``seconds`` at ``frame_rate_hz`` delivers (for the free-space check)."""
    return int(math.ceil(float(seconds) * float(frame_rate_hz) / int(K))) + 1
