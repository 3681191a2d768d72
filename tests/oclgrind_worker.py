"""Runs specgpu's kernels on the Oclgrind device for tests/engine/test_oclgrind.py, in a process of its own (the ICD
loader reads OCL_ICD_VENDORS and Oclgrind its OCLGRIND_* checks once, at start).

    python oclgrind_worker.py cases VARIANT [CASE ...]   every case (or the named ones) in kernel variant VARIANT
    python oclgrind_worker.py race                       the channels-last tile without its barrier
    python oclgrind_worker.py vector_bool                the reduced mask-flag kernel (tests/data/oclgrind_defects.cl)
    python oclgrind_worker.py shuffle KERNEL             one of its reduced shuffle kernels
    python oclgrind_worker.py min_vector_scalar          its reduced integer min of a vector and a scalar
    python oclgrind_worker.py offset_write               its copy of a buffer written from the host at an offset

Before each case it writes ``@@case NAME`` to stderr, so the parent can tell which case an Oclgrind report (also
written to stderr) belongs to; the results go to stdout as one JSON object per line: the case, the error of each
output against the float64 reference (specgpu.engine.selftest.compare) and its tolerance.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

SHAPE = (9, 11)  # 99 pixels: two work-groups of 64 (the second partial), not a multiple of 8 or 16 pixels
N = SHAPE[0] * SHAPE[1]
DATA = Path(__file__).resolve().parent / "data"


def _compare(errors, tolerances, name, got, want, kind, tol):
    from specgpu.engine.selftest import compare

    err, message = compare(name, np.asarray(got), np.asarray(want), kind)
    errors[name] = err if not message else message
    tolerances[name] = tol


def _frames(rng, K, dtype, high):
    if np.dtype(dtype).kind == "f":
        return rng.uniform(0, high, (K, *SHAPE)).astype(dtype)
    return rng.integers(0, high + 1, (K, *SHAPE)).astype(dtype)


def _linear_case(seed, *, K, B, dtype, high, layout, out_dtype, dark=None, gain=False, saturation=None,
                 nonfinite=False):
    from reference import linear_ref, mask_ref

    from specgpu.engine.linear_map import apply_linear

    def run():
        rng = np.random.default_rng(seed)
        frames = _frames(rng, K, dtype, high)
        if nonfinite:
            frames[1, 2, 3] = np.nan
            frames[0, 5, 7] = np.inf
            frames[2, 8, 10] = -np.inf
        A = rng.normal(0, 1e-2, (B, K))
        d = None if dark is None else rng.uniform(0, 5, (K, *SHAPE) if dark == "per frame" else SHAPE).astype(
            np.float32)
        g = rng.uniform(0.9, 1.1, SHAPE).astype(np.float32) if gain else None
        res = apply_linear(frames, A, d, g, out_dtype=out_dtype, layout=layout, saturation=saturation,
                           return_mask=saturation is not None or nonfinite, device="oclgrind")
        y, mask = (res.y, res.mask) if isinstance(res, tuple) else (res, None)
        errors, tolerances = {}, {}
        want = linear_ref(frames, A, d, g, layout)
        _compare(errors, tolerances, "y", y, want, "range", 1e-3 if out_dtype == "float16" else 1e-5)
        if mask is not None:
            want_mask = mask_ref(frames, saturation)
            assert want_mask.any(), "the case must flag some pixels"
            _compare(errors, tolerances, "mask", mask, want_mask, "abs", 0)
        return errors, tolerances

    return run


@contextlib.contextmanager
def _no_tile():
    """The "gpu" variant's channels-last launch without its local-memory tile (a work-item per output element),
    which the engine takes where the tile does not fit the device's local memory."""
    from specgpu.engine import kernels as engine

    saved = engine._TILE_LOCAL_MAX
    engine._TILE_LOCAL_MAX = 0
    try:
        yield
    finally:
        engine._TILE_LOCAL_MAX = saved


def _per_element_case():
    inner = _linear_case(6, K=3, B=5, dtype=np.uint16, high=4095, layout="interleaved", out_dtype="float32",
                         dark="single", gain=True, saturation=4000.0)

    def run():
        with _no_tile():
            return inner()

    return run


