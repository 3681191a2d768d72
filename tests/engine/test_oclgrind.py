"""Every kernel entry and build variant under Oclgrind, the OpenCL device simulator that checks each memory
access, barrier and API call: data races (OCLGRIND_DATA_RACES), API misuse (OCLGRIND_CHECK_API), uninitialised
reads (OCLGRIND_UNINITIALIZED) and out-of-bounds accesses (always on), which PoCL's way of running work-items
hides. Any report fails the case, and every output is compared with the float64 reference.

The kernels run in a process of their own (tests/oclgrind_worker.py): the ICD loader inside the pyopencl wheel
finds Oclgrind through OCL_ICD_VENDORS, a folder with a .icd file naming Oclgrind's ICD library, read once at start.
Skipped, with the reason, where Oclgrind is not installed (Debian / Ubuntu: ``apt-get install oclgrind``);
.ci/run installs it.

Two Oclgrind 21.10 defects are reproduced here with reduced kernels (tests/data/oclgrind_defects.cl), so that
what specgpu does about them stays justified: a vector ``c ? 1 : 0`` evaluates to 255 per true lane once clang
has optimised it (specgpu.engine.runtime builds for Oclgrind with -cl-opt-disable), and multi-lane vector components
crash its uninitialised-value check (kernels/common.h builds vectors from single lanes).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from oclgrind_worker import run_reduced

import specgpu

HERE = Path(__file__).resolve().parents[1]  # tests/: the worker script and the data
WORKER = HERE / "oclgrind_worker.py"
ICD_NAME = "liboclgrind-rt-icd.so"
TIMEOUT_S = 600

#: Lines that start or belong to an Oclgrind report: API errors, fatal errors, races, invalid and uninitialised
#: accesses (each of the last names the kernel on a "Kernel:" line).
REPORT = re.compile(r"Oclgrind - |OCLGRIND|data race|Invalid (read|write)|[Uu]ninitiali[sz]ed|^\s*Kernel: ")
CHECKS = {"OCLGRIND_DATA_RACES": "1", "OCLGRIND_CHECK_API": "1", "OCLGRIND_UNINITIALIZED": "1"}



def oclgrind_icd() -> Path | None:
    """Oclgrind's ICD library, found next to its ``oclgrind`` command (Debian: /usr/lib/oclgrind/)."""
    command = shutil.which("oclgrind")
    if command is None:
        return None
    prefix = Path(command).resolve().parent.parent
    for pattern in (f"lib/oclgrind/{ICD_NAME}", f"lib/*/oclgrind/{ICD_NAME}", f"lib*/{ICD_NAME}",
                    f"lib/*/{ICD_NAME}"):
        found = sorted(prefix.glob(pattern))
        if found:
            return found[0]
    return None


@pytest.fixture(scope="module")
def oclgrind_env(tmp_path_factory):
    """The environment of a worker process that sees the Oclgrind device (and only it)."""
    icd = oclgrind_icd()
    if icd is None:
        pytest.skip("Oclgrind is not installed (apt-get install oclgrind): the kernels are not checked under the "
                    "OpenCL simulator")
    vendors = tmp_path_factory.mktemp("icd")
    (vendors / "oclgrind.icd").write_text(f"{icd}\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OCLGRIND_", "SPECGPU_"))}
    env.update(
        OCL_ICD_VENDORS=str(vendors),
        PYOPENCL_NO_CACHE="1",  # a binary cached by another build of the simulator is not what it would compile
        PYTHONPATH=os.pathsep.join([str(Path(specgpu.__file__).resolve().parent.parent),
                                    env.get("PYTHONPATH", "")]).rstrip(os.pathsep),
    )
    return env


