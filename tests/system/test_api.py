"""The top-level API: every public name resolves to the object its subpackage exports, ``import specgpu`` stays
cheap (no OpenCL, no colour-science), and the engine's examples run as written."""

from __future__ import annotations

import doctest
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import specgpu

#: The public API by the subpackage that owns each name (the contract the top-level package re-exports).
API = {
    "engine": ["apply_linear", "XYZ_to_Lab", "delta_E", "reflectance_to_XYZ", "frames_to_delta_E", "get_queue",
               "run_selftest"],
    "core": ["XYZ_weights"],
    "io": ["read_cube", "write_cube", "read_map", "write_map", "read_sequence", "write_sequence", "open_recording"],
    "planning": ["make_plan", "load_plan", "save_plan", "Plan", "PLAN_METHODS"],
    "calibration": ["calibrate", "load_calibration", "save_calibration", "CalibrationBundle"],
    "pipeline": ["recover", "read_capture", "capture_plan", "evaluate_reflectance", "evaluate_pixels",
                 "render_scene"],
    "rig": ["load_rig", "dump_rig", "colorchecker_scene", "load_scene"],
}
NAMES = [(room, name) for room, names in API.items() for name in names]


@pytest.mark.parametrize(("room", "name"), NAMES, ids=[f"{room}.{name}" for room, name in NAMES])
def test_each_public_name_is_the_object_its_subpackage_exports(room, name):
    package = importlib.import_module(f"specgpu.{room}")
    assert getattr(specgpu, name) is getattr(package, name)
    assert name in package.__all__


def test_the_listed_names_are_exactly_the_top_level_api():
    assert sorted(specgpu.__all__) == sorted(name for _, name in NAMES)
    assert set(dir(specgpu)) >= {name for _, name in NAMES}


def test_importing_specgpu_loads_neither_opencl_nor_colour_science():
    code = ("import sys, specgpu\n"
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('pyopencl', 'colour', 'numpy')\n"
            "               or m.startswith('specgpu.'))\n"
            "print(','.join(heavy))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_a_public_name_imports_only_its_own_subpackage_on_first_use():
    code = ("import sys, specgpu\n"
            "specgpu.read_cube\n"
            "print('specgpu.engine' in sys.modules, 'specgpu.io' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]


def test_a_wrong_attribute_is_an_attribute_error_naming_it():
    with pytest.raises(AttributeError, match="apply_lineer"):
        specgpu.apply_lineer  # noqa: B018
    assert not hasattr(specgpu, "xyz_to_lab")


def test_the_version_is_kept():
    assert isinstance(specgpu.__version__, str) and specgpu.__version__.count(".") == 2


ENGINE_EXAMPLES = [("engine", name) for name in API["engine"]] + [("core", "XYZ_weights")]


@pytest.mark.parametrize(("room", "name"), ENGINE_EXAMPLES, ids=[f"{r}.{n}" for r, n in ENGINE_EXAMPLES])
def test_the_docstring_example_runs_as_written(room, name):
    function = getattr(importlib.import_module(f"specgpu.{room}"), name)
    tests = doctest.DocTestFinder(recurse=False).find(function, name, globs={})
    assert tests and tests[0].examples, f"{name} has no >>> example"
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    for test in tests:
        runner.run(test)
    assert runner.failures == 0, f"{runner.failures} of the examples of {name} failed (output above)"


def test_a_name_two_rooms_export_is_one_object():
    """One name, one meaning: no two rooms export different objects under the same name."""
    seen: dict[str, tuple[str, object]] = {}
    clashes = []
    for room in sorted(p.parent.name for p in Path(specgpu.__file__).parent.glob("*/__init__.pyi")):
        package = importlib.import_module(f"specgpu.{room}")
        for name in package.__all__:
            value = getattr(package, name)
            if name in seen and seen[name][1] is not value:
                clashes.append(f"{name}: specgpu.{seen[name][0]} and specgpu.{room}")
            seen.setdefault(name, (room, value))
    assert not clashes, clashes


#: What a room's list may hold at most: its users' surface, not every helper it has
MAX_ROOM_NAMES = 50


def room_names() -> dict[str, list[str]]:
    rooms = sorted(p.parent.name for p in Path(specgpu.__file__).parent.glob("*/__init__.pyi"))
    return {room: importlib.import_module(f"specgpu.{room}").__all__ for room in rooms}


def test_a_room_lists_its_users_surface_not_its_helpers():
    sizes = {room: len(names) for room, names in room_names().items()}
    assert max(sizes.values()) <= MAX_ROOM_NAMES, sizes
    listed = {name for names in room_names().values() for name in names}
    # the write helpers of io.paths and the validators of core.validate serve the rooms, through their modules
    helpers = {"atomic_path", "disk_full", "error_of", "final_name", "new_temporary", "os_error", "replace_with",
               "write_failed", "write_target", "check_array", "check_frames", "check_matrix", "as_float32", "one_line"}
    assert not listed & helpers


def test_every_listed_function_and_class_is_documented():
    undocumented = []
    for room, names in room_names().items():
        package = importlib.import_module(f"specgpu.{room}")
        for name in names:
            value = getattr(package, name)
            if callable(value) and not (value.__doc__ or "").strip():
                undocumented.append(f"specgpu.{room}.{name}")
    assert not undocumented, undocumented


#: The least share of the listed functions' parameters that carry an annotation (py.typed promises types)
MIN_ANNOTATED = 0.75


def listed_signatures():
    """(qualified name, inspect.Signature) of every function a room lists, and of its listed classes' methods."""
    import inspect

    for room, names in room_names().items():
        package = importlib.import_module(f"specgpu.{room}")
        for name in names:
            value = getattr(package, name)
            if inspect.isclass(value):
                members = [(f"{name}.{m}", f) for m, f in vars(value).items()
                           if inspect.isfunction(f) and (m == "__init__" or not m.startswith("_"))]
            elif inspect.isfunction(value):
                members = [(name, value)]
            else:
                continue
            for qualified, function in members:
                yield f"specgpu.{room}.{qualified}", inspect.signature(function)


def test_the_listed_functions_are_annotated():
    params = [(where, p) for where, sig in listed_signatures() for p in sig.parameters.values()
              if p.name not in ("self", "cls")]
    annotated = sum(p.annotation is not p.empty for _, p in params)
    assert len(params) > 500
    assert annotated / len(params) >= MIN_ANNOTATED, f"{annotated} of {len(params)} parameters annotated"


@pytest.mark.parametrize(("room", "name", "parameter"), [
    ("engine", "apply_linear", "frames"), ("engine", "reflectance_to_XYZ", "R"),
    ("io", "write_cube", "cube"), ("io", "write_cube", "wavelengths"), ("core", "XYZ_weights", "wavelengths"),
    ("pipeline", "evaluate_reflectance", "cube"),
])
def test_arrays_going_in_are_array_like(room, name, parameter):
    import inspect

    function = getattr(importlib.import_module(f"specgpu.{room}"), name)
    assert "ArrayLike" in str(inspect.signature(function).parameters[parameter].annotation)