def _sqrt_case():
    """The stream's standard-deviation output: sqrt(max(A (o - dark) * gain + c, 0)) from one prepared launch."""
    import pyopencl as cl
    from reference import linear_ref, mask_ref

    from specgpu.engine import kernels as engine
    from specgpu.engine.runtime import get_queue

    def run():
        queue = get_queue("oclgrind")
        rng = np.random.default_rng(7)
        K, B = 4, 9
        frames = _frames(rng, K, np.uint16, 1023)
        A = rng.uniform(0.5, 1.5, (B, K))
        offsets = rng.uniform(1, 2, B)
        dark = rng.uniform(0, 5, SHAPE).astype(np.float32)
        gain = rng.uniform(0.9, 1.1, SHAPE).astype(np.float32)
        errors, tolerances = {}, {}
        for layout, name in ((1, "y_interleaved"), (0, "y_planar")):
            launch = engine.prepare_linear(queue, np.uint16, A, n=N, dark=engine.to_device(queue, dark.ravel()),
                                           gain=engine.to_device(queue, gain.ravel()), out_layout=layout,
                                           want_mask=True, saturation=1000.0, sqrt_offsets=offsets)
            out = launch.enqueue(engine.to_device(queue, frames.reshape(-1)).data)
            y = np.empty(B * N, np.float32)
            mask = np.empty(N, np.uint8)
            cl.enqueue_copy(queue, y, out["out"])
            cl.enqueue_copy(queue, mask, out["mask"])
            lin = linear_ref(frames, A, dark, gain, "interleaved" if layout else "planar")
            want = np.sqrt(np.maximum(lin + (offsets if layout else offsets[:, None, None]), 0))
            _compare(errors, tolerances, name, y.reshape(want.shape), want, "range", 1e-5)
            _compare(errors, tolerances, f"mask_{name[2:]}", mask.reshape(SHAPE), mask_ref(frames, 1000.0), "abs", 0)
        return errors, tolerances

    return run


def _random_lab(rng):
    from reference import random_Lab

    return random_Lab(rng, SHAPE).astype(np.float32)


def _xyz_to_lab_case():
    from reference import XYZ_to_Lab_ref

    from specgpu.engine.colorimetry import XYZ_to_Lab

    def run():
        rng = np.random.default_rng(8)
        xyz = rng.uniform(0.0005, 1.0, (*SHAPE, 3)).astype(np.float32)
        xyz[0] *= 0.005  # below (24/116)^3 of the white: the linear part of f(t)
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "Lab", XYZ_to_Lab(xyz, "D65", device="oclgrind"), XYZ_to_Lab_ref(xyz),
                 "abs", 1e-4)
        return errors, tolerances

    return run


def _delta_e_case(method, single=False):
    from reference import delta_E_ref

    from specgpu.engine.colorimetry import delta_E

    def run():
        rng = np.random.default_rng(9)
        lab2 = _random_lab(rng)
        lab1 = lab2[4, 5] if single else (lab2 + rng.normal(0, 3, lab2.shape)).astype(np.float32)
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "dE", delta_E(lab1, lab2, method=method, device="oclgrind"),
                 delta_E_ref(lab1, lab2, method), "abs", 1e-3 if method == "CIE 2000" else 2e-5)
        return errors, tolerances

    return run


def _fused_case(method, single=False):
    from reference import XYZ_to_Lab_ref, delta_E_ref, linear_ref, mask_ref

    from specgpu.engine.colorimetry import frames_to_delta_E

    def run():
        rng = np.random.default_rng(10)
        K = 5
        frames = _frames(rng, K, np.uint16, 4095)
        M = rng.uniform(0, 1.0 / (K * 4095), (3, K))
        dark = rng.uniform(0, 5, SHAPE).astype(np.float32)
        gain = rng.uniform(0.9, 1.1, SHAPE).astype(np.float32)
        reference = _random_lab(rng)
        reference = reference[2, 2] if single else reference
        res = frames_to_delta_E(frames, M, reference, method=method, dark=dark, gain=gain, saturation=4000.0,
                                return_XYZ=True, return_Lab=True, return_mask=True, device="oclgrind")
        xyz = linear_ref(frames, M, dark, gain, "interleaved")
        lab = XYZ_to_Lab_ref(xyz)
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "XYZ", res.XYZ, xyz, "range", 1e-5)
        _compare(errors, tolerances, "Lab", res.Lab, lab, "abs", 5e-4)
        _compare(errors, tolerances, "dE", res.delta_E, delta_E_ref(reference, lab, method), "abs", 1e-3)
        _compare(errors, tolerances, "mask", res.mask, mask_ref(frames, 4000.0), "abs", 0)
        return errors, tolerances

    return run


def _delta_e_sigma_case():
    """The first-order dE2000 standard deviation kernel against specgpu.planning.uncertainty.delta_E_sigma."""
    import pyopencl as cl

    from specgpu.core.spectra import white_point_XYZ
    from specgpu.engine import kernels as engine
    from specgpu.engine.runtime import get_queue
    from specgpu.planning import delta_E_sigma

    def run():
        queue = get_queue("oclgrind")
        rng = np.random.default_rng(11)
        xyz = rng.uniform(0.0005, 0.95, (N, 3))
        xyz[:10] *= 0.005
        R = rng.normal(0, 1e-3, (N, 3, 3))
        cov = R @ np.transpose(R, (0, 2, 1))
        const = np.diag([1e-7, 2e-7, 3e-7])
        pairs = [(i, j) for i in range(3) for j in range(i, 3)]
        six = np.stack([cov[:, i, j] for i, j in pairs], axis=-1).astype(np.float32)
        launch = engine.prepare_delta_E_sigma(queue, white_point_XYZ("D65"), const, n=N)
        out = launch.enqueue(engine.to_device(queue, xyz.astype(np.float32).reshape(-1)).data,
                             inputs={1: engine.to_device(queue, six.reshape(-1)).data})
        got = np.empty(N, np.float32)
        cl.enqueue_copy(queue, got, out["dE_sigma"])
        full = np.empty((N, 3, 3))
        for m, (i, j) in enumerate(pairs):
            full[:, i, j] = full[:, j, i] = six[:, m]
        want = delta_E_sigma(xyz.astype(np.float32), full + const, "D65")
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "dE_sigma", got, want, "range", 2e-4)
        return errors, tolerances

    return run


