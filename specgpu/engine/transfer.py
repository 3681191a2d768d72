"""Host <-> device transfers for NumPy-in / NumPy-out calls on discrete devices: pinned staging, row chunks.

A discrete GPU moves pageable NumPy memory over its bus at a fraction of the rate it moves page-locked (pinned)
memory (measured on an H100: 10-17 GB/s pageable against 55 GB/s pinned). On such devices
(:func:`specgpu.engine.runtime.is_discrete`) :func:`linear_pipelined` therefore

* stages the input frames through pinned host buffers (``ALLOC_HOST_PTR``, mapped once, pooled per context),
* returns its outputs in pinned host memory of its own (NumPy arrays over mapped ``ALLOC_HOST_PTR`` buffers,
  which go back to the pool when the last view of them is dropped), so the read-back is one DMA into the result,
* splits the image along its first spatial axis into chunks that run on three queues (upload, compute,
  read-back), so chunk i + 1 is uploaded while chunk i is computed and chunk i - 1 read back.

CPU devices (PoCL) and integrated GPUs share host memory: they keep the direct path (no staging, no chunks).
``SPECGPU_TRANSFER=pinned|direct`` forces either on any device (CI runs the pinned path on PoCL this way).
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.engine import kernels
from specgpu.engine.runtime import get_allocator, is_discrete, override

__all__ = ["MODES", "transfer_mode", "pinned_empty", "linear_pipelined"]

ENV_TRANSFER = "SPECGPU_TRANSFER"
MODES = ("direct", "pinned")
CHUNK_BYTES = 64 << 20  # output bytes per chunk: large enough to amortise a launch, small enough to overlap
STAGING_SLOTS = 2  # input staging buffers in flight (double buffering)


def transfer_mode(device: cl.Device, mode: str | None = None) -> str:
    """"pinned" on discrete devices, "direct" elsewhere; ``mode`` or SPECGPU_TRANSFER overrides."""
    chosen = override(mode, "transfer", ENV_TRANSFER, MODES, "transfer mode")
    return chosen or ("pinned" if is_discrete(device) else "direct")


# ------------------------------------------------------------------------------------------------ pinned pool


class _Block:
    """One pinned host buffer, mapped once for its lifetime (its host pointer is what transfers use)."""

    def __init__(self, queue: cl.CommandQueue, nbytes: int):
        flags = cl.mem_flags.ALLOC_HOST_PTR | cl.mem_flags.READ_WRITE
        self.nbytes = nbytes
        self.buffer = cl.Buffer(queue.context, flags, nbytes)
        self.host, _ = cl.enqueue_map_buffer(queue, self.buffer, cl.map_flags.READ | cl.map_flags.WRITE, 0,
                                             (nbytes,), np.uint8, is_blocking=True)


class PinnedPool:
    """Pinned host blocks of one context, reused by size (a fresh pinned allocation costs far more than a copy:
    the driver page-locks every page)."""

    def __init__(self, queue: cl.CommandQueue, keep_bytes: int = 8 << 30):
        self.queue = queue
        self.keep_bytes = keep_bytes
        self.free: dict[int, list[_Block]] = {}
        self.lock = threading.Lock()

    @staticmethod
    def _bucket(nbytes: int) -> int:
        return 1 << max(12, (max(nbytes, 1) - 1).bit_length())  # powers of two from 4 KiB

    def take(self, nbytes: int) -> _Block:
        size = self._bucket(nbytes)
        with self.lock:
            blocks = self.free.get(size)
            if blocks:
                return blocks.pop()
        return _Block(self.queue, size)

    def give(self, block: _Block) -> None:
        with self.lock:
            held = sum(b.nbytes for blocks in self.free.values() for b in blocks)
            if held + block.nbytes <= self.keep_bytes:
                self.free.setdefault(block.nbytes, []).append(block)

    def held_bytes(self) -> int:
        with self.lock:
            return sum(b.nbytes for blocks in self.free.values() for b in blocks)


_pools: dict[cl.Context, PinnedPool] = {}
_queues: dict[cl.Context, tuple[cl.CommandQueue, cl.CommandQueue]] = {}
_lock = threading.Lock()


def pinned_pool(queue: cl.CommandQueue) -> PinnedPool:
    with _lock:
        pool = _pools.get(queue.context)
        if pool is None:
            pool = _pools[queue.context] = PinnedPool(queue)
        return pool


def _side_queues(queue: cl.CommandQueue) -> tuple[cl.CommandQueue, cl.CommandQueue]:
    """An upload and a read-back queue beside the compute queue: in-order queues serialise, three overlap."""
    with _lock:
        pair = _queues.get(queue.context)
        if pair is None:
            pair = _queues[queue.context] = (cl.CommandQueue(queue.context, queue.device),
                                             cl.CommandQueue(queue.context, queue.device))
        return pair


class _Lease:
    """The base of a NumPy array over a pinned block: the block returns to its pool when the array and every
    view of it are gone."""

    def __init__(self, pool: PinnedPool, block: _Block, shape, dtype):
        self.__array_interface__ = {
            "data": (block.host.ctypes.data, False), "shape": tuple(shape), "typestr": np.dtype(dtype).str,
            "version": 3,
        }
        self.block = block
        weakref.finalize(self, pool.give, block)


def pinned_empty(queue: cl.CommandQueue, shape, dtype) -> np.ndarray:
    """An uninitialised NumPy array in pinned host memory of ``queue``'s context (pooled)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    pool = pinned_pool(queue)
    return np.asarray(_Lease(pool, pool.take(nbytes), shape, dtype))


