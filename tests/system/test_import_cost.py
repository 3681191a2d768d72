"""Importing the package, a room or io's readers is cheap: colour-science, OpenCL, zarr, Dask and matplotlib load
only in the functions that need them, and every name a room lists resolves to the object its module defines."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ROOMS = sorted(p.parent.name for p in (ROOT / "specgpu").glob("*/__init__.pyi"))
#: Each takes a tenth of a second or more to import, up to seconds for colour-science
HEAVY = ("colour", "pyopencl", "zarr", "dask", "matplotlib", "scipy", "skimage")
#: Generous: the imports measured take well under 0.3 s on an idle machine; a loaded one may take several times that
BOUND_S = 2.0


def fresh_import(statements: str) -> dict:
    """Run ``statements`` in a new interpreter: how long they took (s) and which heavy packages they loaded."""
    code = ("import sys, time, json\n"
            "t = time.perf_counter()\n"
            f"{statements}\n"
            "seconds = time.perf_counter() - t\n"
            f"heavy = sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))\n"
            "print(json.dumps({'seconds': seconds, 'heavy': heavy}))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    return json.loads(out.stdout.splitlines()[-1])


def test_importing_the_package_and_io_is_quick_and_loads_no_heavy_dependency():
    result = fresh_import("import specgpu\nimport specgpu.io")
    assert result["heavy"] == []
    assert result["seconds"] < BOUND_S


@pytest.mark.parametrize("room", ROOMS)
def test_importing_a_room_loads_no_heavy_dependency(room):
    assert fresh_import(f"import specgpu.{room}")["heavy"] == []


def test_reading_and_writing_files_needs_no_opencl_and_no_colour_science():
    """io's readers and writers (and the spectral tables' module) load none of the heavy packages until a
    function that needs one runs: a preview needs colour-science, a recording zarr."""
    result = fresh_import("from specgpu.io import read_cube, write_cube, read_map, write_map, read_sequence, "
                          "write_sequence, open_recording\n"
                          "from specgpu.io.tables import load_npz, save_npz\n"
                          "import specgpu.core.spectra, specgpu.core.validate")
    assert result["heavy"] == []


def test_the_observers_are_read_from_colour_science_on_first_use():
    from specgpu.core.spectra import OBSERVERS

    assert OBSERVERS[:2] == ("CIE 1931 2 Degree Standard Observer", "CIE 1964 10 Degree Standard Observer")
    with pytest.raises(AttributeError, match="OBSERVER"):
        importlib.import_module("specgpu.core.spectra").OBSERVER  # noqa: B018


def test_a_device_array_check_does_not_import_opencl():
    import numpy as np

    result = fresh_import("import numpy as np\nfrom specgpu.core.validate import is_device_array\n"
                          "assert not is_device_array(np.zeros(3))")
    assert "pyopencl" not in result["heavy"]
    from specgpu.core.validate import is_device_array
    from specgpu.engine.kernels import to_device
    from specgpu.engine.runtime import get_queue

    assert is_device_array(to_device(get_queue(), np.zeros(3, np.float32)))
    assert not is_device_array(np.zeros(3, np.float32))


@pytest.mark.parametrize("room", ROOMS)
def test_every_name_a_room_lists_resolves_to_its_module_object(room):
    package = importlib.import_module(f"specgpu.{room}")
    assert package.__all__, f"specgpu.{room} lists no names"
    for name in package.__all__:
        value = getattr(package, name)
        owner = getattr(value, "__module__", None)
        if owner is not None and owner.startswith(f"specgpu.{room}."):
            assert getattr(importlib.import_module(owner), name, value) is value
    assert set(dir(package)) >= set(package.__all__)
