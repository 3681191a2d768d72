"""The stream's per-sequence work, stage by stage, for its ``static`` and ``full`` paths, split into host time and
device time.

``static``: coefficients + XYZ + dE2000 through the device-resident decoder, as the stream's device thread and
sink thread run it (assembly, upload, the fused launches, read-back, the sink's NaN of saturated pixels).
``full``: the same outputs with ``--motion global --denoise --white-roi`` (the decoder's motion mode: the frames
corrected, the estimate, the warped pass, the consistency check and object layers, the white, the guided filter,
colour). Each stage of each sequence is timed three ways: its wall time with the queue finished at its end;
its *host* time on its thread's clock (``time.thread_time``: Python and NumPy on the calling thread); its
*device* time, the sum of the OpenCL profiling intervals of every kernel and copy it enqueued. What the wall time
holds beyond the two is waiting: for a shared CPU, for NumPy's BLAS threads, for the queue. A stage's times
exclude the stages timed inside it. Medians over sequences (the first, which builds kernels, left out).

Also counted: the kernel programs built (:func:`specgpu.engine.runtime.program_cache_size`) and the bytes the
memory pool took from the system after the first sequence (zero in a steady state).

    PYTHONPATH=. python tools/benchmarks/stream_full_profile.py --size 640x480 --sequences 8 \
        --json results/stream_full_profile.json
"""

from __future__ import annotations

import argparse
import json
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from specgpu.capture.assemble import SequenceAssembler
from specgpu.core.mask import Mask
from specgpu.engine.runtime import get_allocator, program_cache_size
from specgpu.pipeline import moving_layers, sequence_decoder
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.pipeline.twin_replay import stream_setup
from specgpu.planning import NoiseModel, smooth_prior, with_estimator
from specgpu.rig.scene import white_tile_roi

OUTPUTS = ("coefficients", "XYZ", "dE")


class Stages:
    """Exclusive wall, host and device seconds per stage of the sequence being timed: every kernel launch and copy
    enqueued while a stage is open is its device time (the events' profiling: the queue profiles)."""

    def __init__(self, queue):
        self.queue = queue
        self.stack = []  # [wall, host, events] of the stages open, their children's time accrued
        self.now = {}
        for attr in ("enqueue_nd_range_kernel", "enqueue_copy"):
            self._collect(attr)

    def _collect(self, attr):
        inner = getattr(cl, attr)

        def collected(*args, **kw):
            event = inner(*args, **kw)
            if self.stack and isinstance(event, cl.Event):
                self.stack[-1][2].append(event)
            return event

        setattr(cl, attr, collected)

    @contextmanager
    def stage(self, name):
        self.stack.append([0.0, 0.0, []])
        w0, h0 = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            self.queue.finish()  # the stage's device work is the stage's
            wall, host = time.perf_counter() - w0, time.thread_time() - h0
            child_wall, child_host, events = self.stack.pop()
            if self.stack:
                self.stack[-1][0] += wall
                self.stack[-1][1] += host
            device = sum(ev.profile.end - ev.profile.start for ev in events) * 1e-9
            w, h, d = self.now.setdefault(name, [0.0, 0.0, 0.0])
            self.now[name] = [w + wall - child_wall, h + host - child_host, d + device]

    def wrap(self, owner, attr, name):
        """Time every call of ``owner.attr`` as stage ``name`` (a module function or a method)."""
        inner = getattr(owner, attr)

        def timed(*args, **kw):
            with self.stage(name):
                return inner(*args, **kw)

        setattr(owner, attr, timed)

    def take(self):
        now, self.now = self.now, {}
        return now


