"""Zarr v3 chunks written by the recorder itself: encoded (little-endian bytes, an optional Blosc compressor, the
CRC32C zarr checks) and written straight to their files, with direct I/O for large chunks where the file system has
it.

These are the same bytes zarr would write for the chunk, at about a third of zarr's memory traffic: zarr fills a new
chunk, copies the data in and copies it again to append the checksum. :func:`encode_chunk` gives the parts,
:func:`write_chunk` writes them to one chunk file, :func:`write_sequence_chunk` writes the chunk of one sequence of
an array. Chunks of 1 MiB and more go through direct I/O (:class:`DirectIO` remembers whether the file system takes
it) as 8 MiB slices in flight at once; :func:`probe_write_rate` measures how fast the disk takes such chunks.
"""

from __future__ import annotations

import errno
import mmap
import os
import statistics
import struct
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import google_crc32c
import numpy as np

__all__ = [
    "COMPRESSIONS", "DirectIO", "checksum_codecs", "encode_chunk", "write_chunk", "write_sequence_chunk",
    "probe_write_rate",
]


def checksum_codecs():
    from zarr.codecs import Crc32cCodec

    return [Crc32cCodec()]


#: Compressors a recording may use besides none: (cname, clevel, shuffle) of a Blosc codec, by label. Both are
#: cheap enough for video rate; which pays back on a given disk is measured (ZarrRecorder, disk_rate).
COMPRESSIONS = {"blosc-lz4": ("lz4", 5, "bitshuffle"), "blosc-zstd": ("zstd", 1, "bitshuffle")}
#: Chunks smaller than this are never compressed (nothing to win against the per-chunk cost).
_COMPRESS_MIN_BYTES = 1 << 18
#: Bytes of a chunk each compressor is measured on.
_COMPRESS_SAMPLE_BYTES = 1 << 20


def _blosc(label: str, typesize: int):
    """(numcodecs encoder, zarr codec for the array's metadata) of the compression ``label``, encoding the same
    bytes (zarr's BloscCodec wraps the same numcodecs encoder)."""
    from numcodecs import Blosc
    from zarr.codecs import BloscCodec

    cname, clevel, shuffle = COMPRESSIONS[label]
    encoder = Blosc(cname=cname, clevel=clevel, shuffle={"shuffle": Blosc.SHUFFLE, "bitshuffle": Blosc.BITSHUFFLE}[
        shuffle], blocksize=0, typesize=typesize)
    return encoder, BloscCodec(cname=cname, clevel=clevel, shuffle=shuffle, typesize=typesize, blocksize=0)


def _chunk_bytes(value, dtype) -> np.ndarray:
    """The little-endian bytes of one chunk (zarr's ``bytes`` codec) as a flat uint8 view where no copy is needed."""
    a = np.ascontiguousarray(value, dtype=np.dtype(dtype).newbyteorder("<"))
    return a.reshape(-1).view(np.uint8)


def encode_chunk(value, dtype, encoder=None) -> tuple:
    """One chunk as zarr v3 stores it with the recorder's codecs: the bytes (compressed by ``encoder`` when given),
    then their CRC32C (4 bytes, little-endian). Returns (flat uint8 data, checksum bytes): no concatenating copy."""
    data = _chunk_bytes(value, dtype)
    if encoder is not None:
        data = np.frombuffer(encoder.encode(data), np.uint8)
    return data, struct.pack("<I", google_crc32c.value(data))


#: Chunks of at least this many bytes are written with direct I/O where the file system has it (below: buffered).
_DIRECT_MIN_BYTES = 1 << 20
#: Alignment of direct I/O (memory address, file offset and length), and the size of each thread's staging buffer.
_ALIGN = 4096
_STAGE_BYTES = 8 << 20
_staging = threading.local()


def _stage() -> np.ndarray:
    """This thread's page-aligned staging buffer (direct I/O writes from aligned memory only)."""
    buf = getattr(_staging, "buf", None)
    if buf is None:

        _staging.map = mmap.mmap(-1, _STAGE_BYTES)  # anonymous maps are page aligned
        buf = _staging.buf = np.frombuffer(_staging.map, np.uint8)
    return buf


