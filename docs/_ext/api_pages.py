"""The API reference's pages, written from the package itself before Sphinx reads its sources.

One page per room (``specgpu.<room>``, in the layers' order, bottom first) with an ``autosummary`` over the
room's ``__all__``, and one page for the top-level names ``import specgpu`` re-exports. A name added to or
removed from a room's ``__all__`` appears on or leaves its page at the next build: nothing is listed by hand.
"""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def rooms() -> list[str]:
    """The rooms, bottom layer first, as the import-linter layers contract of ``pyproject.toml`` names them."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    layers = next(c["layers"] for c in config if c["type"] == "layers")
    names = [name.strip() for layer in reversed(layers) for name in layer.split("|")]
    return [name.split(".", 1)[1] for name in names]


def public_names(module: str) -> list[str]:
    return list(getattr(importlib.import_module(module), "__all__", []))


def _write(path: Path, text: str) -> None:
    if not path.exists() or path.read_text() != text:  # unchanged pages keep their time: no needless re-read
        path.write_text(text)


def write_api_pages(folder: Path) -> list[str]:
    """Write ``index.rst``, ``specgpu.rst`` and one ``<room>.rst`` per room into ``folder``; returns the rooms
    with a page (a room whose ``__all__`` is empty, such as ``apps``, has none: its programs are the CLI)."""
    folder.mkdir(exist_ok=True)
    documented = []
    for room in rooms():
        module = f"specgpu.{room}"
        names = public_names(module)
        if not names:
            continue
        documented.append(room)
        title = f"``{module}``"
        _write(folder / f"{room}.rst", "\n".join([
            title, "=" * len(title), "",
            f".. automodule:: {module}", "   :no-members:", "",
            f".. currentmodule:: {module}", "",
            ".. autosummary::", "   :toctree: generated", "   :nosignatures:", "",
            *(f"   {name}" for name in names), ""]))
    top = importlib.import_module("specgpu")
    rows = []
    for name in top.__all__:
        owner = next(r for r in documented if name in public_names(f"specgpu.{r}"))
        rows.append(f"   specgpu.{owner}.{name}")
    _write(folder / "specgpu.rst", "\n".join([
        "``import specgpu``", "==================", "",
        "The names ``import specgpu`` gives, each loaded from its room on first use (``specgpu.apply_linear`` is",
        "``specgpu.engine.apply_linear``).", "",
        ".. autosummary::", "   :nosignatures:", "", *rows, ""]))
    _write(folder / "index.rst", "\n".join([
        "API reference", "=============", "",
        "The public names of each room (its ``__all__``), bottom layer first; :doc:`/architecture` says what each",
        "room owns and why.", "",
        ".. toctree::", "   :maxdepth: 1", "", "   specgpu", *(f"   {room}" for room in documented), ""]))
    return documented
