"""The documentation site's own machinery: the API pages follow each room's ``__all__``, the measured figures
carry their command, date and machine, and every page has its title."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem + "_under_test", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_api_pages_list_each_room_public_names_in_layer_order(tmp_path):
    api = load(DOCS / "_ext" / "api_pages.py")
    rooms = api.write_api_pages(tmp_path)
    assert rooms[0] == "core" and rooms[-1] == "pipeline" and "apps" not in rooms  # apps exports nothing
    import specgpu.io

    page = (tmp_path / "io.rst").read_text()
    listed = re.findall(r"^   (\w+)$", page.split(".. autosummary::", 1)[1], flags=re.M)
    assert listed == list(specgpu.io.__all__)
    index = (tmp_path / "index.rst").read_text()
    entries = [line.strip() for line in index.split(":maxdepth: 1", 1)[1].splitlines() if line.strip()]
    assert entries == ["specgpu", *rooms]
    top = (tmp_path / "specgpu.rst").read_text()
    assert "   specgpu.engine.apply_linear" in top and "   specgpu.io.read_cube" in top


def test_api_pages_follow_a_room_export_that_changes(tmp_path, monkeypatch):
    api = load(DOCS / "_ext" / "api_pages.py")
    import specgpu.rig

    monkeypatch.setattr(specgpu.rig, "__all__", ["load_rig", "dump_rig", "colorchecker_scene", "load_scene"])
    api.write_api_pages(tmp_path)
    listed = re.findall(r"^   (\w+)$", (tmp_path / "rig.rst").read_text(), flags=re.M)
    assert listed == ["load_rig", "dump_rig", "colorchecker_scene", "load_scene"]


def test_every_committed_result_says_its_command_date_and_machine():
    refresh = load(DOCS / "results" / "refresh.py")
    results = sorted((DOCS / "results").glob("*.json"))
    assert {p.stem for p in results} == set(refresh.COMMANDS)
    for path in results:
        record = json.loads(path.read_text())
        assert record["command"] == refresh.COMMANDS[path.stem]
        assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC", record["date_utc"])
        assert record["machine"]["cpu"] and record["machine"]["cores"] >= 1
        assert record["result"]


def test_refresh_refuses_an_unknown_result_in_one_line(capsys):
    refresh = load(DOCS / "results" / "refresh.py")
    assert refresh.main(["nonesuch"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'nonesuch'" in err[0] and "bench" in err[0]


def test_results_tables_render_with_their_provenance():
    pytest.importorskip("docutils")
    results = load(DOCS / "_ext" / "results.py")
    record = json.loads((DOCS / "results" / "bench.json").read_text())
    line = results.provenance(record).astext()
    assert record["date_utc"] in line and record["machine"]["cpu"] in line and record["command"] in line
    nodes = results.render_bench(record["result"])
    text = " ".join(n.astext() for n in nodes)
    assert record["result"]["cases"][0]["case"] in text
    accuracy = json.loads((DOCS / "results" / "accuracy.json").read_text())["result"]
    text = " ".join(n.astext() for n in results.render_accuracy(accuracy))
    assert "symmetric" in text and f"{accuracy['methods']['symmetric']['rmse'][0]:.3g}" in text


def test_every_page_has_one_title():
    pages = [p for p in DOCS.rglob("*.md") if p.relative_to(DOCS).parts[0] not in ("_build", "api", "auto_examples")]
    assert len(pages) > 15
    def headings(text):  # a comment line in a fenced code block is not a heading
        return re.findall(r"^# \S", re.sub(r"^```.*?^```", "", text, flags=re.M | re.S), flags=re.M)

    untitled = [str(p.relative_to(ROOT)) for p in pages if len(headings(p.read_text())) != 1]
    assert not untitled, untitled


def _sphinx_build(tmp_path, body: str) -> tuple[int, str]:
    """A one-page Sphinx project using the site's reference resolver, built with -W -n; (status, warnings)."""
    build_main = pytest.importorskip("sphinx.cmd.build").build_main
    src = tmp_path / "src"
    src.mkdir()
    (src / "conf.py").write_text(f"import sys\nsys.path.insert(0, {str(DOCS / '_ext')!r})\n"
                                 f"sys.path.insert(0, {str(ROOT)!r})\n"
                                 "extensions = ['sphinx.ext.autodoc', 'api_aliases']\n")
    (src / "index.rst").write_text("Test\n====\n\n.. autofunction:: specgpu.io.open_recording\n\n" + body + "\n")
    warnings = tmp_path / "warnings.txt"
    status = build_main(["-q", "-W", "-n", "-w", str(warnings), "-b", "html", str(src), str(tmp_path / "out")])
    return status, warnings.read_text() if warnings.exists() else ""


def test_a_reference_by_another_name_of_a_documented_object_resolves(tmp_path):
    status, warnings = _sphinx_build(tmp_path, "See :func:`specgpu.io.recording.open_recording` and "
                                               ":mod:`specgpu.io.recording`.")
    assert status == 0, warnings
    page = (tmp_path / "out" / "index.html").read_text()
    assert 'href="#specgpu.io.open_recording"' in page  # linked to where it is documented


def test_a_stale_reference_fails_the_strict_build(tmp_path):
    status, warnings = _sphinx_build(tmp_path, "See :func:`specgpu.io.recording.no_such_reader`.")
    assert status != 0 and "specgpu.io.recording.no_such_reader" in warnings