def _motion(rng, K, kind):
    """Per-frame motion of ``kind`` on SHAPE: (K, 2) translations, (K, 2, 3) affine maps or a (K, 2, H, W) flow,
    reaching a pixel or two outside the field."""
    h, w = SHAPE
    if kind == "translate":
        return rng.uniform(-1.6, 1.6, (K, 2))
    if kind == "affine":
        maps = np.tile(np.eye(2, 3), (K, 1, 1))
        angle = rng.uniform(-0.05, 0.05, K)
        maps[:, 0, 0] = maps[:, 1, 1] = np.cos(angle)
        maps[:, 0, 1], maps[:, 1, 0] = -np.sin(angle), np.sin(angle)
        maps[:, :, 2] = rng.uniform(-1.2, 1.2, (K, 2))
        return maps
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([np.stack([1.5 * np.sin(xx / 3.0 + k), np.cos(yy / 2.0 - k)]) for k in range(K)])


def _warp_case(kind):
    from reference import linear_warp_ref

    from specgpu.core.mask import Mask
    from specgpu.engine.warp_map import apply_linear_warped

    def run():
        rng = np.random.default_rng({"translate": 21, "affine": 22, "flow": 23, "strips": 24}[kind])
        K, B = 4, 5
        if kind == "strips":
            # translations the two-pass path runs as vectors along strips of rows (the upper source row held from
            # the row above) on most of a 21 x 35 field: six strips, the last partial, rows ending within a step of
            # 8; one frame whole pixels (its right and lower taps of weight zero), one sample saturated
            shape = (21, 35)
            frames = rng.integers(0, 4000, (K, *shape)).astype(np.uint16)
            saturated = [(2, 9, 12), (3, 4, 20)]  # frame, row, column
            for k, r, c in saturated:
                frames[k, r, c] = 4095
            motion = np.array([[0.0, 0.0], [1.25, 0.5], [0.6, 1.75], [1.0, 1.0]])
        else:
            shape = SHAPE
            frames = _frames(rng, K, np.uint16, 4095)
            motion = _motion(rng, K, kind)
        A = rng.normal(0, 1e-2, (B, K))
        dark = rng.uniform(0, 5, shape).astype(np.float32)
        gain = rng.uniform(0.9, 1.1, shape).astype(np.float32)
        got = apply_linear_warped(frames, A, motion, dark, gain, return_mask=True, device="oclgrind",
                                  saturation=4095.0 if kind == "strips" else None)
        want, outside = linear_warp_ref(frames, A, np.asarray(motion, np.float32), dark, gain)
        errors, tolerances = {}, {}
        inside = ~outside
        _compare(errors, tolerances, "y", got.y[inside], want[inside], "abs", 1e-3)
        _compare(errors, tolerances, "outside", ((got.mask & Mask.OUTSIDE) > 0).astype(np.float32),
                 outside.astype(np.float32), "abs", 0.0)
        if kind == "strips":  # the saturated sample flags the outputs whose taps read it with a weight above zero
            near = np.zeros(shape, bool)
            for k, r, c in saturated:
                dx, dy = motion[k]
                for ty in {int(np.floor(dy)), int(np.ceil(dy))}:
                    for tx in {int(np.floor(dx)), int(np.ceil(dx))}:
                        near[r - ty, c - tx] = True
            _compare(errors, tolerances, "saturated", ((got.mask & 1) > 0).astype(np.float32),
                     near.astype(np.float32), "abs", 0.0)
        return errors, tolerances

    return run