def _write_all(fd: int, view) -> None:
    view = memoryview(view).cast("B")
    while view:
        view = view[os.write(fd, view):]


def _pwrite_all(fd: int, view, offset: int) -> None:
    view = memoryview(view).cast("B")
    while view:
        done = os.pwrite(fd, view, offset)
        view, offset = view[done:], offset + done


_SLICES: list = []
_SLICES_LOCK = threading.Lock()


def _slice_pool():
    """Threads writing the 8 MiB slices of one large chunk at once (a direct write waits for the disk: several in
    flight keep it busy). Slices never submit work of their own, so writer threads may wait on them."""
    with _SLICES_LOCK:
        if not _SLICES:

            _SLICES.append(ThreadPoolExecutor(max_workers=4, thread_name_prefix="specgpu-chunk-slices"))
        return _SLICES[0]


def _write_direct(fd: int, data: np.ndarray, tail: bytes) -> None:
    """``data`` (flat uint8) then ``tail`` through a file opened with O_DIRECT: whole aligned 8 MiB slices written
    in parallel at their offsets, straight from ``data`` when it is aligned (else through each thread's staging
    buffer), then the last block zero-padded and the file cut back to its length."""
    n = data.size - data.size % _ALIGN
    aligned = data.ctypes.data % _ALIGN == 0

    def piece(start):
        k = min(_STAGE_BYTES, n - start)
        if aligned:
            _pwrite_all(fd, data[start:start + k], start)
        else:
            stage = _stage()
            stage[:k] = data[start:start + k]
            _pwrite_all(fd, stage[:k], start)

    starts = range(0, n, _STAGE_BYTES)
    if len(starts) > 1:
        list(_slice_pool().map(piece, starts))  # waits for every slice, re-raises the first error
    else:
        for start in starts:
            piece(start)
    stage = _stage()
    last = data[n:].tobytes() + tail
    padded = -(-len(last) // _ALIGN) * _ALIGN
    stage[:padded] = 0
    stage[:len(last)] = np.frombuffer(last, np.uint8)
    _pwrite_all(fd, stage[:padded], n)
    os.ftruncate(fd, data.size + len(tail))


class DirectIO:
    """Whether the recording's file system takes O_DIRECT (decided by the first large chunk; then fixed)."""

    def __init__(self, enabled: bool = True):
        self.state = None if enabled and hasattr(os, "O_DIRECT") else False


def write_chunk(path: str, parts, *, direct: DirectIO | None = None) -> None:
    """Write one chunk file (its folders made as needed): no temporary file and no sync. A chunk is written once,
    before the commit count includes its sequence, so a write cut short is beyond the commit and never read.

    ``parts`` is (flat uint8 data, bytes after it). With ``direct`` a chunk of at least 1 MiB is written with
    direct I/O (O_DIRECT): from the process's memory to the disk, with none of the copy into the page cache and
    write-back that cost more CPU than the whole stream on a small machine; a file system without it (tmpfs)
    falls back to buffered writes, once and for all."""
    data, tail = parts
    use_direct = direct is not None and direct.state is not False and data.size >= _DIRECT_MIN_BYTES
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_BINARY", 0)  # Windows: no newline translation
    made = False
    while True:
        try:
            fd = os.open(path, flags | (os.O_DIRECT if use_direct else 0), 0o666)
            break
        except FileNotFoundError:
            if made:
                raise
            os.makedirs(os.path.dirname(path), exist_ok=True)
            made = True
        except OSError as exc:
            if not use_direct or exc.errno != errno.EINVAL:
                raise
            direct.state, use_direct = False, False  # no O_DIRECT on this file system
    try:
        if use_direct:
            try:
                _write_direct(fd, data, tail)
                direct.state = True
                return
            except OSError as exc:
                if exc.errno != errno.EINVAL or direct.state:
                    raise
                direct.state = False  # opened, but the writes are refused: buffered from now on
                os.close(fd)
                fd = -1  # closed: never closed again below (the number may be another thread's file by then)
                fd = os.open(path, flags, 0o666)
        _write_all(fd, data)
        _write_all(fd, tail)
    finally:
        if fd >= 0:
            os.close(fd)


def _endian(codec) -> str | None:
    """A zarr BytesCodec's byte order as text: an ``Endian`` enum up to zarr 3.1, a plain string from 3.2 on."""
    endian = codec.endian
    return getattr(endian, "value", endian)


def _fast_encoder(array):
    """(True, Blosc encoder or None) when ``array``'s codecs are ones :func:`encode_chunk` writes (little-endian
    bytes, optionally Blosc, then CRC32C) and it lives in a local folder; (False, None) otherwise."""
    from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec
    from zarr.storage import LocalStore

    codecs = list(array.metadata.codecs) if array.metadata.zarr_format == 3 else []
    if not isinstance(array.store_path.store, LocalStore) or len(codecs) not in (2, 3) \
            or not isinstance(codecs[0], BytesCodec) or not isinstance(codecs[-1], Crc32cCodec) \
            or _endian(codecs[0]) not in (None, "little"):
        return False, None
    if len(codecs) == 2:
        return True, None
    if not isinstance(codecs[1], BloscCodec):
        return False, None
    config = codecs[1].to_dict()["configuration"]
    label = next((k for k, (cname, clevel, shuffle) in COMPRESSIONS.items()
                  if (cname, clevel, shuffle) == (config["cname"], config["clevel"], config["shuffle"])), None)
    if label is None or config.get("blocksize", 0) != 0:
        return False, None
    return True, _blosc(label, int(config["typesize"]))[0]


def write_sequence_chunk(array, index: int, value, *, direct: DirectIO | None = None) -> None:
    """``array[index] = value`` for a zarr v3 array with one chunk per sequence along its first axis, written as
    the recorder writes its chunks (:func:`encode_chunk`, :func:`write_chunk`: the same bytes as zarr, at a third
    of its memory traffic, large chunks with direct I/O); arrays with other codecs or stores go through zarr."""
    ok, encoder = _fast_encoder(array)
    if not ok or array.chunks[1:] != array.shape[1:] or array.chunks[0] != 1:
        array[index] = value
        return
    value = np.broadcast_to(np.asarray(value), array.shape[1:])
    key = array.metadata.encode_chunk_key((int(index),) + (0,) * (array.ndim - 1))
    path = os.path.join(str(array.store_path.store.root), *array.store_path.path.split("/"), *key.split("/"))
    write_chunk(path, encode_chunk(value, array.dtype, encoder), direct=direct)


def probe_write_rate(path, nbytes: int = 64 << 20, *, repeats: int = 3, max_seconds: float = 2.0,
                     direct: bool = True) -> float:
    """Bytes/s the file system that will hold ``path`` takes a recording's large chunks at: ``nbytes`` written in
    8 MiB blocks as the recorder writes them (direct I/O where the file system has it, else buffered) and synced
    to the disk, the median of ``repeats`` (at most about ``max_seconds`` in all). The probe file is a hidden
    temporary one next to ``path``, always removed."""
    probe = Path(path)
    while not probe.exists():
        probe = probe.parent
    block = mmap.mmap(-1, _STAGE_BYTES)  # page aligned, as direct I/O needs
    block.write(np.random.default_rng(0).integers(0, 256, _STAGE_BYTES, dtype=np.uint8).tobytes())  # incompressible
    use_direct = direct and hasattr(os, "O_DIRECT")
    rates = []
    t_end = time.perf_counter() + max_seconds
    for _ in range(max(1, int(repeats))):
        fd, name = tempfile.mkstemp(prefix=".specgpu-write-probe-", dir=probe)
        try:
            if use_direct:
                os.close(fd)
                try:
                    fd = os.open(name, os.O_WRONLY | os.O_DIRECT)
                except OSError as exc:
                    if exc.errno != errno.EINVAL:
                        raise
                    use_direct = False
                    fd = os.open(name, os.O_WRONLY)
            t0, written = time.perf_counter(), 0
            while written < nbytes:
                _write_all(fd, block)
                written += _STAGE_BYTES
                if time.perf_counter() > t_end:
                    break
            getattr(os, "fdatasync", os.fsync)(fd)  # macOS has fsync only
            rates.append(written / max(time.perf_counter() - t0, 1e-9))
        finally:
            os.close(fd)
            os.unlink(name)
        if time.perf_counter() > t_end:
            break
    block.close()
    return float(statistics.median(rates))
