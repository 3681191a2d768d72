"""Kernel regression suite: the golden set every device must reproduce.

The golden set (``tests/data/golden.npz``, shipped in the wheel as ``specgpu/_golden/golden.npz``) holds small
inputs with odd image sizes (not a multiple of the vector width) and the outputs computed in float64 by the
NumPy / colour-science references (``tools/maintenance/make_golden.py``), plus Sharma, Wu and Dalal's published
CIEDE2000 pairs. :func:`run_selftest` runs every case through the public API on the chosen device and compares.

Each output of a case has its own tolerance, either absolute ("abs": Lab 1e-4 and CIEDE2000 1e-3, the documented
float32 bounds) or relative to the output's range ("range": max|error| / max(1, max|expected|); 1e-5 for float32
matrix products, 1e-3 for float16 outputs, whose rounding is 2^-11 relative). Non-finite values must come out
exactly where the reference has them, and masks must match exactly.
"""

from __future__ import annotations

import json
import time
import zipfile
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from specgpu.engine.colorimetry import XYZ_to_Lab, delta_E, frames_to_delta_E, reflectance_to_XYZ
from specgpu.engine.guided import guided_filter
from specgpu.engine.linear_map import apply_linear
from specgpu.engine.runtime import get_queue

__all__ = ["golden_path", "load_golden", "run_selftest", "SelftestReport", "CaseResult", "CASES"]


def golden_path() -> Path:
    """The golden file: the copy inside an installed package first, else the source tree's tests/data."""
    packaged = resources.files("specgpu") / "_golden" / "golden.npz"
    if packaged.is_file():
        return Path(str(packaged))
    source_tree = Path(__file__).resolve().parents[2] / "tests" / "data" / "golden.npz"
    if source_tree.is_file():
        return source_tree
    raise FileNotFoundError(f"golden set not found at {packaged} nor {source_tree}: the installation is incomplete")


def load_golden(path: Path | None = None) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """(manifest, arrays by case) of a golden file; a corrupt or foreign file is a one-line error naming it."""
    path = Path(path) if path is not None else golden_path()
    try:
        with np.load(path, allow_pickle=False) as data:
            manifest = json.loads(str(data["_manifest"]))
            arrays: dict[str, dict[str, np.ndarray]] = {}
            for key in data.files:
                if key == "_manifest":
                    continue
                case, _, name = key.partition("/")
                arrays.setdefault(case, {})[name] = data[key]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise ValueError(f"golden set {path} is unreadable or not a specgpu golden file: {error}") from error
    if manifest.get("format") != "specgpu-golden" or manifest.get("version") != 1:
        raise ValueError(f"golden set {path} has format {manifest.get('format')!r} version "
                         f"{manifest.get('version')!r}; expected specgpu-golden version 1")
    return manifest, arrays


# --------------------------------------------------------------------------------------------------- the cases


def _linear(d, device, **kw):
    dark = d.get("dark")
    gain = d.get("gain")
    sat = float(d["saturation"]) if "saturation" in d else None
    res = apply_linear(d["frames"], d["A"], dark, gain, out_dtype=kw["out_dtype"], layout=kw["layout"],
                       saturation=sat, return_mask=sat is not None, device=device)
    if sat is not None:
        return {"y": res.y.astype(np.float64), "mask": res.mask}
    return {"y": res.astype(np.float64)}


def _xyz_to_lab(d, device, **kw):
    return {"Lab": XYZ_to_Lab(d["XYZ"], illuminant=kw["illuminant"], device=device)}


def _reflectance_to_lab(d, device, **kw):
    colours = {"wavelengths": d["wavelengths"], "integration": kw["integration"]}
    XYZ = reflectance_to_XYZ(d["R"], d["wavelengths"], illuminant=kw["illuminant"], cmfs=kw["cmfs"],
                             integration=kw["integration"], device=device)
    return {"XYZ": XYZ, "Lab": XYZ_to_Lab(XYZ, kw["illuminant"], observer=kw["cmfs"], device=device, **colours)}


def _delta_e(d, device, **kw):
    return {"dE": delta_E(d["Lab_1"], d["Lab_2"], method=kw["method"], device=device)}


def _reflectance_to_xyz(d, device, **kw):
    return {"XYZ": reflectance_to_XYZ(d["R"], d["wavelengths"], illuminant=kw["illuminant"], cmfs=kw["cmfs"],
                                      device=device)}


def _fused(d, device, **kw):
    res = frames_to_delta_E(d["frames"], d["A"], d["reference"], C=d["C"], illuminant=kw["illuminant"],
                            method=kw["method"], dark=d.get("dark"), gain=d.get("gain"),
                            saturation=float(d["saturation"]), return_XYZ=True, return_Lab=True,
                            return_mask=True, device=device)
    return {"XYZ": res.XYZ, "Lab": res.Lab, "dE": res.delta_E, "mask": res.mask}