def _warp_groups_case(shape):
    """The translation path as the stream prepares it (specgpu.engine.warp_map.PreparedWarp): float frames with a
    NaN and an inf (one at the field's corner, read by clamped taps), four of five frames read from one device
    buffer, a dark per frame, a gain with a dead pixel, frames shifted by sub-pixels, whole pixels and one axis'
    whole pixels, and the outputs in two groups (interleaved, planar), on ``shape``: 21 x 35, or 5 x 270 (two
    work-items along a row, the second ending within a step of 8). The outputs that read no flagged sample against
    the float64 reference; the mask and the NaNs against the per-pixel kernel's (a uniform flow), which the other
    warp cases check."""
    import pyopencl as cl
    from reference import linear_warp_ref

    from specgpu.core.mask import Mask
    from specgpu.engine.kernels import to_device
    from specgpu.engine.runtime import get_queue
    from specgpu.engine.warp_map import PreparedWarp, apply_linear_warped

    def run():
        queue = get_queue("oclgrind")
        rng = np.random.default_rng(25)
        K_in = 5
        h, w = shape
        read = [3, 0, 4, 1]
        frames = rng.uniform(0, 100, (K_in, *shape)).astype(np.float32)
        frames[0, h // 2, w // 2] = np.nan
        frames[4, 0, w - 1] = np.inf
        A = rng.normal(0, 1e-2, (5, K_in))
        dark = rng.uniform(0, 5, (K_in, *shape)).astype(np.float32)
        gain = rng.uniform(0.9, 1.1, shape).astype(np.float32)
        gain[h // 3, w // 5] = np.nan
        shifts = np.zeros((K_in, 2))
        shifts[read] = [[0.7, -1.2], [0.0, 0.0], [1.0, 0.4], [-1.5, 0.25]]
        warp = PreparedWarp(queue, np.float32, A, shape, dark, gain, saturation=99.0, read=read,
                            outputs=[("a", 3, "interleaved"), ("b", 2, "planar")])
        out = warp.enqueue(to_device(queue, frames.reshape(-1)), shifts)
        a, b, mask = np.empty((h, w, 3), np.float32), np.empty((2, h, w), np.float32), np.empty(shape, np.uint8)
        for buf, host in ((out["a"], a), (out["b"], b), (out["mask"], mask)):
            cl.enqueue_copy(queue, host, buf)
        y = np.concatenate([a, np.moveaxis(b, 0, -1)], axis=-1)
        flow = np.broadcast_to(shifts[:, :, None, None], (K_in, 2, h, w))
        exact = apply_linear_warped(frames, A, flow, dark, gain, saturation=99.0, read=read, return_mask=True,
                                    device="oclgrind")
        sel = frames[read]
        want, outside = linear_warp_ref(np.nan_to_num(sel, nan=0, posinf=0), A[:, read],
                                        shifts[read].astype(np.float32), dark[read], np.nan_to_num(gain, nan=1e30))
        clean = (mask == 0) & (np.abs(want) < 1e20).all(axis=-1)  # no flag, no dead pixel read
        assert clean.sum() > 0.5 * h * w and (mask & 1).any() and (mask & 2).any() and (mask & 4).any()
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "y", y[clean], want[clean], "abs", 1e-3)
        _compare(errors, tolerances, "mask", mask, exact.mask, "abs", 0)
        _compare(errors, tolerances, "nan", np.isnan(y).astype(np.float32), np.isnan(exact.y).astype(np.float32),
                 "abs", 0.0)
        _compare(errors, tolerances, "outside", ((mask & Mask.OUTSIDE) > 0).astype(np.float32),
                 outside.astype(np.float32), "abs", 0.0)
        return errors, tolerances

    return run


def _check_errors(textured, worst, grads, motion, window, own, floor=None):
    from specgpu.engine.consistency import consistency_maps_numpy

    textured_ref, worst_ref = consistency_maps_numpy(grads, motion, window=window, own=own, floor=floor)
    assert (worst_ref < 0.9).any() and textured_ref.any(), "the case must have pixels that disagree"
    if floor is not None:
        unfloored = consistency_maps_numpy(grads, motion, window=window, own=own)[1]
        assert (unfloored != worst_ref).any(), "the case's floor must decide some frames"
    errors, tolerances = {}, {}
    _compare(errors, tolerances, "worst", worst, worst_ref, "abs", 1e-3)
    _compare(errors, tolerances, "textured", textured.astype(np.float32), textured_ref.astype(np.float32), "abs", 0.0)
    return errors, tolerances


@contextlib.contextmanager
def _counting_strips():
    """The names of the consistency kernels launched inside, in order."""
    from specgpu.engine import kernels as engine

    names = []
    launch = engine.launch_range

    def counting(queue, kernel, *args):
        names.append(kernel.function_name)
        return launch(queue, kernel, *args)

    engine.launch_range = counting
    try:
        yield names
    finally:
        engine.launch_range = launch


def _consistency_case(kind, floor=False):
    """The check of gradient images given as one array (uploaded in one write: see the offset-write test), own = 1
    so that frames count and the undecided lists fill: translations, affine maps or a flow with a 5-pixel window;
    "window9" a 9-pixel window (the row sums by swizzles) on 21 x 35 pixels; ``floor``: with a noise floor per frame
    and pixel about the local variances (sampled where each frame saw the pixel)."""
    from specgpu.engine.consistency import consistency_maps

    def run():
        rng = np.random.default_rng({"translate": 31, "affine": 32, "flow": 33, "window9": 34}[kind] + 10 * floor)
        K = 5
        shape = (21, 35) if kind == "window9" else SHAPE
        grads = rng.uniform(0.0, 1.0, (K, *shape)).astype(np.float32)
        window = 9 if kind == "window9" else 5
        motion = rng.uniform(-1.6, 1.6, (K, 2)) if kind == "window9" else _motion(rng, K, kind)
        floors = rng.uniform(0.0, 0.15, (K, *shape)).astype(np.float32) if floor else None
        textured, worst = consistency_maps(grads, motion, window=window, own=1.0, floor=floors, device="oclgrind")
        return _check_errors(textured, worst, grads, motion, window, 1.0, floors)

    return run


def _consistency_misled_case():
    """Strips of 8 rows, a sample of 2 strips of 2 rows holding all the texture: some frame's median is outside the
    sample's bracket, and the strips run again with every value kept (runs: how many more or fewer than 2)."""
    from specgpu.engine import consistency as check

    def run():
        rng = np.random.default_rng(35)
        K, shape = 4, (24, 11)
        saved = check._ROWS, check._SAMPLE_ROWS, check._SAMPLE_STRIPS
        check._ROWS, check._SAMPLE_ROWS, check._SAMPLE_STRIPS = 8, 2, 2
        try:
            grads = rng.uniform(0.0, 0.3, (K, *shape)).astype(np.float32)
            for row in (6, 7, 18, 19):  # the sampled rows: strips 3 and 9 of 12
                grads[:, row] += rng.uniform(0.0, 6.0, (K, shape[1])).astype(np.float32)
            grads[1, 10:16, 2:8] = rng.uniform(0.0, 3.0, (6, 6))
            motion = rng.uniform(-1.2, 1.2, (K, 2))
            with _counting_strips() as launched:
                textured, worst = check.consistency_maps(grads, motion, window=5, own=1.0, device="oclgrind")
        finally:
            check._ROWS, check._SAMPLE_ROWS, check._SAMPLE_STRIPS = saved
        errors, tolerances = _check_errors(textured, worst, grads, motion, 5, 1.0)
        _compare(errors, tolerances, "runs", np.float32(launched.count("consistency_strips")), np.float32(2), "abs",
                 0.0)
        return errors, tolerances

    return run


def _gradient_case(dtype, dark):
    """engine.gradients.gradient_images against the host's gradient_image: a flat field with a dead pixel, one
    dark frame or one per frame."""
    from specgpu.engine.gradients import gradient_images
    from specgpu.motion.images import gradient_image

    def run():
        rng = np.random.default_rng(41 if dark == "single" else 42)
        K = 3
        frames = _frames(rng, K, dtype, 4095 if dtype == np.uint16 else 1000.0)
        d = rng.uniform(0, 5, (K, *SHAPE) if dark == "per frame" else SHAPE).astype(np.float32)
        g = rng.uniform(0.9, 1.1, SHAPE).astype(np.float32)
        g[4, 6] = np.nan
        got = gradient_images(frames, d, g, device="oclgrind").get()
        want = np.stack([gradient_image(f, d[k] if d.ndim == 3 else d, g) for k, f in enumerate(frames)])
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "gradients", got, want, "range", 1e-5)
        return errors, tolerances

    return run