def assemble(setup, count, held: int = 6):
    """The sequences of the first ``count`` * K replayed frames, and each sequence's assembly (wall, host) seconds
    (no device work), timed as the stream assembles: ``held`` sequences alive at once (its result buffers), so a new
    sequence's memory is one freed before, not fresh pages."""
    K = setup.plan.K
    count = min(count, len(setup.infos) // K)  # the recording once: its frame ids do not repeat

    def frames():
        i = 0
        while True:
            yield setup.frames[i % len(setup.infos)], setup.infos[i % len(setup.infos)]
            i += 1

    asm, source, alive, seconds = SequenceAssembler(K), frames(), [], []
    for _ in range(count):
        t0, h0 = time.perf_counter(), time.thread_time()
        seq = None
        while seq is None:
            seq = asm.push(*next(source))
        seconds.append((time.perf_counter() - t0, time.thread_time() - h0))
        alive = [*alive[1 - held:], seq]
    asm, source = SequenceAssembler(K), frames()
    seqs = []
    while len(seqs) < count:
        seq = asm.push(*next(source))
        if seq is not None:
            seqs.append(seq)
    return seqs, seconds


def sink(stages, arrays):
    with stages.stage("sink"):  # the stream's sink thread: saturated pixels NaN in every map
        saturated = (arrays["mask"] & Mask.SATURATED).astype(bool) if arrays["mask"].any() else None
        if saturated is not None:
            for name, arr in arrays.items():
                if name != "mask":
                    arr[saturated] = np.nan


def static_sequence(dec, stages, seq):
    q = dec.queue
    with stages.stage("upload"):
        flat = seq.frames.reshape(-1)
        buf = cl.Buffer(q.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=flat)
        frames = cla.Array(q, flat.shape, flat.dtype, data=buf)
    with stages.stage("kernels"):
        outs = dec.enqueue(frames)
    with stages.stage("read-back"):
        host = {}
        for name, (shape, dtype) in dec.device_shapes().items():
            host[name], _ = cl.enqueue_map_buffer(q, outs[name], cl.map_flags.READ | cl.map_flags.WRITE, 0, shape,
                                                  dtype, is_blocking=True)
    sink(stages, host)
    for arr in host.values():
        arr.base.release(q)


def full_sequence(dec, stages, seq):
    maps = dec.maps(seq.frames)
    for key in ("estimate", "layers", "white_gains"):
        maps.pop(key, None)
    sink(stages, maps)


def instrument_full(stages):
    """The motion mode's steps as stages (each a function the decoder calls, timed where it is looked up)."""
    stages.wrap(sequence_decoder.Corrections, "sensor", "correct")
    stages.wrap(moving_layers, "estimate_motion", "estimate")
    stages.wrap(moving_layers, "_warped", "warp")
    stages.wrap(moving_layers, "consistency", "check")
    stages.wrap(moving_layers, "decode_object_layers", "check")
    stages.wrap(moving_layers, "_recover", "check")  # what is left of it: flags grown, NaN set
    stages.wrap(SequenceDecoder, "warped_outputs", "white")  # what is left: the white's gains, its decoder's rows
    stages.wrap(SequenceDecoder, "filtered", "denoise")
    stages.wrap(SequenceDecoder, "smoothed", "sigma")  # with a sigma output: the filter's parts for the sigmas
    stages.wrap(SequenceDecoder, "_warped_sigmas", "sigma")
    stages.wrap(sequence_decoder, "lab_and_delta_E", "colour")  # its launch, the read-back in "outputs"
    stages.wrap(SequenceDecoder, "_moving_maps", "outputs")  # what is left: maps sliced, colour uploaded and read


def profile(case, setup, seqs, assembly_s, device, outputs=OUTPUTS):
    h, w = setup.frames.shape[1:]
    full = case == "full"
    dec = SequenceDecoder(setup.plan, setup.bundle, tuple(outputs), reference=setup.reference, device=device,
                          frame_shape=(h, w), white_roi=white_tile_roi(h, w) if full else None,
                          denoise=(DENOISE_RADIUS, DENOISE_EPS) if full else None,
                          motion="global" if full else "none")
    stages = Stages(dec.queue)
    if full:
        instrument_full(stages)
    pool = get_allocator(dec.queue)
    rows, built, grown = [], [], []
    for i, seq in enumerate(seqs):
        programs, managed = program_cache_size(), pool.managed_bytes
        t0 = time.perf_counter()
        (full_sequence if full else static_sequence)(dec, stages, seq)
        total = time.perf_counter() - t0
        row = stages.take()
        row["assembly"] = [*assembly_s[i], 0.0]
        row["total"] = [total + assembly_s[i][0], None, None]
        rows.append(row)
        built.append(program_cache_size() - programs)
        grown.append(pool.managed_bytes - managed)
    steady = rows[1:] or rows
    table = {}
    for name in rows[0]:
        med = [float(np.median([r[name][j] for r in steady if name in r])) * 1e3 if rows[0][name][j] is not None
               else None for j in range(3)]
        table[name] = {"wall_ms": med[0], "host_ms": med[1], "device_ms": med[2]}
    return {"case": case, "stages": table, "programs_built_after_first": int(sum(built[1:])),
            "pool_bytes_grown_after_first": int(sum(grown[1:])), "sequences": len(seqs)}


def _ms(v) -> str:
    return f"{v:8.2f}" if v is not None else f"{'':>8}"


def format_table(report) -> str:
    lines = []
    for prof in report["profiles"]:
        lines.append(f"{prof['case']}: ms per sequence, median of {prof['sequences'] - 1} (after the first); "
                     f"programs built after the first {prof['programs_built_after_first']}, pool bytes grown "
                     f"{prof['pool_bytes_grown_after_first']}")
        lines.append(f"  {'stage':<10} {'wall':>8} {'host':>8} {'device':>8}   (ms)")
        for name, t in prof["stages"].items():
            lines.append(f"  {name:<10} {_ms(t['wall_ms'])} {_ms(t['host_ms'])} {_ms(t['device_ms'])}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480", help="WxH of the frames")
    ap.add_argument("--sequences", type=int, default=8, help="sequences timed per case (the first not counted)")
    ap.add_argument("--cases", default="static,full")
    ap.add_argument("--device", default=None)
    ap.add_argument("--outputs", default=",".join(OUTPUTS), help="the decoder's outputs (the bench's full case adds "
                    "sigma_rms)")
    ap.add_argument("--json", default=None, help="write the table here as JSON")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    setup = stream_setup(w, h, white_tile=0.99)
    outputs = [o.strip() for o in args.outputs.split(",") if o.strip()]
    if {"sigma", "sigma_rms", "dE_sigma"} & set(outputs):  # the bench's noise model (its sigma cases)
        plan = with_estimator(setup.plan, setup.bundle, "projection", noise=NoiseModel.from_rig(
            setup.description, setup.plan.exposure_s), prior=smooth_prior(np.arange(400.0, 700.0 + 1e-9, 5.0)))
        setup = replace(setup, plan=plan)
    seqs, assembly_s = assemble(setup, args.sequences)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    profiles = [profile(c, setup, seqs, assembly_s, args.device, outputs) for c in cases]
    report = {"width": w, "height": h, "K": setup.plan.K, "outputs": outputs, "profiles": profiles}
    print(format_table(report))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
