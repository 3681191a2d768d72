"""The package's layout rules hold (docs/architecture.md, "Rules"): the rooms import only downward (the import-linter
contracts of pyproject.toml, function-local imports included), no private name crosses a room, function-local
imports only for optional heavy dependencies, small modules, a thin CLI, and no citation of anything outside the
repository."""

from __future__ import annotations

import ast
import functools
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

from cli_helpers import python_path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "specgpu"

MAX_MODULE_LINES = 700
MAX_COMMAND_LINES = 40
TOP_LEVEL_FILES = {"__init__.py", "__main__.py", "py.typed"}
# optional or heavy third-party packages a function may import when it needs them (and only these)
LOCAL_IMPORTS_ALLOWED = {"dask", "zarr", "numcodecs", "distributed", "napari", "usb", "harvesters", "genicam",
                         "seabreeze", "scipy", "matplotlib", "colour",
                         # the LED controller's pyserial; the OL490's pythonnet (clr) and the .NET namespace it opens
                         "serial", "clr", "System",
                         # the Qt shim napari ships: the spectrum widget's Qt classes, only with the viewer extra
                         "qtpy"}


def parsed(path: Path) -> ast.Module:
    """The syntax tree of a source file, parsed once per version of it (several checks read every module)."""
    stat = path.stat()
    return _parse(str(path), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=1024)
def _parse(path: str, mtime_ns: int, size: int) -> ast.Module:
    return ast.parse(Path(path).read_text(), path)


# --- the import-linter contracts -----------------------------------------------------------------------------------

def lint_imports(cwd: Path) -> subprocess.CompletedProcess:
    """Run import-linter on the package found under ``cwd`` (its pyproject.toml holds the contracts)."""
    code = ("import sys; from importlinter.cli import lint_imports_command; "
            "sys.argv = ['lint-imports', '--no-cache', '--no-logo']; lint_imports_command()")
    env = {**os.environ, "PYTHONPATH": python_path(cwd)}
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


def contracts() -> list[dict]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]


def rooms() -> set[str]:
    """The rooms the layers contract names (``specgpu.io | specgpu.engine`` is two rooms on one layer)."""
    layers, = [c["layers"] for c in contracts() if c["type"] == "layers"]
    return {name.strip().split(".")[1] for layer in layers for name in re.split(r"[|:]", layer)}