def _consistency_frames_case():
    """engine.consistency.consistency_from_frames: the gradient images made on the device and the check's samples
    scaled by each frame's 1 / mean (SCALED), against the host's check of the host's images."""
    from specgpu.engine.consistency import consistency_from_frames
    from specgpu.motion.images import gradient_image

    def run():
        rng = np.random.default_rng(43)
        K = 4
        frames = _frames(rng, K, np.uint16, 4095)
        dark = rng.uniform(0, 5, SHAPE).astype(np.float32)
        motion = rng.uniform(-1.6, 1.6, (K, 2))
        textured, worst = consistency_from_frames(frames, motion, dark, window=5, own=1.0, device="oclgrind")
        grads = np.stack([gradient_image(f, dark) for f in frames])
        return _check_errors(textured, worst, grads, motion, 5, 1.0)

    return run


def _guided_case(shape, r, strip, nonfinite):
    """engine.guided's three passes against the reference's float64 guided filter (windows clipped to the image),
    strips short enough that work-items start inside the image; a NaN in the image and an inf in the guide, whose
    windows come out NaN and leave the others as the reference of the clean inputs."""
    import pyopencl.array as cla
    from reference import guided_filter_numpy

    from specgpu.engine.guided import guided_filter_device
    from specgpu.engine.runtime import get_queue

    def run():
        rng = np.random.default_rng(sum(shape) + r)
        H, W, C = shape
        g = rng.uniform(0.2, 1.0, (H, W)).astype(np.float32)
        p = (g[..., None] * rng.uniform(0.2, 1.0, C) + rng.normal(0, 0.05, shape)).astype(np.float32)
        want = guided_filter_numpy(p, g, r, 1e-3)
        if nonfinite:
            p[2, 3, 0], g[H - 2, W - 1] = np.nan, np.inf
            for (y, x), channels in (((2, 3), 0), ((H - 2, W - 1), slice(None))):
                want[max(y - 2 * r, 0):y + 2 * r + 1, max(x - 2 * r, 0):x + 2 * r + 1, channels] = np.nan
        queue = get_queue("oclgrind")
        got = guided_filter_device(queue, cla.to_device(queue, p), cla.to_device(queue, g), r, 1e-3, strip=strip)
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "q", got.get(), want, "range", 1e-4)
        return errors, tolerances

    return run