def run_worker(env, *args, checks=CHECKS) -> tuple[subprocess.CompletedProcess, dict[str, list[str]]]:
    """Run the worker; returns the finished process and the Oclgrind report lines by case ("" before any)."""
    proc = subprocess.run([sys.executable, str(WORKER), *args], env={**env, **checks}, capture_output=True,
                          text=True, timeout=TIMEOUT_S, cwd=HERE)
    reports: dict[str, list[str]] = {}
    case = ""
    for line in proc.stderr.splitlines():
        if line.startswith("@@case "):
            case = line.split(" ", 1)[1]
        elif REPORT.search(line):
            reports.setdefault(case, []).append(line)
    return proc, reports


def results(proc) -> tuple[dict[str, dict], list[str]]:
    cases, programs = {}, []
    for line in proc.stdout.splitlines():
        record = json.loads(line)
        if "programs" in record:
            programs = record["programs"]
        else:
            cases[record["case"]] = record
    return cases, programs


def stderr_of(proc, case: str, limit: int = 40) -> str:
    """The worker's stderr from ``case``'s marker on (its Oclgrind reports, a traceback), first lines."""
    text = proc.stderr
    start = text.find(f"@@case {case}\n")
    lines = text[start if start >= 0 else 0:].splitlines()
    return "\n".join(lines[:limit])


@pytest.mark.slow  # a simulator interprets every work-item of 38 cases: about a minute per variant
@pytest.mark.parametrize("variant", ["cpu", "gpu"])
def test_every_kernel_is_clean_and_right_under_oclgrind(oclgrind_env, variant):
    """Each case of the worker (linear: planar / channels last, float32 / float16, the "cpu" variant's 16-pixel
    float16 entry and register transpose, the "gpu" variant's local-memory tile and per-element launch, mask,
    dark, gain, square root; XYZ -> Lab; dE76 / 94 / 2000 alone and fused; the dE2000 sigma; the motion-compensated
    linear map and the consistency check, each with translations, affine maps and a flow (the check also with a
    noise floor per frame and pixel); the outputs' variance at the warped samples
    (translations and affine maps); the check's noise floors; the check's images given
    as one array, uploaded in one write: see the offset-write test below) on 99 pixels (two work-groups, the second
    partial), and the map's translations on 21 x 35 pixels as well, which its two passes run along strips of rows,
    and as the stream prepares them (output groups interleaved and planar, frames read from a larger buffer, float
    frames with NaN and inf, a dead pixel) on 21 x 35 and 5 x 270 pixels; the check with a 9-pixel window on
    21 x 35 pixels, with a sample that misleads its bracket (the strips run twice), and from raw frames (the
    gradient images made on the device, the samples scaled); the gradient images alone with a dead pixel and a dark
    frame per frame; the guided filter (three passes, or one along strips of rows), nine channels in short strips
    with a NaN in the image and an inf in the guide, and one channel with windows wider than the image; the
    registration of images on the device, translations and affine maps: no Oclgrind report, and every output within
    its tolerance."""
    proc, reports = run_worker(oclgrind_env, "cases", variant)
    assert proc.returncode == 0, f"the worker ended with {proc.returncode}:\n{proc.stderr[-4000:]}"
    cases, programs = results(proc)
    failures = case_failures(proc, cases, reports)
    assert not failures, "\n".join(failures)
    assert len(cases) == 42, sorted(cases)

    # the variant's own code paths were built (the variant comes from SPECGPU_VARIANT in the worker); the motion
    # kernels' programs (the warp's OUT_INTERLEAVED per pixel or GROUPS for translations, the check's WINDOW, the
    # gradient images' GROWS) have one set of entries for every device, the translations a work shape per variant,
    # the check's strips and selections one per variant
    warp = [p for p in programs if "-DOUT_INTERLEAVED=" in p or "-DGROUPS=" in p]
    steps = "-DXSTEPS=1 " if variant == "gpu" else "-DXSTEPS=16 "
    assert all(steps in p + " " for p in warp if "-DGROUPS=" in p)
    check = [p for p in programs if "-DWINDOW=" in p]
    gradient = [p for p in programs if "-DGROWS=" in p]
    register = [p for p in programs if "-DHROWS=" in p]  # the registration's, one size of group per variant
    linear = [p for p in programs if "-DB=" in p and p not in warp]
    # the guided filter: three passes on GPUs, a pixel and a row per work-item; one pass along strips of rows on CPUs
    guided = [p for p in programs if "-DSTRIPS=" in p]
    assert guided and all(f"-DSTRIPS={int(variant == 'cpu')} " in p + " " for p in guided)
    if variant == "gpu":
        assert all("-DVW=1" in p for p in programs if p not in warp + check + gradient + guided + register)
        assert any("-DTILE=1" in p for p in linear) and any("-DTILE=0" in p for p in linear)
        assert all("-DSELECT_GROUP=64" in p and "-DV=1 " in p for p in check)  # small strips, atomic counts
    else:
        assert not any("-DVW=1" in p for p in programs)
        assert all("-DSELECT_GROUP=1" in p for p in check)
        assert any("-DOUT_HALF=1" in p and "-DOUT_LAYOUT=0" in p for p in linear)  # linear_apply_h16
    assert any("-DOUT_SQRT=1" in p for p in linear)
    for method in (76, 94, 2000):
        assert any(f"-DDE_METHOD={method}" in p for p in programs)
    # the motion kernels' variants: the warp's translations in two passes (one and two output groups) and flow per
    # pixel; the consistency check's translations, affine maps (neither) and flow
    assert any("-DGROUPS=1" in p for p in warp) and any("-DGROUPS=2" in p for p in warp)
    assert any("-DFLOW=1" in p for p in warp)
    assert any("-DTRANSLATE=1" in p for p in check) and any("-DFLOW=1" in p for p in check)
    assert any("-DTRANSLATE=0" in p and "-DFLOW" not in p for p in check)
    assert any("-DWINDOW=9" in p for p in check) and any("-DSCALED=1" in p for p in check)
    assert any("-DFLOOR=1" in p and "-DTRANSLATE=1" in p for p in check)
    assert any("-DFLOOR=1" in p and "-DFLOW=1" in p for p in check)
    assert any("-DFLOOR=1" in p and "-DTRANSLATE=0" in p and "-DFLOW" not in p for p in check)
    assert any("-DHAS_DARK=2" in p and "-DIN_T=float" in p for p in gradient)
    assert any("-DHAS_GAIN=1" in p and "-DIN_T=ushort" in p for p in gradient)
    # the registration's steps: a translation (8 pixels at a time) and an affine map, in the variant's group size
    group = "-DGROUP=64" if variant == "gpu" else "-DGROUP=1"
    assert any("-DAFFINE=0" in p and group in p for p in programs)
    assert any("-DAFFINE=1" in p and group in p for p in programs)