def test_import_contracts_are_kept():
    result = lint_imports(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"Contracts: {len(contracts())} kept, 0 broken." in result.stdout


def test_import_contract_catches_an_upward_import(tmp_path):
    """An upward import, even inside a function, breaks the contract: the check cannot pass vacuously."""
    shutil.copytree(PACKAGE, tmp_path / "specgpu", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    with open(tmp_path / "specgpu" / "core" / "numerics.py", "a") as f:
        f.write("\n\ndef upward():\n    import specgpu.apps.cli  # noqa: F401\n")
    result = lint_imports(tmp_path)
    assert result.returncode != 0, result.stdout + result.stderr
    assert "Rooms import only downward BROKEN" in result.stdout
    assert "specgpu.core.numerics -> specgpu.apps.cli" in result.stdout, result.stdout


def test_every_room_is_in_the_layers_contract():
    """The top level holds only the package's entry files and the rooms the contract places on a layer."""
    entries = [p for p in PACKAGE.iterdir() if p.name != "__pycache__"]
    files = {p.name for p in entries if not p.is_dir()}
    folders = {p.name for p in entries if p.is_dir()}
    assert files <= TOP_LEVEL_FILES, sorted(files - TOP_LEVEL_FILES)
    assert folders == rooms(), (sorted(folders - rooms()), sorted(rooms() - folders))


# --- checks over the source ----------------------------------------------------------------------------------------

def modules(root: Path = PACKAGE) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package under ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def room(module: str, root: Path = PACKAGE) -> str:
    """``specgpu.io.cube`` -> ``io``; the package's own top-level files are the room ``specgpu``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and (root / parts[1]).is_dir() else parts[0]


def private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def absolute(module: str, node: ast.ImportFrom, is_package: bool) -> str:
    """The absolute module an ``from ... import`` names, relative imports resolved."""
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base[:len(base) - node.level + (1 if is_package else 0)]
    return ".".join(base + ([node.module] if node.module else []))


def private_crossings(root: Path = PACKAGE) -> list[str]:
    """``file:line: name`` for every private name (module or attribute) one room takes from another."""
    known = modules(root)
    found = []
    for module, path in known.items():
        own = room(module, root)
        tree = parsed(path)
        aliases: dict[str, str] = {}  # local name -> specgpu module it stands for
        where = f"{path.relative_to(root.parent)}"

        def check(target: str, name: str, line: int) -> None:
            if target.split(".")[0] == "specgpu" and room(target, root) != own:
                dotted = f"{target}.{name}" if name else target
                if any(private(p) for p in dotted.split(".")[1:]):
                    found.append(f"{where}:{line}: {dotted}")

        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    check(a.name, "", node.lineno)
                    if a.name.startswith("specgpu"):
                        aliases[a.asname or a.name] = a.name if a.asname else a.name.split(".")[0]
            elif isinstance(node, ast.ImportFrom):
                target = absolute(module, node, path.name == "__init__.py")
                for a in node.names:
                    check(target, a.name, node.lineno)
                    if f"{target}.{a.name}" in known:
                        aliases[a.asname or a.name] = f"{target}.{a.name}"
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and private(node.attr):
                chain, inner = [], node.value
                while isinstance(inner, ast.Attribute):
                    chain.append(inner.attr)
                    inner = inner.value
                if isinstance(inner, ast.Name) and inner.id in aliases:
                    target = ".".join([aliases[inner.id], *reversed(chain)])
                    if target in known:
                        check(target, node.attr, node.lineno)
    return found


def local_imports(root: Path = PACKAGE) -> list[tuple[str, str]]:
    """(``file:line``, imported module) for every import inside a function."""
    found = []
    functions = (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)
    for module, path in modules(root).items():
        tree = parsed(path)
        inner = {node for func in ast.walk(tree) if isinstance(func, functions)
                 for node in ast.walk(func) if isinstance(node, (ast.Import, ast.ImportFrom))}
        for node in inner:
            where = f"{path.relative_to(root.parent)}:{node.lineno}"
            if isinstance(node, ast.Import):
                found += [(where, a.name) for a in node.names]
            else:
                found.append((where, absolute(module, node, path.name == "__init__.py")))
    return sorted(set(found))


def test_no_private_name_crosses_a_room():
    assert not private_crossings(), "\n".join(private_crossings())


def test_no_function_imports_a_specgpu_module():
    """A local import of the package's own code hides a cycle: the code belongs to the layer that owns it."""
    bad = [f"{w}: {m}" for w, m in local_imports() if m.split(".")[0] == "specgpu"]
    assert not bad, f"{len(bad)} function-local imports of specgpu modules:\n" + "\n".join(bad)


def test_function_local_imports_are_only_optional_heavy_dependencies():
    bad = [f"{w}: {m}" for w, m in local_imports()
           if m.split(".")[0] not in LOCAL_IMPORTS_ALLOWED | {"specgpu"}]
    assert not bad, f"{len(bad)} function-local imports outside {sorted(LOCAL_IMPORTS_ALLOWED)}:\n" + "\n".join(bad)


def test_no_module_is_over_700_lines():
    sizes = {str(p.relative_to(ROOT)): len(p.read_text().splitlines()) for p in modules().values()}
    big = {name: n for name, n in sizes.items() if n > MAX_MODULE_LINES}
    assert not big, big


def command_bodies(root: Path = PACKAGE) -> dict[str, int]:
    """``file:function`` -> lines of its body (the docstring left out), for every click command or group under
    ``apps/cli``."""
    cli = root / "apps"
    paths = sorted((cli / "cli").rglob("*.py"))
    out = {}
    for path in paths:
        for node in ast.walk(parsed(path)):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if not any(re.search(r"\.(command|group)\b|^(command|group)\b", ast.unparse(d))
                       for d in node.decorator_list):
                continue
            body = node.body
            if (isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                    and isinstance(body[0].value.value, str) and len(body) > 1):
                body = body[1:]
            out[f"{path.relative_to(root.parent)}:{node.name}"] = node.end_lineno - body[0].lineno + 1
    return out


def test_cli_commands_only_parse_and_call():
    bodies = command_bodies()
    assert len(bodies) >= 10  # the commands are found
    long = {name: n for name, n in bodies.items() if n > MAX_COMMAND_LINES}
    assert not long, long


# a citation of a file outside the repository (the planning notes, the work machine's folders), or of an issue /
# item number of the tracker
CITATION = re.compile(r"\b(?:DESIGN|GPU|PAPER)\.md\b|(?<![\w.])/wor(?:k)/|\b(?:issue|item)s?\s+#?\d+", re.I)
TEXT_SUFFIXES = {".py", ".md", ".toml", ".txt", ".cfg", ".ini", ".json", ".sh", ".cl", ".yaml", ".yml", ".rst"}


def test_nothing_cites_a_file_outside_the_repository_or_an_issue_number():
    paths = [ROOT / "README.md"]
    for folder in ("specgpu", "tests", "tools", "docs"):
        paths += [p for p in (ROOT / folder).rglob("*") if p.suffix in TEXT_SUFFIXES and p.is_file()]
    found = []
    for path in paths:
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            found += [f"{path.relative_to(ROOT)}:{number}: {m.group(0)}" for m in CITATION.finditer(line)]
    assert not found, "\n".join(found)


# a path inside the repository, as prose cites it (``tests/io/test_zarr.py``); globs and placeholders are left out
CITED_PATH = re.compile(r"(?<![\w/.-])(?:specgpu|tests|tools|kernels|docs)/[\w/.-]*\w\.(?:py|md|cl|h|npz|toml|sh)\b")


def cited_paths() -> list[str]:
    paths = [ROOT / "README.md", ROOT / "pyproject.toml"]
    for folder in ("specgpu", "tests", "tools", "docs"):
        paths += [p for p in (ROOT / folder).rglob("*") if p.suffix in TEXT_SUFFIXES and p.is_file()]
    found = []
    for path in paths:
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            found += [(f"{path.relative_to(ROOT)}:{number}", m.group(0)) for m in CITED_PATH.finditer(line)]
    return found


def test_every_repository_path_cited_exists():
    """Files moved into rooms leave no stale path behind in the prose (README, docstrings, comments)."""
    cited = cited_paths()
    assert len(cited) > 10  # the pattern finds the README's citations
    wheel = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["hatch"]["build"]["targets"]["wheel"]
    packaged = tuple(wheel["force-include"].values())  # paths only the wheel has (specgpu/_kernels ...)
    missing = [f"{where}: {path}" for where, path in cited
               if not (ROOT / path).exists() and not path.startswith(packaged)]
    assert not missing, "\n".join(missing)


# --- the checks find what they look for ----------------------------------------------------------------------------

def test_the_source_checks_find_planted_faults(tmp_path):
    """Each source check flags a planted fault, and a room's own ``__init__`` re-exporting its modules is fine."""
    pkg = tmp_path / "specgpu"
    for folder in ("core", "io", "apps/cli"):
        (pkg / folder).mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "core" / "__init__.py").write_text("from specgpu.core.spectra import _grid, spectra_of\n"
                                              "from . import spectra\n")
    (pkg / "core" / "spectra.py").write_text("def _grid(): pass\ndef spectra_of(): pass\n")
    (pkg / "io" / "__init__.py").write_text("")
    (pkg / "io" / "npz.py").write_text(
        "import specgpu.core.spectra as sp\n"
        "from specgpu.core import spectra\n"
        "from specgpu.core.spectra import _grid\n"
        "def read():\n"
        "    import zarr\n"
        "    import colour\n"
        "    from ..core import spectra as s\n"
        "    return sp._grid, spectra._grid, s.spectra_of, sp.__name__\n")
    (pkg / "apps" / "__init__.py").write_text("")
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_COMMAND_LINES + 1))
    (pkg / "apps" / "cli" / "group.py").write_text(
        "import click\n@click.group()\ndef main():\n    '''doc'''\n\n"
        f"@main.command()\n@click.option('--a')\ndef long(a):\n    '''doc'''\n{body}\n"
        "@main.command('short')\ndef short():\n    '''doc'''\n    return 1\n")

    assert private_crossings(pkg) == ["specgpu/io/npz.py:3: specgpu.core.spectra._grid",
                                      "specgpu/io/npz.py:8: specgpu.core.spectra._grid",
                                      "specgpu/io/npz.py:8: specgpu.core.spectra._grid"]
    assert local_imports(pkg) == [("specgpu/io/npz.py:5", "zarr"), ("specgpu/io/npz.py:6", "colour"),
                                  ("specgpu/io/npz.py:7", "specgpu.core")]
    assert command_bodies(pkg) == {"specgpu/apps/cli/group.py:main": 1,
                                   "specgpu/apps/cli/group.py:long": MAX_COMMAND_LINES + 1,
                                   "specgpu/apps/cli/group.py:short": 1}
    assert CITATION.search("as issue " "19 says") and CITATION.search("see Item " "#7") and CITATION.search("GPU" ".md")
    assert CITATION.search("run /" "work/venv/bin/python")
    assert not CITATION.search("the items of the list") and not CITATION.search("issue_id = 3")


