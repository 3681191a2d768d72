"""Throughput of the kernels against NumPy / colour-science baselines doing the same work, in one run.

Five cases at each image size:

1. ``cube_float32``: 9 uint16 frames (10-bit codes) -> 61-band float32 cube, planar (B, H, W) and
   interleaved (H, W, B); baseline: a float32 NumPy matmul in the matching layout.
2. ``cube_float16``: the same to float16; baseline: the float32 matmul ``.astype(np.float16)``.
3. ``fused_dE2000``: 9 frames -> XYZ (M = C . A, 3 x 9) -> Lab -> dE2000 against a per-pixel reference Lab
   image, one device pass; baseline: ``np.einsum`` + ``colour.XYZ_to_Lab`` + ``colour.delta_E("CIE 2000")``.
4. ``XYZ_Lab_dE2000``: an XYZ image -> Lab -> dE2000 against the reference (two kernels, data stays on the
   device); baseline: ``colour.XYZ_to_Lab`` + ``colour.delta_E("CIE 2000")``.
5. ``guided_filter``: ``recover --denoise``'s guided filter of a 9-frame plan's outputs (their 9 coordinates,
   :mod:`specgpu.apps.bench.denoise`); baseline: the same filter of the same image in NumPy with SciPy's box
   filter, timed in interleaved rounds (its speedup the median of the rounds' ratios).

Device timings are steady state: inputs already on the device, outputs drawn from the memory pool of
:func:`specgpu.engine.runtime.get_allocator`, one untimed warm-up call (program build, pool priming), then the
median wall time of enqueue + ``queue.finish()``. The NumPy-in / NumPy-out API call (``apply_linear``,
``frames_to_delta_E``, ``XYZ_to_Lab`` + ``delta_E``) is timed too, so the host round trip is visible.
Every device result is checked against its baseline, so the comparison is provably the same work.

A measured copy bandwidth on the same device (``cl.enqueue_copy`` buffer to buffer, bytes moved = 2 x size)
is the yardstick for the memory-bound cube cases.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import colour
import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from tqdm import tqdm

from specgpu import __version__, engine
from specgpu.apps.bench.denoise import BANDS, guided_case
from specgpu.core.spectra import XYZ_weights, white_point_XYZ
from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E, frames_to_delta_E
from specgpu.engine.linear_map import LAYOUTS, apply_linear
from specgpu.engine.runtime import get_allocator, get_queue

__all__ = ["run_bench", "CaseResult", "copy_bandwidth", "format_report", "TARGETS"]

K_FRAMES = 9
WAVELENGTHS = np.arange(400.0, 701.0, 5.0)  # 61 bands
CODE_MAX = 1023  # 10-bit sensor codes stored in uint16
LARGE_PIXELS = 1_000_000  # above this, fewer repeats (keeps the default run within ~3 minutes on 2 cores)

#: The kernel targets: fused >= 20x the colour-science chain; cube >= 70% of copy bandwidth; float16 faster; the
#: guided filter >= 5x the same filter in NumPy / SciPy.
TARGETS = {"fused_speedup": 20.0, "cube_fraction_of_copy": 0.70, "guided_speedup": 5.0}

# Largest acceptable difference to the baseline, by case: float32 rounding (different summation order),
# float16 rounding (half an ulp at 2^-11 either side of the float32 value), dE2000 in float32 vs float64.
TOLERANCES = {"cube_float32": 1e-5, "cube_float16": 2e-3, "fused_dE2000": 1e-3, "XYZ_Lab_dE2000": 1e-3,
              "guided_filter": 1e-4}


@dataclass
class CaseResult:
    """One benchmark row; times in milliseconds (medians), ``None`` where a figure does not apply."""

    case: str
    width: int
    height: int
    layout: str | None
    device_ms: float
    api_ms: float
    baseline_ms: float
    speedup: float
    Mpix_per_s: float
    GBps: float | None
    fraction_of_copy: float | None
    bytes_moved: int | None
    max_diff: float
    max_diff_kind: str
    tolerance: float
    within_tolerance: bool
    repeats: int
    api_repeats: int
    baseline_repeats: int
    baseline: str


# ---------------------------------------------------------------------------------------------------- timing


def _timed(fn: Callable, repeats: int, sync: Callable | None = None):
    """Median wall time (ms) of ``fn()`` (+ ``sync()``) over ``repeats`` calls, and the last result."""
    times, out = [], None
    for _ in range(repeats):
        out = None  # release the previous result first, so device outputs go back to the pool
        start = time.perf_counter()
        out = fn()
        if sync is not None:
            sync()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times), out


def _measure(queue, device: Callable, api: Callable, baseline: Callable, reps: tuple[int, int]):
    """Time the three forms of one case; returns (device_ms, api_ms, baseline_ms, device result on the host,
    baseline result).

    The device form runs once untimed first (program build, memory pool primed), so the timed calls reuse
    pooled outputs; the API result is dropped before the baseline runs (1 GB at 2048 x 2048 for the cube).
    """
    device()
    queue.finish()
    device_ms, out = _timed(device, reps[0], queue.finish)
    result = out.get()
    del out  # back to the pool
    api_ms = _timed(api, reps[1])[0]
    baseline_ms, expected = _timed(baseline, reps[1])
    return device_ms, api_ms, baseline_ms, result, expected


def _repeats(n_pixels: int, repeats: int | None) -> tuple[int, int]:
    """(device repeats, API / baseline repeats): the slow host paths get fewer at large sizes."""
    if repeats is not None:
        return repeats, repeats
    return (15, 5) if n_pixels <= LARGE_PIXELS else (5, 3)


def copy_bandwidth(queue: cl.CommandQueue, size_mib: int = 256, repeats: int = 5) -> tuple[float, float]:
    """Measured memory-copy bandwidth in GB/s (1e9 bytes): the device's buffer copy, and ``np.copyto``.

    Both buffers are written before timing (no first-touch page faults) and one copy warms up. Bytes moved
    per copy are 2 x size (read the source, write the destination).

    Returns
    -------
    (float, float)
        Device ``cl.enqueue_copy`` bandwidth and NumPy ``np.copyto`` bandwidth.
    """
    nbytes = size_mib << 20
    src = cl.Buffer(queue.context, cl.mem_flags.READ_WRITE, nbytes)
    dst = cl.Buffer(queue.context, cl.mem_flags.READ_WRITE, nbytes)
    cl.enqueue_fill_buffer(queue, src, np.uint8(1), 0, nbytes)
    cl.enqueue_fill_buffer(queue, dst, np.uint8(0), 0, nbytes)
    cl.enqueue_copy(queue, dst, src, byte_count=nbytes)
    queue.finish()
    device_ms, _ = _timed(lambda: cl.enqueue_copy(queue, dst, src, byte_count=nbytes), repeats, queue.finish)
    src.release()
    dst.release()

    host_src = np.ones(nbytes, np.uint8)
    host_dst = np.zeros(nbytes, np.uint8)
    np.copyto(host_dst, host_src)
    host_ms, _ = _timed(lambda: np.copyto(host_dst, host_src), repeats)
    return 2 * nbytes / (device_ms * 1e6), 2 * nbytes / (host_ms * 1e6)


# ------------------------------------------------------------------------------------------------ test data


def decoder_matrix() -> np.ndarray:
    """A (61, 9) float32 decoder: Gaussian band weights around 9 illuminant centres, rows summing to
    1 / 1023, so 10-bit codes map to reflectance in [0, 1] (a realistic range for the XYZ / Lab cases)."""
    centres = np.linspace(WAVELENGTHS[0], WAVELENGTHS[-1], K_FRAMES)
    A = np.exp(-0.5 * ((WAVELENGTHS[:, None] - centres[None, :]) / 30.0) ** 2)
    return (A / A.sum(axis=1, keepdims=True) / CODE_MAX).astype(np.float32)


@dataclass
class _Data:
    frames: np.ndarray  # (9, H, W) uint16
    A: np.ndarray  # (61, 9) float32
    M: np.ndarray  # (3, 9) float64, C . A
    XYZ: np.ndarray  # (H, W, 3) float32, [0, 1]
    reference: np.ndarray  # (H, W, 3) float32 Lab


def _make_data(width: int, height: int, seed: int = 0) -> _Data:
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, CODE_MAX + 1, size=(K_FRAMES, height, width), dtype=np.uint16)
    A = decoder_matrix()
    M = XYZ_weights(WAVELENGTHS, "D65") @ A.astype(np.float64)
    XYZ = (frames.reshape(K_FRAMES, -1).T.astype(np.float32) @ M.T.astype(np.float32)).reshape(height, width, 3)
    # The reference is the image's own Lab plus a few units of noise: dE values of a real comparison.
    Lab = colour.XYZ_to_Lab(XYZ, _illuminant_xy())
    reference = (Lab + rng.normal(0.0, 2.0, Lab.shape)).astype(np.float32)
    return _Data(frames, A, M, XYZ, reference)


def _D65() -> tuple:
    """The D65 white of the benchmark's grid (XYZ, Y = 1, what the kernels take) and its chromaticity
    (colour-science's baseline)."""
    return white_point_XYZ("D65", wavelengths=WAVELENGTHS), _illuminant_xy()


def _illuminant_xy():
    return colour.XYZ_to_xy(white_point_XYZ("D65", wavelengths=WAVELENGTHS))


def _max_abs_diff(a: np.ndarray, b: np.ndarray, chunk: int = 1 << 24) -> float:
    """max |a - b| in float64, in chunks (the cube at 2048 x 2048 is 1 GB: no full-size temporaries)."""
    a, b = a.reshape(-1), b.reshape(-1)
    worst = 0.0
    for i in range(0, a.size, chunk):
        worst = max(worst, float(np.max(np.abs(a[i:i + chunk].astype(np.float64) - b[i:i + chunk]))))
    return worst


# ------------------------------------------------------------------------------------------------- the cases


def _cube_case(queue, data: _Data, frames_dev, out_dtype, layout: str, reps: tuple[int, int]) -> CaseResult:
    B, K = data.A.shape
    _, height, width = data.frames.shape
    n = width * height
    out_layout = LAYOUTS[layout]
    name = "cube_float32" if out_dtype == np.float32 else "cube_float16"

    def device():
        out, _ = engine.launch_linear(queue, frames_dev, data.A, n=n, out_dtype=out_dtype, out_layout=out_layout)
        return out

    def api():
        return apply_linear(data.frames, data.A, out_dtype=out_dtype, layout=layout, device=queue)

    flat = data.frames.reshape(K, -1)
    if layout == "planar":
        def baseline():
            y = data.A @ flat.astype(np.float32)
            return y if out_dtype == np.float32 else y.astype(np.float16)
        text = "A @ f.reshape(9,-1).astype(float32)"
    else:
        A_T = np.ascontiguousarray(data.A.T)

        def baseline():
            y = flat.T.astype(np.float32) @ A_T
            return y if out_dtype == np.float32 else y.astype(np.float16)
        text = "f.reshape(9,-1).T.astype(float32) @ A.T"
    if out_dtype == np.float16:
        text += " .astype(float16)"

    device_ms, api_ms, baseline_ms, result, expected = _measure(queue, device, api, baseline, reps)
    # Relative to the largest magnitude: element-wise relative error is meaningless near zero reflectance.
    diff = _max_abs_diff(result, expected) / max(float(np.max(np.abs(expected))), 1e-30)
    bytes_moved = n * (K * data.frames.itemsize + B * np.dtype(out_dtype).itemsize)
    return _row(name, width, height, layout, device_ms, api_ms, baseline_ms, diff, "max relative",
                reps, text, bytes_moved)


def _fused_case(queue, data: _Data, frames_dev, reference_dev, reps: tuple[int, int]) -> CaseResult:
    _, height, width = data.frames.shape
    n, (white, xy) = width * height, _D65()

    def device():
        return engine.launch_frames_to_delta_E(queue, frames_dev, data.M, white, reference_dev, n=n,
                                               method="CIE 2000", reference_single=False).delta_E

    def api():
        return frames_to_delta_E(data.frames, data.M, data.reference, wavelengths=WAVELENGTHS, device=queue)

    def baseline():
        XYZ = np.einsum("ck,khw->hwc", data.M, data.frames)
        return colour.delta_E(data.reference, colour.XYZ_to_Lab(XYZ, xy), method="CIE 2000")

    device_ms, api_ms, baseline_ms, result, expected = _measure(queue, device, api, baseline, reps)
    return _row("fused_dE2000", width, height, None, device_ms, api_ms, baseline_ms,
                _max_abs_diff(result, expected), "max abs (dE)", reps,
                "np.einsum + colour.XYZ_to_Lab + colour.delta_E(CIE 2000)")


def _lab_case(queue, data: _Data, xyz_dev, reference_dev, reps: tuple[int, int]) -> CaseResult:
    height, width, _ = data.XYZ.shape
    n, (white, xy) = width * height, _D65()

    def device():
        lab = engine.launch_XYZ_to_Lab(queue, xyz_dev, white, n=n)
        return engine.launch_delta_E(queue, reference_dev, lab, method="CIE 2000", n=n)

    def api():
        return delta_E(data.reference, XYZ_to_Lab(data.XYZ, "D65", wavelengths=WAVELENGTHS, device=queue),
                       "CIE 2000", device=queue)

    def baseline():
        return colour.delta_E(data.reference, colour.XYZ_to_Lab(data.XYZ, xy), method="CIE 2000")

    device_ms, api_ms, baseline_ms, result, expected = _measure(queue, device, api, baseline, reps)
    return _row("XYZ_Lab_dE2000", width, height, None, device_ms, api_ms, baseline_ms,
                _max_abs_diff(result, expected), "max abs (dE)", reps,
                "colour.XYZ_to_Lab + colour.delta_E(CIE 2000)")


def _row(case, width, height, layout, device_ms, api_ms, baseline_ms, diff, kind, reps, baseline,
         bytes_moved=None) -> CaseResult:
    n = width * height
    tolerance = TOLERANCES[case]
    return CaseResult(
        case=case, width=width, height=height, layout=layout,
        device_ms=device_ms, api_ms=api_ms, baseline_ms=baseline_ms,
        speedup=baseline_ms / device_ms,
        Mpix_per_s=n / (device_ms * 1e3),
        GBps=None if bytes_moved is None else bytes_moved / (device_ms * 1e6),
        fraction_of_copy=None, bytes_moved=bytes_moved,
        max_diff=diff, max_diff_kind=kind, tolerance=tolerance,
        within_tolerance=bool(math.isfinite(diff) and diff <= tolerance),
        repeats=reps[0], api_repeats=reps[1], baseline_repeats=reps[1], baseline=baseline,
    )


def _steps(sizes):
    """The (size, case, layout) work list, in the order it runs (for the progress bar)."""
    for size in sizes:
        for layout in ("planar", "interleaved"):
            yield size, "cube_float32", layout
            yield size, "cube_float16", layout
        yield size, "fused_dE2000", None
        yield size, "XYZ_Lab_dE2000", None
        yield size, "guided_filter", None


# -------------------------------------------------------------------------------------------- the report


def evaluate_targets(cases: list[CaseResult]) -> dict:
    """The kernel targets (:data:`TARGETS`), per size (and layout) and overall.

    Returns
    -------
    dict
        ``{name: {"threshold", "passed", "results": [{"width", "height", "layout", "value", "passed"}]}}``;
        ``passed`` is True only when every measured row meets the target.
    """
    def target(threshold, rows):
        return {"threshold": threshold, "passed": bool(rows) and all(r["passed"] for r in rows), "results": rows}

    fused = [dict(width=c.width, height=c.height, layout=None, value=c.speedup,
                  passed=c.speedup >= TARGETS["fused_speedup"])
             for c in cases if c.case == "fused_dE2000"]
    cube = [dict(width=c.width, height=c.height, layout=c.layout, value=c.fraction_of_copy,
                 passed=c.fraction_of_copy is not None and c.fraction_of_copy >= TARGETS["cube_fraction_of_copy"])
            for c in cases if c.case == "cube_float32"]
    f32 = {(c.width, c.height, c.layout): c for c in cases if c.case == "cube_float32"}
    half = [dict(width=c.width, height=c.height, layout=c.layout,
                 value=f32[(c.width, c.height, c.layout)].device_ms / c.device_ms,
                 passed=c.device_ms < f32[(c.width, c.height, c.layout)].device_ms)
            for c in cases if c.case == "cube_float16" and (c.width, c.height, c.layout) in f32]
    guided = [dict(width=c.width, height=c.height, layout=None, value=c.speedup,
                   passed=c.speedup >= TARGETS["guided_speedup"])
              for c in cases if c.case == "guided_filter"]
    return {
        "fused_speedup_vs_colour_science": target(TARGETS["fused_speedup"], fused),
        "guided_speedup_vs_numpy": target(TARGETS["guided_speedup"], guided),
        "cube_fraction_of_copy_bandwidth": target(TARGETS["cube_fraction_of_copy"], cube),
        "float16_faster_than_float32": target(1.0, half),
    }


def _load_avg() -> float | None:
    """The 1-minute load average (None where the system has none): the conditions a timing was taken under."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def _fmt(value, spec: str, missing: str = "-") -> str:
    return missing if value is None else format(value, spec)


def format_report(report: dict, cases: list[CaseResult]) -> str:
    """The printed report: device, copy bandwidth, the table of cases, and PASS / MISS per target."""
    load = report.get("load_avg_1min") or {}
    lines = [
        f"specgpu {report['specgpu_version']} bench on {report['device']} ({report['platform']})"
        + (f", {report['date_utc']}" if report.get("date_utc") else "")
        + (f"; load average (1 min) {load['start']:.2f} at start, {load['end']:.2f} at end (the machine's other "
           "work competes for the same cores)" if load.get("start") is not None else ""),
        f"copy bandwidth: device {report['copy_bandwidth_GBps']:.2f} GB/s (cl.enqueue_copy, "
        f"{report['copy_size_MiB']} MiB), numpy {report['numpy_copy_bandwidth_GBps']:.2f} GB/s (np.copyto)",
        "times are medians in ms; device = data on the device, enqueue + finish; API = NumPy in / NumPy out",
        "",
    ]
    header = ("case", "size", "layout", "device ms", "API ms", "Mpx/s", "GB/s", "baseline ms", "speedup",
              "of copy", "max diff")
    rows = [header]
    for c in cases:
        flag = "" if c.within_tolerance else " MISMATCH"
        rows.append((
            c.case, f"{c.width}x{c.height}", c.layout or "-", f"{c.device_ms:.2f}", f"{c.api_ms:.2f}",
            f"{c.Mpix_per_s:.1f}", _fmt(c.GBps, ".2f"), f"{c.baseline_ms:.2f}", f"{c.speedup:.1f}x",
            _fmt(None if c.fraction_of_copy is None else 100 * c.fraction_of_copy, ".0f") +
            ("%" if c.fraction_of_copy is not None else ""),
            f"{c.max_diff:.1e}{flag}",
        ))
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    for i, r in enumerate(rows):
        lines.append("  ".join(cell.ljust(w) if j < 3 else cell.rjust(w) for j, (cell, w) in
                               enumerate(zip(r, widths))).rstrip())
        if i == 0:
            lines.append("  ".join("-" * w for w in widths))
    lines.append("")
    lines.append("max diff: cube rows max |device - numpy| / max |numpy|; dE rows max |device - colour| "
                 f"(tolerances: {', '.join(f'{k} {v:g}' for k, v in TOLERANCES.items())})")
    for c in cases:
        if not c.within_tolerance:
            lines.append(f"MISMATCH: {c.case} {c.width}x{c.height} {c.layout or ''} max diff {c.max_diff:.3e} "
                         f"> {c.tolerance:g}: device and baseline disagree")
    lines.append("")
    lines.append("targets:")
    t = report["targets"]
    for r in t["fused_speedup_vs_colour_science"]["results"]:
        lines.append(f"  {'PASS' if r['passed'] else 'MISS'}  fused_dE2000 {r['width']}x{r['height']}: "
                     f"{r['value']:.1f}x the colour-science chain (target >= {TARGETS['fused_speedup']:g}x)")
    for r in t["cube_fraction_of_copy_bandwidth"]["results"]:
        lines.append(f"  {'PASS' if r['passed'] else 'MISS'}  cube_float32 {r['width']}x{r['height']} {r['layout']}: "
                     f"{100 * r['value']:.0f}% of copy bandwidth "
                     f"(target >= {100 * TARGETS['cube_fraction_of_copy']:.0f}%)")
    for r in t["float16_faster_than_float32"]["results"]:
        lines.append(f"  {'PASS' if r['passed'] else 'MISS'}  cube_float16 {r['width']}x{r['height']} {r['layout']}: "
                     f"{r['value']:.2f}x the speed of cube_float32 (target > 1x)")
    for r in t["guided_speedup_vs_numpy"]["results"]:
        case = next(c for c in cases if c.case == "guided_filter" and (c.width, c.height) == (r["width"], r["height"]))
        lines.append(f"  {'PASS' if r['passed'] else 'MISS'}  guided_filter {r['width']}x{r['height']}x{BANDS}: device "
                     f"{case.device_ms:.2f} ms, NumPy/SciPy {case.baseline_ms:.2f} ms in the same run, "
                     f"{r['value']:.1f}x (median of {case.baseline_repeats} rounds; target >= "
                     f"{TARGETS['guided_speedup']:g}x)")
    return "\n".join(lines)


def run_bench(sizes=((640, 480), (2048, 2048)), device=None, repeats: int | None = None,
              json_path: str | Path | None = None, echo: Callable[[str], None] | None = print,
              progress: bool = True, copy_mib: int = 256) -> dict:
    """Run the five cases at each size, print the report and optionally write it as JSON.

    Parameters
    ----------
    sizes : sequence of (int, int)
        (width, height) image sizes.
    device : optional
        Device, queue or selector string (see :mod:`specgpu.engine.runtime`).
    repeats : int, optional
        Timed repetitions for every timing; default by size (device 15 and host 5 up to 1 Mpixel,
        device 5 and host 3 above).
    json_path : str or Path, optional
        Where to write the figures as JSON.
    echo : callable or None
        Receives the printed report (None: print nothing).
    progress : bool
        Show a progress bar on stderr.
    copy_mib : int
        Size of the copy-bandwidth buffers in MiB (256 or more measures main memory, not caches).

    Returns
    -------
    dict
        The JSON report: ``device``, ``platform``, ``specgpu_version``, ``copy_bandwidth_GBps``,
        ``numpy_copy_bandwidth_GBps``, ``date_utc``, ``load_avg_1min`` (``start``, ``end``), ``cases`` (one dict per
        :class:`CaseResult`) and ``targets`` (see :func:`evaluate_targets`).
    """
    sizes = [(int(w), int(h)) for w, h in sizes]
    if repeats is not None and repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    queue = get_queue(device)
    pool = get_allocator(queue)
    started, load_start = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), _load_avg()
    steps = list(_steps(sizes))
    bar = tqdm(total=len(steps) + 1, desc="specgpu bench", unit="case", file=sys.stderr, disable=not progress,
               leave=False)
    bar.set_postfix_str("copy bandwidth")
    copy_GBps, numpy_copy_GBps = copy_bandwidth(queue, copy_mib)
    bar.update()

    cases: list[CaseResult] = []
    try:
        for width, height in sizes:
            reps = _repeats(width * height, repeats)
            data = _make_data(width, height)
            frames_dev = cla.to_device(queue, data.frames.reshape(-1))
            reference_dev = cla.to_device(queue, data.reference.reshape(-1))
            xyz_dev = cla.to_device(queue, data.XYZ.reshape(-1))
            for size, case, layout in steps:
                if size != (width, height):
                    continue
                bar.set_postfix_str(f"{case} {width}x{height} {layout or ''}".rstrip())
                if case.startswith("cube"):
                    dtype = np.float32 if case == "cube_float32" else np.float16
                    row = _cube_case(queue, data, frames_dev, dtype, layout, reps)
                    row.fraction_of_copy = row.GBps / copy_GBps
                elif case == "fused_dE2000":
                    row = _fused_case(queue, data, frames_dev, reference_dev, reps)
                elif case == "guided_filter":
                    row = guided_case(queue, width, height, reps, _row)
                else:
                    row = _lab_case(queue, data, xyz_dev, reference_dev, reps)
                cases.append(row)
                bar.update()
            del frames_dev, reference_dev, xyz_dev, data
            pool.free_held()  # the next size needs other buffer sizes: give this size's back
    finally:
        bar.close()

    report = {
        "device": queue.device.name.strip(),
        "platform": queue.device.platform.name.strip(),
        "specgpu_version": __version__,
        "copy_bandwidth_GBps": copy_GBps,
        "numpy_copy_bandwidth_GBps": numpy_copy_GBps,
        "copy_size_MiB": copy_mib,
        "date_utc": started,
        "load_avg_1min": {"start": load_start, "end": _load_avg()},
        "cases": [asdict(c) for c in cases],
    }
    report["targets"] = evaluate_targets(cases)
    if echo is not None:
        echo(format_report(report, cases))
    if json_path is not None:
        Path(json_path).write_text(json.dumps(report, indent=2) + "\n")
    return report
