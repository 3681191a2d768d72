"""The motion-compensated pass of a stream of sequences set up once and kept on the device: the warped decoding
with the residual check (:mod:`specgpu.motion.residual`) run beside it, per sequence nothing built, nothing
allocated outside the memory pool and no sample read back.

:func:`warped_checked` is the translation case of :func:`specgpu.pipeline.moving_layers.recover_moving`'s
checked pass (every decoding of a global motion and of an object layer): one
:class:`~specgpu.engine.warp_map.PreparedWarp` writes the outputs (interleaved) and the samples of the frames the
check reads (planar, device only), then :class:`~specgpu.engine.residual.PreparedResidual` flags the pixels no
single reflectance explains in the pass's mask. Only the outputs and the mask are read back. The set-ups (the
kernels, the plan's matrices, the dark and flat field on the device) are kept per thread, keyed by what they were
made from, so the sequences of a stream, a recording or the layers of one sequence reuse them (a
:class:`PreparedWarp` holds kernel arguments of its own: one per thread, as the stream decodes on several); so is
the consistency check's noise floors' (:func:`noise_floor_set_up`).
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
import pyopencl as cl

from specgpu.core.numerics import live_gain
from specgpu.engine.kernels import to_device
from specgpu.engine.linear_map import LinearResult
from specgpu.engine.noise_floor import PreparedNoiseFloors
from specgpu.engine.residual import PreparedResidual
from specgpu.engine.runtime import get_queue
from specgpu.engine.warp_map import MAX_TRANSLATE_FRAMES, PreparedWarp

__all__ = ["SETUPS_KEPT", "kept_set_up", "noise_floor_set_up", "set_ups", "warped_checked"]

#: Set-ups kept per thread (the oldest dropped first): a stream's global pass and its object layers' passes
#: share one, its noise floors take another; a few more serve a recording decoded with several plans. Each holds
#: the dark and flat field on the device (and a device copy may hold its host array): a caller that makes a new dark
#: per call fills them all.
SETUPS_KEPT = 4

_local = threading.local()


def set_ups() -> dict:
    """This thread's kept set-ups (key -> (the set-up, weak references to the arrays it was made from))."""
    kept = getattr(_local, "kept", None)
    if kept is None:
        kept = _local.kept = {}
    return kept


def kept_set_up(key, arrays, make):
    """This thread's set-up under ``key`` (which names ``arrays`` by id), made from ``arrays`` (None entries
    allowed): the one kept by an earlier call while those arrays live, else ``make()``, kept (the oldest of
    :data:`SETUPS_KEPT` dropped first). Set-ups made from arrays since freed are dropped: their memory on the device
    goes with them, and their ids may name new arrays."""
    kept = set_ups()
    for stale in [k for k, (_, refs) in kept.items() if not _alive(refs)]:
        del kept[stale]
    entry = kept.get(key)
    if entry is not None and _alive(entry[1], arrays):
        return entry[0]
    made = make()
    try:  # held weakly: a set-up lives no longer than what it was made from
        refs = tuple(None if a is None else weakref.ref(a) for a in arrays)
    except TypeError:  # an input no weak reference can follow (a list): this set-up serves this call only
        return made
    if len(kept) >= SETUPS_KEPT:
        kept.pop(next(iter(kept)))
    kept[key] = (made, refs)
    return made


def _translations(shifts, K: int) -> bool:
    d = np.asarray(shifts)
    return d.shape == (K, 2) and bool(np.all(np.isfinite(d)))


def _set_up(queue, frames, A, dark, gain, read, residual, saturation):
    """The (warp, check, the check's flat field on the device) of these inputs: kept from an earlier call, or
    made and kept."""
    h, w = frames.shape[1:]
    key = (queue, frames.dtype.str, (h, w), A.shape, A.tobytes(), saturation, None if read is None else tuple(read),
           id(dark), id(gain), id(residual))

    def make():
        gain_dev = check_gain = None
        if gain is not None:  # the pass reads the live flat field; the check weighs the noise by the finite one
            live, finite = live_gain(gain), np.asarray(gain, np.float32)
            gain_dev = to_device(queue, live)
            check_gain = gain_dev if live is finite else to_device(queue, finite)
        N = len(residual.frames)
        warp = PreparedWarp(queue, frames.dtype, np.vstack([A, residual.rows]), (h, w), dark, gain_dev,
                            saturation=saturation, read=read,
                            outputs=[("y", A.shape[0], "interleaved"), ("samples", N, "planar")])
        nm = residual.noise
        check = PreparedResidual(queue, residual.project, residual.mismatch, gain_e_per_dn=nm.gain_e_per_dn,
                                 read_var_dn2=nm.read_var_dn2, light_rms=nm.light_rms,
                                 threshold=residual.threshold, has_gain=gain_dev is not None)
        return warp, check, check_gain

    return kept_set_up(key, (dark, gain, residual), make)


def noise_floor_set_up(queue, shape, dark, gain, noise, window: int = 9) -> PreparedNoiseFloors:
    """The consistency check's noise floors of one sensor (:class:`~specgpu.engine.noise_floor.PreparedNoiseFloors`:
    its dark level, flat field and read noise on the device), kept as the passes' set-ups are."""
    key = ("floors", queue, tuple(shape), int(window), noise.gain_e_per_dn, noise.read_var_dn2, id(dark), id(gain))
    return kept_set_up(key, (dark, gain), lambda: PreparedNoiseFloors(
        queue, shape, dark, gain, gain_e_per_dn=noise.gain_e_per_dn, read_var_dn2=noise.read_var_dn2,
        window=window))


def _alive(refs, objects=None) -> bool:
    """Whether every array a set-up was made from (weak references, None for none) still lives, and, given
    ``objects``, is that object."""
    got = [None if r is None else r() for r in refs]
    if objects is not None:
        return all(g is o for g, o in zip(got, objects))
    return all(g is not None or r is None for g, r in zip(got, refs))


def warped_checked(frames, A, shifts, dark, gain, read, residual, *, saturation=None,
                   device=None) -> LinearResult | None:
    """The checked warped pass of one sequence on the device (see the module notes): ``y`` (H, W, B) float32 and
    the mask, INCONSISTENT where the residual check flags a pixel; as
    :func:`specgpu.pipeline.moving_layers.recover_moving`'s pass with the samples' chi2 computed on the host.
    None where it does not apply (not one translation per frame, a dtype the prepared pass does not read, more
    frames than it samples): the caller takes the general path."""
    frames = np.asarray(frames)
    K = len(frames)
    n_read = K if read is None else len(read)
    if (frames.ndim != 3 or not _translations(shifts, K) or n_read > MAX_TRANSLATE_FRAMES
            or frames.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
            or (dark is not None and np.ndim(dark) != 2)):
        return None
    A = np.asarray(A, np.float64)
    queue = get_queue(device)
    warp, check, check_gain = _set_up(queue, frames, A, dark, gain, read, residual,
                          None if saturation is None else float(saturation))
    h, w = frames.shape[1:]
    out = warp.enqueue(to_device(queue, np.ascontiguousarray(frames).reshape(-1)), np.asarray(shifts, np.float32))
    check.enqueue(out["samples"], check_gain, out["mask"], h * w)
    y = np.empty((h, w, A.shape[0]), np.float32)
    mask = np.empty((h, w), np.uint8)
    cl.enqueue_copy(queue, y, out["y"], is_blocking=False)
    cl.enqueue_copy(queue, mask, out["mask"])  # blocking: the in-order queue has run everything before it
    return LinearResult(y, mask)