def _registration_case(model):
    """engine.registration.register_gradients (the pyramid's halving, the coarse search, the steps of a translation
    or an affine map) on three analytic images 48 x 51 px (the smallest that halve once; a partial chunk of 8 and
    of 16 columns on both levels), each frame seeing the reference's point x at a known map M_k x: the maps within
    0.05 px. The search reaches 2 px per frame (5 x 5 shifts on the coarse level, the best one inside, so the
    parabola has both neighbours): the simulator's time goes with the shifts tried, and the cases move 1.35 px at
    most."""
    from specgpu.engine.registration import register_gradients

    def texture(x, y):
        return 2.0 + np.sin(0.31 * x + 0.2 * y) + np.cos(0.17 * x - 0.43 * y) + 0.5 * np.sin(0.53 * x + 0.11 * y + 1)

    def run():
        h, w = 48, 51
        maps = np.tile(np.eye(3), (3, 1, 1))
        maps[0, :2, 2], maps[2, :2, 2] = (-0.8, 0.45), (1.35, -0.6)
        if model == "affine":
            maps[2, :2, :2] = [[1.004, -0.006], [0.006, 1.004]]
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        images = []
        for M in maps:  # frame k at y shows the reference's point M_k^-1 y
            inv = np.linalg.inv(M)
            images.append(texture(inv[0, 0] * xx + inv[0, 1] * yy + inv[0, 2], inv[1, 0] * xx + inv[1, 1] * yy
                                  + inv[1, 2]))
        got = register_gradients(np.stack(images).astype(np.float32), 1, model=model, max_speed=2.0,
                                 device="oclgrind")
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
        errors = {"maps": float(np.abs(got.to_reference @ corners - maps @ corners).max())}
        return errors, {"maps": 0.05}

    return run


def _warped_variance_case(kind, shape=SHAPE):
    """engine.warped_variance (the outputs' variance at the warped samples: total, own and as the filter takes it,
    three channels) against the float64 per-frame variances of pipeline.moving_decode summed through the same
    weights: uint16 frames with an ambient frame, a flat field with a dead pixel, frames seen outside the field;
    translations on 9 x 35 px as well, where the "cpu" variant reads the taps of 8 pixels as vectors."""
    from types import SimpleNamespace

    from specgpu.engine.runtime import get_queue
    from specgpu.engine.warped_variance import PreparedWarpedVariance
    from specgpu.pipeline.moving_decode import _interpolation_correlation, warped_sample_variances

    def run():
        rng = np.random.default_rng(11)
        K, read = 4, [0, 1, 2, 3]
        frames = rng.integers(0, 4001, (K, *shape)).astype(np.uint16)
        dark = rng.uniform(50.0, 60.0, shape).astype(np.float32)
        gain = rng.uniform(0.9, 1.1, shape).astype(np.float32)
        gain[4, 5] = np.nan
        motion = _motion(rng, K, kind)
        weights = rng.uniform(0.0, 1.0, (3, K))
        noise = {"gain_e_per_dn": 2.0, "read_var_dn2": 5.0, "light_rms": 0.01}
        want = warped_sample_variances(frames, SimpleNamespace(params={"noise": noise}), dark, gain, motion,
                                       read=read, filtered=2, ambient=3)
        prep = PreparedWarpedVariance(get_queue("oclgrind"), shape, dark, gain, **noise)
        got = prep.channels(frames, motion, read, weights, ambient=3, own=True, corr=_interpolation_correlation(2))
        errors, tolerances = {}, {}
        for name, g, V in zip(("total", "own", "filtered"), got, want):
            _compare(errors, tolerances, name, g, np.tensordot(V, weights.T, axes=([0], [0])), "range", 1e-5)
        return errors, tolerances

    return run


def _noise_floor_case(shape):
    """engine.noise_floor (the check's noise floors: the column pass down strips, the row pass along spans, their
    partial last strip and span) against motion.consistency's NumPy floors: uint16 frames, a dark frame, a flat
    field with a NaN (read as 0)."""
    from specgpu.engine.runtime import get_queue
    from specgpu.motion.consistency import noise_floors, noise_floors_on_device
    from specgpu.planning.noise import NoiseModel

    def run():
        rng = np.random.default_rng(13)
        frames = rng.integers(0, 4001, (3, *shape)).astype(np.uint16)
        dark = rng.uniform(50.0, 60.0, shape).astype(np.float32)
        gain = rng.uniform(0.9, 1.1, shape).astype(np.float32)
        gain[2, 3] = np.nan
        noise = NoiseModel(gain_e_per_dn=2.0, read_var_dn2=5.0)
        want = noise_floors(frames, noise, dark, gain)
        got = noise_floors_on_device(frames, noise, dark, gain, device=get_queue("oclgrind")).get()
        errors, tolerances = {}, {}
        _compare(errors, tolerances, "floors", got, want, "range", 1e-5)
        return errors, tolerances

    return run