def _guided(d, device, **kw):
    return {"q": guided_filter(d["image"], d["guide"], radius=kw["radius"], eps=kw["eps"], device=device)}


#: kernel label, runner, keyword arguments; the expected arrays are in the golden file.
CASES = {
    "linear_u16_planar_f32_dark_gain": ("linear", _linear, {"out_dtype": "float32", "layout": "planar"}),
    "linear_u8_interleaved_f16": ("linear", _linear, {"out_dtype": "float16", "layout": "interleaved"}),
    "linear_f32_perframe_dark_mask_nan": ("linear", _linear, {"out_dtype": "float32", "layout": "interleaved"}),
    "linear_u16_k61_b31_f16_planar": ("linear", _linear, {"out_dtype": "float16", "layout": "planar"}),
    "xyz_to_lab_d65": ("xyz_to_lab", _xyz_to_lab, {"illuminant": "D65"}),
    "xyz_to_lab_a": ("xyz_to_lab", _xyz_to_lab, {"illuminant": "A"}),
    "delta_e_cie1976": ("delta_e", _delta_e, {"method": "CIE 1976"}),
    "delta_e_cie1994": ("delta_e", _delta_e, {"method": "CIE 1994"}),
    "delta_e_cie2000": ("delta_e", _delta_e, {"method": "CIE 2000"}),
    "delta_e_cie2000_single_reference": ("delta_e", _delta_e, {"method": "CIE 2000"}),
    "delta_e_cie2000_sharma2005": ("delta_e", _delta_e, {"method": "CIE 2000"}),
    "reflectance_to_xyz_d65_2deg": ("linear", _reflectance_to_xyz,
                                    {"illuminant": "D65", "cmfs": "CIE 1931 2 Degree Standard Observer"}),
    "reflectance_to_xyz_a_10deg": ("linear", _reflectance_to_xyz,
                                   {"illuminant": "A", "cmfs": "CIE 1964 10 Degree Standard Observer"}),
    "fused_frames_to_de2000": ("fused", _fused, {"illuminant": "D65", "method": "CIE 2000"}),
    "fused_frames_to_de94": ("fused", _fused, {"illuminant": "D65", "method": "CIE 1994"}),
    "guided_r2_eps0.0001": ("guided", _guided, {"radius": 2, "eps": 1e-4}),
    "guided_r4_eps0.01": ("guided", _guided, {"radius": 4, "eps": 1e-2}),
    # a perfect white in the first row: (100, 0, 0) with the white of the cube's grid and integration
    "reflectance_white_to_lab_d65_10nm": ("xyz_to_lab", _reflectance_to_lab,
                                          {"illuminant": "D65", "cmfs": "CIE 1931 2 Degree Standard Observer",
                                           "integration": "rectangle"}),
    "reflectance_white_to_lab_a_astm_20nm": ("xyz_to_lab", _reflectance_to_lab,
                                             {"illuminant": "A", "cmfs": "CIE 1964 10 Degree Standard Observer",
                                              "integration": "ASTM E308"}),
}


# ---------------------------------------------------------------------------------------------- the comparison


@dataclass
class CaseResult:
    """One golden case run on the device: its kernel, whether it passed, and its error against the golden output."""

    name: str
    kernel: str
    passed: bool
    errors: dict[str, float] = field(default_factory=dict)
    tolerances: dict[str, float] = field(default_factory=dict)
    message: str = ""
    seconds: float = 0.0


@dataclass
class SelftestReport:
    """The regression suite on one device: the device, the golden set read and every case's result."""

    device: str
    golden: str
    cases: list[CaseResult]

    @property
    def passed(self) -> bool:
        return bool(self.cases) and all(c.passed for c in self.cases)

    def failed_kernels(self) -> list[str]:
        return sorted({c.kernel for c in self.cases if not c.passed})

    def kernels(self) -> dict[str, bool]:
        out: dict[str, bool] = {}
        for c in self.cases:
            out[c.kernel] = out.get(c.kernel, True) and c.passed
        return out

    def format(self, verbose: bool = False) -> str:
        lines = [f"specgpu selftest on {self.device}", f"golden set: {self.golden}"]
        for kernel, ok in self.kernels().items():
            n = sum(c.kernel == kernel for c in self.cases)
            lines.append(f"  {kernel:<12} {'PASS' if ok else 'FAIL'}  ({n} cases)")
        for c in self.cases:
            if verbose or not c.passed:
                figures = ", ".join(f"{k} {v:.2e} (tol {c.tolerances.get(k, float('nan')):.0e})"
                                    for k, v in c.errors.items())
                status = "ok  " if c.passed else "FAIL"
                lines.append(f"    {status} {c.name}: {figures}{'; ' + c.message if c.message else ''}")
        lines.append("PASS: every kernel reproduces the golden set" if self.passed else
                     f"FAIL: {', '.join(self.failed_kernels())}")
        return "\n".join(lines)