# --- the rig's light registers as a capture light source -----------------------------------------------------------

def test_programmable_light_is_a_light_source_once_capture_is_loaded():
    import specgpu.capture.twin_driver  # noqa: F401  (registers the twin's light)
    from specgpu.capture.driver import LightSource
    from specgpu.rig.light import ProgrammableLight

    assert isinstance(ProgrammableLight(), LightSource)


def test_tests_import_their_helpers_as_ci_runs_them():
    """`pytest` (as CI runs it) puts tests/ on the path, not the repository: a helper is `cli_helpers`, never
    `tests.cli_helpers`, which imports only under `python -m pytest` from the repository's root."""
    bad = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.walk(parsed(path)):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            bad += [f"{path.relative_to(ROOT)}:{node.lineno}" for n in names if n.split(".")[0] == "tests"]
    assert not bad, bad


# --- the tests keep to the layers too ------------------------------------------------------------------------------

def _imports(path: Path) -> list[tuple[int, list[str]]]:
    """(line, the modules one import statement names) for every absolute import of a file, in functions too;
    ``from specgpu import apps`` names ``specgpu`` and ``specgpu.apps``."""
    out = []
    for node in ast.walk(parsed(path)):
        if isinstance(node, ast.Import):
            out.append((node.lineno, [a.name for a in node.names]))
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, [node.module] + [f"{node.module}.{a.name}" for a in node.names]))
    return sorted(out)