def case_failures(proc, cases, reports) -> list[str]:
    """Each case's error over its tolerance, exception or Oclgrind report, as lines."""
    failures = []
    for name, record in cases.items():
        if "raised" in record:
            failures.append(f"{name}: raised {record['raised']}")
            continue
        for out, err in record["errors"].items():
            tol = record["tolerances"][out]
            if isinstance(err, str) or not err <= tol:
                failures.append(f"{name}: {out} error {err} (tolerance {tol})")
        if name in reports:
            failures.append(f"{name}: {len(reports[name])} Oclgrind report lines:\n{stderr_of(proc, name)}")
    if "" in reports:
        failures.append("Oclgrind reports before the first case:\n" + "\n".join(reports[""][:20]))
    return failures


def test_a_missing_barrier_is_reported(oclgrind_env):
    """The check catches a race: the "gpu" variant's channels-last tile with its barrier taken out (work-items
    then read tile entries other work-items have not written yet) gives data-race reports on local memory."""
    proc, reports = run_worker(oclgrind_env, "race", checks={"OCLGRIND_DATA_RACES": "1"})
    assert proc.returncode == 0, proc.stderr[-4000:]
    lines = reports.get("linear_u16_interleaved_f32_b9_mask", [])
    races = [line for line in lines if "data race at local memory" in line]
    assert races, f"no race reported:\n{proc.stderr[-4000:]}"
    assert any("Kernel: linear_apply" in line for line in lines)