def cases() -> dict:
    """Every kernel entry and build variant the host launches, on small images (name -> callable returning
    (errors, tolerances)). The kernel variant (cpu / gpu) comes from SPECGPU_VARIANT."""
    return {
        "linear_u16_planar_f32_dark_gain_mask": _linear_case(
            1, K=5, B=9, dtype=np.uint16, high=4095, layout="planar", out_dtype="float32", dark="single",
            gain=True, saturation=4000.0),
        "linear_u16_planar_f16_gain": _linear_case(  # "cpu": the 16-pixel float16 entry
            2, K=4, B=5, dtype=np.uint16, high=4095, layout="planar", out_dtype="float16", gain=True,
            saturation=4000.0),
        "linear_u8_interleaved_f16_b9": _linear_case(  # "cpu": register transpose, last block shifted back
            3, K=3, B=9, dtype=np.uint8, high=255, layout="interleaved", out_dtype="float16", saturation=240.0),
        "linear_u16_interleaved_f32_b9_mask": _linear_case(  # "gpu": the local-memory tile
            4, K=3, B=9, dtype=np.uint16, high=4095, layout="interleaved", out_dtype="float32", dark="single",
            gain=True, saturation=4000.0),
        "linear_f32_interleaved_b3_perframe_dark_nonfinite": _linear_case(  # "cpu": strided stores (B < 8)
            5, K=4, B=3, dtype=np.float32, high=1000.0, layout="interleaved", out_dtype="float32",
            dark="per frame", saturation=990.0, nonfinite=True),
        "linear_u16_interleaved_per_element": _per_element_case(),
        "linear_sqrt": _sqrt_case(),
        "xyz_to_lab": _xyz_to_lab_case(),
        "delta_e_76": _delta_e_case("CIE 1976"),
        "delta_e_94": _delta_e_case("CIE 1994"),
        "delta_e_2000": _delta_e_case("CIE 2000"),
        "delta_e_2000_single_reference": _delta_e_case("CIE 2000", single=True),
        "fused_de76": _fused_case("CIE 1976"),
        "fused_de94": _fused_case("CIE 1994"),
        "fused_de2000": _fused_case("CIE 2000"),
        "fused_de2000_single_reference": _fused_case("CIE 2000", single=True),
        "delta_e_sigma": _delta_e_sigma_case(),
        **{f"warp_{kind}": _warp_case(kind) for kind in ("translate", "strips", "affine", "flow")},
        "warp_groups": _warp_groups_case((21, 35)),
        "warp_groups_wide": _warp_groups_case((5, 270)),
        **{f"consistency_{kind}": _consistency_case(kind) for kind in ("translate", "affine", "flow", "window9")},
        **{f"consistency_floor_{kind}": _consistency_case(kind, True) for kind in ("translate", "affine", "flow")},
        "consistency_misled": _consistency_misled_case(),
        **{f"warped_variance_{kind}": _warped_variance_case(kind) for kind in ("translate", "affine")},
        "warped_variance_rows": _warped_variance_case("translate", (9, 35)),
        "noise_floor": _noise_floor_case((37, 139)),
        "consistency_from_frames": _consistency_frames_case(),
        "gradients_u16_dark_dead_pixel": _gradient_case(np.uint16, "single"),
        "gradients_f32_dark_per_frame": _gradient_case(np.float32, "per frame"),
        # the registration before the guided filter: run after it in one simulator process, the registration's
        # first reads of its (freshly written) pyramid are reported uninitialised, which neither family is alone
        # nor in this order (Oclgrind's shadow memory of the filter's released buffers, reused at the same
        # addresses)
        "registration_translation": _registration_case("translation"),
        "registration_affine": _registration_case("affine"),
        "guided_c9_strips_nonfinite": _guided_case((9, 11, 9), 2, 4, True),
        "guided_c1_radius_past_the_image": _guided_case((7, 6, 1), 5, None, False),
    }


def run_cases(names) -> int:
    table = cases()
    for name in names or list(table):
        print(f"@@case {name}", file=sys.stderr, flush=True)
        try:
            errors, tolerances = table[name]()
        except Exception as error:  # noqa: BLE001 (reported to the parent, which fails the case)
            print(json.dumps({"case": name, "raised": f"{type(error).__name__}: {error}"}), flush=True)
            continue
        print(json.dumps({"case": name, "errors": errors, "tolerances": tolerances}), flush=True)
    from specgpu.engine import runtime

    # the build options of every program made, so the parent can tell which variants and entries ran
    print(json.dumps({"programs": sorted(" ".join(key[2]) for key in runtime._programs)}), flush=True)
    return 0


def run_race() -> int:
    """The "gpu" variant's channels-last tile with its barrier removed: work-items read tile entries other
    work-items write, unordered. The kernels are a copy with that one line taken out."""
    from specgpu.engine import runtime

    source = runtime.kernel_dir()
    with tempfile.TemporaryDirectory() as tmp:
        for path in source.iterdir():
            if path.suffix in (".cl", ".h"):
                shutil.copy(path, tmp)
        linear = Path(tmp) / "linear.cl"
        text = linear.read_text()
        barrier = "    barrier(CLK_LOCAL_MEM_FENCE);\n"
        if text.count(barrier) != 1:
            raise SystemExit("linear.cl no longer has exactly one barrier: update the race drill")
        linear.write_text(text.replace(barrier, ""))
        runtime.kernel_dir = lambda: Path(tmp)
        runtime.kernel_source.cache_clear()
        os.environ["SPECGPU_VARIANT"] = "gpu"
        return run_cases(["linear_u16_interleaved_f32_b9_mask"])


