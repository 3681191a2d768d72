"""The installed wheel carries kernels/ and the golden set, finds them, and builds every .cl file."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from cli_helpers import python_path

ROOT = Path(__file__).resolve().parents[2]

CHECK = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    import specgpu
    from specgpu.engine import runtime
    from specgpu.engine import selftest
    site = Path(sys.argv[1]).resolve()
    assert Path(specgpu.__file__).resolve().is_relative_to(site), specgpu.__file__
    kdir = runtime.kernel_dir()
    assert kdir.resolve() == (site / "specgpu" / "_kernels").resolve(), kdir
    sources = sorted(p.name for p in kdir.glob("*.cl"))
    assert sources == sys.argv[2].split(","), sources  # every kernel file of the repository, no other
    queue = runtime.get_queue()
    # every kernel of every file, with the colour-difference family switched on; the guided filter's two forms; the
    # warped decoders for 16-bit frames: the per-pixel one, and the translation's (built where output groups are given)
    warp = dict(K=3, B=2, IN_T="ushort", HAS_DARK=0, HAS_GAIN=0, IS_FLOAT_IN=0)
    macros = {"guided.cl": [dict(C=3, STRIPS=0), dict(C=3, STRIPS=1)],
              "register.cl": [dict(AFFINE=1, GROUP=64, HROWS=16)],
              "warp.cl": [warp, dict(warp, GROUPS=1, G0_ROWS=2, G0_IL=1)]}
    for name in sources:
        found = set()
        for m in macros.get(name, [dict(DE_METHOD=2000, K=3, B=2)]):
            program = runtime.get_program(queue.context, name, runtime.build_options(**m))
            found.update(k.function_name for k in program.program.all_kernels())
        print(name, sorted(found))
    assert selftest.golden_path().resolve().is_relative_to(site)
    report = selftest.run_selftest()
    print(report.format())
    sys.exit(0 if report.passed else 1)
    """
)


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("hatchling") is None,
                    reason="hatchling (the build backend, in the test extra) is not installed: the wheel is built "
                           "without build isolation")
def test_installed_wheel_finds_and_builds_every_kernel(tmp_path):
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(dist), str(ROOT)], check=True)
    wheels = list(dist.glob("specgpu-*.whl"))
    assert len(wheels) == 1
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site),
                    str(wheels[0])], check=True)
    kernels = ",".join(sorted(p.name for p in (ROOT / "kernels").glob("*.cl")))
    result = subprocess.run([sys.executable, "-c", CHECK, str(site), kernels], cwd=tmp_path, capture_output=True,
                            text=True,
                            env={"PYTHONPATH": python_path(site), "PATH": "/usr/bin:/bin", "HOME": str(Path.home())})
    assert result.returncode == 0, result.stdout + result.stderr
    assert "linear.cl ['linear_apply']" in result.stdout
    assert ("colorimetry.cl ['delta_e', 'delta_e_sigma', 'frames_to_delta_e', 'xyz_to_delta_e', 'xyz_to_lab']"
            in result.stdout)
    assert "guided.cl ['gf_columns_in', 'gf_columns_out', 'gf_rows', 'gf_strips']" in result.stdout
    assert "register.cl ['register_halve', 'register_search', 'register_shift', 'register_step']" in result.stdout
    assert "warp.cl ['linear_warp', 'linear_warp_translate', 'warp_correct']" in result.stdout
    assert ("consistency.cl ['consistency_bracket', 'consistency_median', 'consistency_sample', 'consistency_settle', "
            "'consistency_strips']" in result.stdout)
    assert "gradient.cl ['gradient_apply', 'gradient_scale', 'gradient_sobel']" in result.stdout
    assert "guided_variance.cl ['gv_apply', 'gv_stats']" in result.stdout
    assert "residual.cl ['residual_flag']" in result.stdout
    assert "noise_floor.cl ['floor_cols', 'floor_rows']" in result.stdout
    assert "warped_variance.cl ['warped_variances']" in result.stdout
    assert "PASS" in result.stdout


@pytest.mark.skipif(importlib.util.find_spec("hatchling") is None, reason="hatchling (the build backend) is absent")
def test_wheel_and_sdist_carry_the_license(tmp_path):
    # pyproject declares BSD-3-Clause: the licence text itself must travel with every distribution
    import tarfile
    import zipfile

    for target in ("wheel", "sdist"):
        subprocess.run([sys.executable, "-m", "hatchling", "build", "-t", target, "-d", str(tmp_path)], cwd=ROOT,
                       check=True, capture_output=True)
    wheel, = tmp_path.glob("specgpu-*.whl")
    sdist, = tmp_path.glob("specgpu-*.tar.gz")
    text = (ROOT / "LICENSE").read_text()
    assert "BSD 3-Clause License" in text and "Copyright (c) 2026, specgpu developers" in text
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        assert z.read(next(n for n in names if n.endswith(".dist-info/licenses/LICENSE"))).decode() == text
        metadata = z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert "License-Expression: BSD-3-Clause" in metadata and "License-File: LICENSE" in metadata
    with tarfile.open(sdist) as t:
        member = next(m for m in t.getmembers() if m.name.endswith("/LICENSE") and m.name.count("/") == 1)
        assert t.extractfile(member).read().decode() == text


@pytest.mark.skipif(importlib.util.find_spec("hatchling") is None, reason="hatchling (the build backend) is absent")
def test_wheel_carries_the_type_information(tmp_path):
    """py.typed (PEP 561) and every room's __init__.pyi, the names type checkers and the lazy loader read."""
    import zipfile

    subprocess.run([sys.executable, "-m", "hatchling", "build", "-t", "wheel", "-d", str(tmp_path)], cwd=ROOT,
                   check=True, capture_output=True)
    wheel, = tmp_path.glob("specgpu-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    stubs = {str(p.relative_to(ROOT)) for p in (ROOT / "specgpu").glob("*/__init__.pyi")}
    assert len(stubs) >= 9
    assert {"specgpu/py.typed", *stubs} <= names
