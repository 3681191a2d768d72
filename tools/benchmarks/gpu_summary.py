"""The GPU targets against the figures tools/benchmarks/gpu_check.sh wrote (bench.json, stream_*.json, tests.txt).

    PYTHONPATH=. python tools/benchmarks/gpu_summary.py OUT_DIR

Prints one line per target: the figure, the threshold and PASS / MISS (or "not measured" when its file is absent).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _load(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _line(name: str, value, threshold: str, passed) -> str:
    verdict = "not measured" if value is None else ("PASS" if passed else "MISS")
    return f"{name:<62} {'-' if value is None else value:>14}  target {threshold:<12} {verdict}"


def summarise(out: Path) -> list[str]:
    lines = []
    bench = _load(out / "bench.json")
    cases = (bench or {}).get("cases", [])

    def case(name, layout, size=(4096, 4096)):
        for c in cases:
            if c["case"] == name and c.get("layout") == layout and (c["width"], c["height"]) == size:
                return c
        return None

    if bench:
        lines.append(f"device: {bench.get('device', '?')}, "
                     f"copy bandwidth {bench.get('copy_bandwidth_GBps', 0):.0f} GB/s")
    for layout, threshold in (("planar", 0.75), ("interleaved", 0.40)):
        c = case("cube_float32", layout)
        frac = None if c is None or c.get("fraction_of_copy") is None else c["fraction_of_copy"]
        lines.append(_line(f"4096x4096 f32 cube {layout}: fraction of copy bandwidth",
                           None if frac is None else f"{frac:.0%} ({c['device_ms']:.2f} ms)", f">= {threshold:.0%}",
                           frac is not None and frac >= threshold))
    for layout in ("planar", "interleaved"):
        c32, c16 = case("cube_float32", layout), case("cube_float16", layout)
        ok = c32 is not None and c16 is not None
        lines.append(_line(f"4096x4096 f16 faster than f32, {layout}",
                           f"{c16['device_ms']:.2f} vs {c32['device_ms']:.2f} ms" if ok else None, "f16 < f32",
                           ok and c16["device_ms"] < c32["device_ms"]))
    c = case("cube_float32", "planar")
    api = None if c is None else c.get("api_ms")
    lines.append(_line("4096x4096 f32 planar cube, NumPy in / NumPy out", None if api is None else f"{api:.0f} ms",
                       "<= 250 ms", api is not None and api <= 250))
    for size, threshold in (("2048", 1000.0), ("640", 8000.0)):
        rep = _load(out / f"stream_{size}.json")
        rows = {r["case"]: r for r in (rep or {}).get("cases", [])}
        fused = rows.get("coefficients+XYZ+dE2000")
        fps = None if fused is None else fused["frames_per_s"]
        lines.append(_line(f"stream {size}: coefficients + XYZ + dE2000, raw frames/s",
                           None if fps is None else f"{fps:.0f} ({fused['cpu_cores']:.1f} cores)",
                           f">= {threshold:.0f}", fps is not None and fps >= threshold))
        if size == "640":
            cube = rows.get("cube float16 61 bands to memory")
            fps = None if cube is None else cube["frames_per_s"]
            lines.append(_line("stream 640: 61-band float16 cube, raw frames/s",
                               None if fps is None else f"{fps:.0f} ({cube['cpu_cores']:.1f} cores)", ">= 2000",
                               fps is not None and fps >= 2000))
    tests = out / "tests.txt"
    if tests.is_file():
        tail = [t for t in tests.read_text().splitlines() if " passed" in t or " failed" in t]
        last = tail[-1] if tail else "no pytest summary line"
        lines.append(_line("test suite on the GPU", last.strip("= ")[:14], "all pass",
                           "failed" not in last and "error" not in last and " passed" in last))
    else:
        lines.append(_line("test suite on the GPU", None, "all pass", False))
    return lines


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: PYTHONPATH=. python tools/benchmarks/gpu_summary.py OUT_DIR")
    print("\n".join(summarise(Path(sys.argv[1]))))