def _is_apps(module: str) -> bool:
    return module == "specgpu.apps" or module.startswith("specgpu.apps.")


def apps_imports(tests: Path = ROOT / "tests") -> list[str]:
    """``file:line: chain`` for every import by which a test of a room below ``apps`` (a file under
    ``tests/<room>/``, or the ``conftest.py`` every test runs under) reaches ``specgpu.apps``: directly, or through
    the helpers beside the room folders (``cli_helpers`` imports the command line), however deep."""
    helpers = {p.stem: p for p in tests.glob("*.py")}
    reached: dict[str, str | None] = {}

    def reach(stem: str, seen: frozenset = frozenset()) -> str | None:
        """The chain by which helper ``stem`` reaches ``specgpu.apps``, or None."""
        if stem not in reached:
            chain = None
            for _, names in _imports(helpers[stem]):
                chain = next((n for n in names if _is_apps(n)), None)
                tops = [n for n in names if n in helpers and n not in seen | {stem}]
                chain = chain or next((f"{t} -> {c}" for t in tops if (c := reach(t, seen | {stem}))), None)
                if chain:
                    break
            reached[stem] = chain
        return reached[stem]

    paths = [tests / "conftest.py"] if (tests / "conftest.py").exists() else []
    for room in sorted(rooms() - {"apps"}):
        paths += sorted((tests / room).rglob("*.py"))
    found = []
    for path in paths:
        for line, names in _imports(path):
            chain = next((n for n in names if _is_apps(n)), None)
            chain = chain or next((f"{n} -> {reach(n)}" for n in names if n in helpers and reach(n)), None)
            if chain:
                found.append(f"{path.relative_to(tests.parent)}:{line}: {chain}")
    return found


def test_no_test_of_a_lower_room_imports_apps():
    """A room's tests need nothing above it: a test of the command line (or the demo, the viewer, the bench) lives
    in tests/apps/, so the rooms below can be tested, and moved, without the programs built on them."""
    found = apps_imports()
    assert not found, "\n".join(found)


def test_the_apps_import_check_finds_planted_imports(tmp_path):
    tests = tmp_path / "tests"
    for folder in ("io", "pipeline", "apps"):
        (tests / folder).mkdir(parents=True)
    (tests / "cli_helpers.py").write_text("from specgpu.apps.cli import main\n")
    (tests / "deep_helpers.py").write_text("import numpy\nimport cli_helpers\n")
    (tests / "plain_helpers.py").write_text("from specgpu.io import read_cube\n")
    (tests / "io" / "test_a.py").write_text("import plain_helpers\n\ndef test():\n    from specgpu import apps\n")
    (tests / "io" / "test_b.py").write_text("from deep_helpers import x\nimport specgpu.pipeline\n")
    (tests / "pipeline" / "test_c.py").write_text("import specgpu.apps.demo as demo\n")
    (tests / "apps" / "test_d.py").write_text("from cli_helpers import run\nfrom specgpu.apps.cli import main\n")
    at = "tests/{}.py:{}: ".format  # (a path in prose would be checked as a citation of a file that exists)
    assert apps_imports(tests) == [at("io/test_a", 4) + "specgpu.apps",
                                   at("io/test_b", 1) + "deep_helpers -> cli_helpers -> specgpu.apps.cli",
                                   at("pipeline/test_c", 1) + "specgpu.apps.demo"]