def test_oclgrind_zero_extends_vector_booleans_to_255(oclgrind_env):
    """The simulator's defect behind the "cpu" variant's wrong masks, reduced (tests/data/oclgrind_defects.cl):
    optimised, ``v >= level ? (int8)(1) : (int8)(0)`` comes out 255 where OpenCL C (and PoCL, see the test below)
    gives 1, while the explicit select() gives 1; unoptimised, both give 1, which is why specgpu.engine.runtime builds
    with -cl-opt-disable for Oclgrind. Should a later Oclgrind fix it, the first assertion fails and that option
    can go."""
    proc, reports = run_worker(oclgrind_env, "vector_bool", checks={})
    assert proc.returncode == 0, proc.stderr[-4000:]
    optimised, unoptimised = (json.loads(line) for line in proc.stdout.splitlines())
    expected = [1 if x >= 10 else 0 for x in optimised["x"]]
    assert optimised["ternary"] == [255 * e for e in expected]
    assert optimised["select"] == expected
    assert unoptimised["ternary"] == expected and unoptimised["select"] == expected


def test_vector_bool_reduced_kernel_on_the_test_devices(queue):
    """The same reduced kernel on the devices the suite runs on (PoCL at least): 1 per true lane in both rows,
    as OpenCL C defines, so 255 is the simulator's error and not the kernel's."""
    import pyopencl as cl

    program = cl.Program(queue.context, (HERE / "data" / "oclgrind_defects.cl").read_text()).build()
    x = np.array([0, 5, 10, 3, 20, 1, 10, 0], np.float32)
    out = run_reduced(program.vector_bool, queue.context, queue, x, np.float32(10))
    expected = (x >= 10).astype(np.int32)
    np.testing.assert_array_equal(out[:8], expected)
    np.testing.assert_array_equal(out[8:], expected)


def test_oclgrind_uninitialised_check_crashes_on_multi_lane_components(oclgrind_env):
    """The reduced form of what kernels/common.h's 8 x 8 transpose avoids: a vector built from two-lane
    components kills the process under OCLGRIND_UNINITIALIZED=1 (a segmentation fault in the simulator, which no
    kernel can cause legitimately), the same vector from single lanes runs and is right."""
    checks = {"OCLGRIND_UNINITIALIZED": "1"}
    crashed, _ = run_worker(oclgrind_env, "shuffle", "pairs_multi_lane", checks=checks)
    assert crashed.returncode != 0
    ran, reports = run_worker(oclgrind_env, "shuffle", "pairs_single_lane", checks=checks)
    assert ran.returncode == 0 and not reports, ran.stderr[-4000:]
    assert json.loads(ran.stdout)["out"] == [0, 1, 8, 9, 4, 5, 12, 13]