def _oclgrind_context():
    import pyopencl as cl

    device = next(d for p in cl.get_platforms() if "oclgrind" in p.name.lower() for d in p.get_devices())
    context = cl.Context([device])
    return context, cl.CommandQueue(context)


def run_reduced(kernel, context, queue, x, *scalars) -> np.ndarray:
    """One work-item of a reduced kernel of tests/data/oclgrind_defects.cl that reads 8 values ``x`` and writes two
    rows of 8 ints: the rows (16,) int32 (also the suite's devices' check, tests/engine/test_oclgrind.py)."""
    import pyopencl as cl

    out = np.zeros(16, np.int32)
    mf = cl.mem_flags
    x_buf = cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    kernel(queue, (1,), None, x_buf, out_buf, *scalars)
    cl.enqueue_copy(queue, out, out_buf)
    return out


def run_vector_bool() -> int:
    """vector_bool of tests/data/oclgrind_defects.cl, optimised and not: one JSON object per build on stdout."""
    import pyopencl as cl

    context, queue = _oclgrind_context()
    source = (DATA / "oclgrind_defects.cl").read_text()
    x = np.array([0, 5, 10, 3, 20, 1, 10, 0], np.float32)
    for options in ([], ["-cl-opt-disable"]):
        program = cl.Program(context, source).build(options=options)
        out = run_reduced(program.vector_bool, context, queue, x, np.float32(10))
        print(json.dumps({"options": options, "x": x.tolist(), "ternary": out[:8].tolist(),
                          "select": out[8:].tolist()}), flush=True)
    return 0


def run_min_vector_scalar() -> int:
    """min_vector_scalar of tests/data/oclgrind_defects.cl, unoptimised (as specgpu builds for Oclgrind): one JSON
    object on stdout."""
    import pyopencl as cl

    context, queue = _oclgrind_context()
    program = cl.Program(context, (DATA / "oclgrind_defects.cl").read_text()).build(options=["-cl-opt-disable"])
    x = np.array([-3, 0, 4, 10, 11, 25, 7, 10], np.int32)
    out = run_reduced(program.min_vector_scalar, context, queue, x, np.int32(10))
    print(json.dumps({"x": x.tolist(), "scalar": out[:8].tolist(), "vector": out[8:].tolist()}), flush=True)
    return 0


def run_offset_write() -> int:
    """copy_floats of tests/data/oclgrind_defects.cl on a buffer written whole, then on one written in two halves
    (the second at an offset); a case marker on stderr before each, the second copy's output on stdout as JSON."""
    import pyopencl as cl

    context, queue = _oclgrind_context()
    program = cl.Program(context, (DATA / "oclgrind_defects.cl").read_text()).build(options=["-cl-opt-disable"])
    data = np.arange(32, dtype=np.float32)
    mf = cl.mem_flags
    out = np.zeros(32, np.float32)
    for case in ("from offset 0", "at an offset"):
        print(f"@@case {case}", file=sys.stderr, flush=True)
        buf = cl.Buffer(context, mf.READ_ONLY, data.nbytes)
        if case == "from offset 0":
            cl.enqueue_copy(queue, buf, data)
        else:
            cl.enqueue_copy(queue, buf, data[:16])
            cl.enqueue_copy(queue, buf, data[16:], dst_offset=data[:16].nbytes)
        out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
        program.copy_floats(queue, (32,), None, buf, out_buf)
        cl.enqueue_copy(queue, out, out_buf)
        queue.finish()
    print(json.dumps({"out": out.astype(int).tolist()}), flush=True)
    return 0


def run_shuffle(kernel: str) -> int:
    """One pairs_* kernel of tests/data/oclgrind_defects.cl; its output on stdout as JSON."""
    import pyopencl as cl

    context, queue = _oclgrind_context()
    program = cl.Program(context, (DATA / "oclgrind_defects.cl").read_text()).build()
    v = np.arange(16, dtype=np.float32)
    out = np.zeros(8, np.float32)
    mf = cl.mem_flags
    v_buf = cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=v)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    getattr(program, kernel)(queue, (1,), None, v_buf, out_buf)
    cl.enqueue_copy(queue, out, out_buf)
    print(json.dumps({"kernel": kernel, "out": out.tolist()}), flush=True)
    return 0


if __name__ == "__main__":
    mode = sys.argv[1]
    if mode == "cases":
        os.environ["SPECGPU_VARIANT"] = sys.argv[2]
        sys.exit(run_cases(sys.argv[3:]))
    if mode == "race":
        sys.exit(run_race())
    if mode == "vector_bool":
        sys.exit(run_vector_bool())
    if mode == "shuffle":
        sys.exit(run_shuffle(sys.argv[2]))
    if mode == "min_vector_scalar":
        sys.exit(run_min_vector_scalar())
    if mode == "offset_write":
        sys.exit(run_offset_write())
    raise SystemExit(f"unknown mode {mode!r}: cases, race, vector_bool, shuffle, min_vector_scalar or offset_write")