def compare(name: str, got: np.ndarray, expected: np.ndarray, kind: str) -> tuple[float, str]:
    """Error of ``got`` against ``expected``: absolute (``kind="abs"``) or relative to the range (``"range"``:
    max|got - expected| / max(1, max|expected|)) over the finite entries. Non-finite values (NaN, inf) must be
    at the same places; integer arrays (masks) must be equal (the error is the number of differing entries).

    Returns (error, message); the message is empty unless the shapes or NaN patterns differ.
    """
    got = np.asarray(got)
    expected = np.asarray(expected)
    if got.shape != expected.shape:
        return float("inf"), f"{name} has shape {got.shape}, expected {expected.shape}"
    if expected.dtype.kind in "iub":
        wrong = int(np.sum(got != expected))
        return float(wrong), ""
    got = got.astype(np.float64)
    finite = np.isfinite(expected)
    if not np.array_equal(np.isfinite(got), finite):
        return float("inf"), f"{name}: non-finite values differ in place from the reference"
    if not finite.any():
        return 0.0, ""
    error = float(np.max(np.abs(got[finite] - expected[finite])))
    if kind == "range":
        error /= max(1.0, float(np.max(np.abs(expected[finite]))))
    elif kind != "abs":
        raise ValueError(f"unknown tolerance kind {kind!r} in the golden set")
    return error, ""


def run_selftest(device=None, path: Path | None = None) -> SelftestReport:
    """Run every golden case on ``device`` and compare each output with its reference within its tolerance.

    Parameters
    ----------
    device : optional
        Explicit device, queue or selector (see :func:`specgpu.engine.runtime.get_queue`); default: the
        resolved device.
    path : path-like, optional
        Golden file (default: :func:`golden_path`, the copy shipped with the package).

    Returns
    -------
    SelftestReport
        One :class:`CaseResult` per case; ``passed`` is True when every case passes, ``format()`` gives the
        report ``specgpu selftest`` prints. A failing kernel is a failed case, not an exception.

    Raises
    ------
    ValueError
        The golden file is unreadable or not a specgpu golden file.

    Examples
    --------
    >>> from specgpu.engine import run_selftest
    >>> report = run_selftest()
    >>> report.passed, report.failed_kernels()
    (True, [])
    >>> sorted(report.kernels())
    ['delta_e', 'fused', 'guided', 'linear', 'xyz_to_lab']
    """
    queue = get_queue(device)
    manifest, arrays = load_golden(path)
    results = []
    for entry in manifest["cases"]:
        name = entry["name"]
        if name not in CASES:
            results.append(CaseResult(name, "unknown", False, message="case not known to this specgpu version"))
            continue
        kernel, runner, kwargs = CASES[name]
        data = arrays.get(name, {})
        inputs = {k: v for k, v in data.items() if not k.startswith("expected_")}
        kinds = {k: v[0] for k, v in entry["tolerances"].items()}
        tolerances = {k: float(v[1]) for k, v in entry["tolerances"].items()}
        t0 = time.perf_counter()
        try:
            outputs = runner(inputs, queue, **kwargs)
        except Exception as error:  # noqa: BLE001 (a failing kernel is a FAIL line, not a crash of the suite)
            results.append(CaseResult(name, kernel, False, message=f"raised {type(error).__name__}: {error}"))
            continue
        errors, messages = {}, []
        for out_name in tolerances:
            if out_name not in outputs or f"expected_{out_name}" not in data:
                errors[out_name] = float("inf")
                messages.append(f"{out_name}: missing from the run or from the golden set")
                continue
            err, msg = compare(out_name, outputs[out_name], data[f"expected_{out_name}"], kinds[out_name])
            errors[out_name] = err
            if msg:
                messages.append(msg)
        passed = not messages and all(errors[k] <= tolerances[k] for k in tolerances)
        results.append(CaseResult(name, kernel, passed, errors, tolerances, "; ".join(messages),
                                  time.perf_counter() - t0))
    missing = sorted(set(CASES) - {e["name"] for e in manifest["cases"]})
    for name in missing:
        results.append(CaseResult(name, CASES[name][0], False, message="missing from the golden set"))
    device_name = f"{queue.device.name.strip()} ({queue.device.platform.name.strip()})"
    return SelftestReport(device_name, str(path or golden_path()), results)