def test_split_sincos_gives_the_same_ciede2000(queue):
    """CIEDE2000 with SPLIT_SINCOS (sin() and cos(), the build Oclgrind gets) equals the sincos() build on the test
    devices to float32 rounding."""
    import pyopencl.array as cla
    from reference import random_Lab

    from specgpu.engine.runtime import get_kernel

    rng = np.random.default_rng(12)
    n = 1001
    lab2 = random_Lab(rng, (n,)).astype(np.float32)
    lab1 = (lab2 + rng.normal(0, 3, lab2.shape)).astype(np.float32)
    d1, d2 = cla.to_device(queue, lab1), cla.to_device(queue, lab2)
    outs = []
    for split in (0, 1):
        kernel = get_kernel(queue, "colorimetry.cl", "delta_e", DE_METHOD=2000, SPLIT_SINCOS=split)
        out = cla.empty(queue, n, np.float32)
        kernel(queue, (-(-n // 64) * 64,), (64,), d1.data, d2.data, out.data, np.uint64(n))
        outs.append(out.get())
    np.testing.assert_allclose(outs[1], outs[0], rtol=0, atol=1e-4)
    assert np.all(np.isfinite(outs[0]))


def test_nv_attributes_are_asked_only_of_devices_that_report_them():
    """pyopencl's kernel invoker asks every device for NVIDIA's compute capability; specgpu.engine.runtime makes that
    query only of devices with the cl_nv_device_attribute_query extension (the others would answer
    CL_INVALID_VALUE, which Oclgrind's API check reports once per kernel object)."""
    import pyopencl.characterize as characterize

    import specgpu.engine.runtime  # noqa: F401  (installs the guard)

    class Device:
        """Answers the NVIDIA queries as a real device does: with an error unless it has the extension."""

        def __init__(self, extensions, major=None):
            self.extensions, self.major, self.queried = extensions, major, False

        @property
        def compute_capability_major_nv(self):
            self.queried = True
            if self.major is None:
                raise RuntimeError("clGetDeviceInfo failed: INVALID_VALUE")
            return self.major

        compute_capability_minor_nv = 0

    other = Device("cl_khr_fp64 cl_khr_byte_addressable_store")
    assert characterize.nv_compute_capability(other) is None
    assert not other.queried
    nvidia = Device("cl_khr_fp64 cl_nv_device_attribute_query", 8)
    assert characterize.nv_compute_capability(nvidia) == (8, 0)
    assert nvidia.queried


def test_oclgrind_gets_the_integer_min_of_a_vector_and_a_scalar_wrong(oclgrind_env):
    """The reduced form of what kernels/consistency.cl avoids (tests/data/oclgrind_defects.cl): OpenCL C's
    min(int8, int) comes out wrong under Oclgrind (its sample indices were all 0, and its results off by up to 1.4
    in correlation), while the same min with the scalar made a vector is right. Should a later Oclgrind fix it,
    the first assertion fails and the kernel's vector bounds can go."""
    proc, _ = run_worker(oclgrind_env, "min_vector_scalar", checks={})
    assert proc.returncode == 0, proc.stderr[-4000:]
    record = json.loads(proc.stdout)
    expected = np.minimum(record["x"], 10).tolist()
    assert record["scalar"] != expected
    assert record["vector"] == expected


def test_min_of_a_vector_and_a_scalar_on_the_test_devices(queue):
    """The same reduced kernel on the devices the suite runs on: both forms right, so the wrong one is the
    simulator's."""
    import pyopencl as cl

    program = cl.Program(queue.context, (HERE / "data" / "oclgrind_defects.cl").read_text()).build()
    x = np.array([-3, 0, 4, 10, 11, 25, 7, 10], np.int32)
    out = run_reduced(program.min_vector_scalar, queue.context, queue, x, np.int32(10))
    np.testing.assert_array_equal(out[:8], np.minimum(x, 10))
    np.testing.assert_array_equal(out[8:], np.minimum(x, 10))


def test_oclgrind_leaves_a_host_write_at_an_offset_uninitialised(oclgrind_env):
    """Why the consistency check's cases give their gradient images as one array (engine.consistency uploads an
    array in one write, a list of planes one write per plane at its offset): Oclgrind 21.10's uninitialised-value
    check takes the part of a buffer written from the host at a nonzero offset as never written, and reports
    every value a kernel computes from it; the part written at offset 0 is clean. Reduced:
    tests/data/oclgrind_defects.cl, copy_floats."""
    proc, reports = run_worker(oclgrind_env, "offset_write", checks={"OCLGRIND_UNINITIALIZED": "1"})
    assert proc.returncode == 0, proc.stderr[-4000:]
    record = json.loads(proc.stdout)
    assert record["out"] == list(range(32))  # the values themselves arrived
    assert not reports.get("from offset 0") and reports.get("at an offset")