# --------------------------------------------------------------------------------------------- the pipeline


def _rows_per_chunk(rows: int, row_out_bytes: int, chunk_bytes: int) -> int:
    return max(1, min(rows, chunk_bytes // max(row_out_bytes, 1)))


def linear_pipelined(queue, frames: np.ndarray, A: np.ndarray, *, dark=None, dark_per_frame=False, gain=None,
                     out_dtype=np.float32, out_layout: int = 0, want_mask: bool = False, saturation=None,
                     chunk_bytes: int | None = None):
    """:func:`specgpu.engine.kernels.launch_linear` for host frames (K, R, ...) with host results, through pinned
    staging and row chunks.

    ``dark`` ((R, ...) or (K, R, ...)) and ``gain`` ((R, ...)) are host arrays already validated. Returns
    (y, mask): y (B, R, ...) planar or (R, ..., B) interleaved, mask (R, ...) or None, both NumPy arrays in pinned
    memory.
    """
    K = frames.shape[0]
    spatial = frames.shape[1:]
    B = A.shape[0]
    out_dtype = np.dtype(out_dtype)
    rows = spatial[0]
    row_px = int(np.prod(spatial[1:], dtype=np.int64))
    n = rows * row_px
    y = pinned_empty(queue, (*spatial, B) if out_layout else (B, *spatial), out_dtype)
    mask = pinned_empty(queue, spatial, np.uint8) if want_mask else None
    if n == 0:
        return y, mask
    step = _rows_per_chunk(rows, row_px * B * out_dtype.itemsize, chunk_bytes or CHUNK_BYTES)
    up_q, down_q = _side_queues(queue)
    pool = pinned_pool(queue)
    alloc = get_allocator(queue)
    frames3 = frames.reshape(K, rows, row_px)
    y_host = y.reshape(rows * row_px * B) if out_layout else y.reshape(B, rows * row_px)
    isz = out_dtype.itemsize
    staging = [pool.take(K * step * row_px * frames.dtype.itemsize) for _ in range(STAGING_SLOTS)]
    staged: list[cl.Event | None] = [None] * STAGING_SLOTS
    keep = []  # device buffers of chunks in flight: a pooled buffer must not be reused before its read-back
    reads = []
    try:
        for index, r0 in enumerate(range(0, rows, step)):
            r1 = min(rows, r0 + step)
            m = (r1 - r0) * row_px
            slot = index % STAGING_SLOTS
            if staged[slot] is not None:
                staged[slot].wait()  # the upload that last read this staging buffer is done
            block = staging[slot]
            chunk = block.host[: K * m * frames.dtype.itemsize].view(frames.dtype).reshape(K, r1 - r0, row_px)
            np.copyto(chunk, frames3[:, r0:r1])
            frames_dev = cla.empty(queue, (K * m,), frames.dtype, allocator=alloc)
            up = cl.enqueue_copy(up_q, frames_dev.data, chunk, is_blocking=False)
            staged[slot] = up
            dark_dev = gain_dev = None
            if dark is not None:
                d = dark.reshape(K if dark_per_frame else 1, rows, row_px)[:, r0:r1]
                dark_dev = kernels.to_device(queue, np.ascontiguousarray(d, np.float32).reshape(-1))
            if gain is not None:
                gain_dev = kernels.to_device(queue, np.ascontiguousarray(
                    gain.reshape(rows, row_px)[r0:r1], np.float32).reshape(-1))
            cl.enqueue_barrier(queue, wait_for=[up])  # the compute queue waits for this chunk's upload only
            out_dev, mask_dev = kernels.launch_linear(queue, frames_dev, A, n=m, dark=dark_dev,
                                                      dark_per_frame=dark_per_frame, gain=gain_dev,
                                                      out_dtype=out_dtype, out_layout=out_layout,
                                                      want_mask=want_mask, saturation=saturation)
            done = cl.enqueue_marker(queue)
            keep.append((frames_dev, dark_dev, gain_dev, out_dev, mask_dev))
            if out_layout:
                reads.append(cl.enqueue_copy(down_q, y_host[r0 * row_px * B: r1 * row_px * B], out_dev.data,
                                             is_blocking=False, wait_for=[done]))
            else:  # B plane segments of m pixels -> rows r0..r1 of every plane: one rectangular copy
                reads.append(cl.enqueue_copy(
                    down_q, y_host, out_dev.data, buffer_origin=(0, 0, 0), host_origin=(r0 * row_px * isz, 0, 0),
                    region=(m * isz, B, 1), buffer_pitches=(m * isz, 0), host_pitches=(n * isz, 0),
                    is_blocking=False, wait_for=[done]))
            if want_mask:
                reads.append(cl.enqueue_copy(down_q, mask.reshape(-1)[r0 * row_px: r1 * row_px], mask_dev.data,
                                             is_blocking=False, wait_for=[done]))
        cl.wait_for_events(reads)
    finally:
        up_q.finish()
        down_q.finish()
        for block in staging:
            pool.give(block)
    return y, mask
