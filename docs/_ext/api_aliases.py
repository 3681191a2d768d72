"""Cross-references to the package's objects by any of their names.

Docstrings name an object where it is defined (``specgpu.io.recording.open_recording``), the API reference
documents it where its room exports it (``specgpu.io.open_recording``). A Python reference Sphinx cannot find is
resolved here by importing what it names: an object the reference documents under another name links there; an
object that exists but has no page of its own (a module, a room's internal helper) is shown as code, unlinked.
A name that does not import stays unresolved, and ``-n`` reports it: a stale reference fails the build.
"""

from __future__ import annotations

import importlib
import inspect
import re
import sys

from docutils import nodes
from docutils.utils import get_source_line
from sphinx.util.nodes import make_refnode

FIELD = object()  # what _import gives for a dataclass field: it exists, with no object of its own
MISSING = object()  # what _import gives for a name that does not exist


def _import(path: str):
    """The object a dotted path names, :data:`FIELD` for a dataclass field without one, or :data:`MISSING`."""
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attribute in parts[cut:]:
            try:
                obj = getattr(obj, attribute)
            except AttributeError:
                # a dataclass field without a default is no class attribute, yet it exists
                fields = getattr(obj, "__dataclass_fields__", {}) if inspect.isclass(obj) else {}
                return FIELD if attribute in fields and attribute == parts[-1] else MISSING
        return obj
    return MISSING


def _scopes(path: str) -> list[str]:
    """The names a reference in the docstring of ``path`` is relative to: the object's own dotted path and that
    of the place it is defined, each with its parents, innermost first."""
    obj = _import(path)
    paths = [path]
    home = getattr(obj, "__module__", None)
    if isinstance(home, str) and hasattr(obj, "__qualname__"):
        paths.append(f"{home}.{obj.__qualname__}")
    out = []
    for p in paths:
        parts = p.split(".")
        out += [".".join(parts[:cut]) for cut in range(len(parts), 0, -1)]
    return out


def _candidates(node) -> list[str]:
    target = node["reftarget"].lstrip("~.")
    contexts = []
    source = get_source_line(node)[0] or ""
    found = re.search(r"docstring of ([\w.]+)", source)
    if found:
        contexts.append(found.group(1))
    row = node.parent
    while row is not None and not isinstance(row, nodes.row):
        row = row.parent
    if row is not None and len(row.children) > 1:  # an autosummary line: relative to the object of its row
        name = row.children[0].astext().split("(")[0].strip()
        room = node.get("py:module")
        contexts.append(name if name.startswith("specgpu") or not room else f"{room}.{name}")
    docname = node.get("refdoc", "")
    if docname.startswith("api/generated/"):
        contexts.append(docname.rsplit("/", 1)[1])
    module, cls = node.get("py:module"), node.get("py:class")
    if module and cls:
        contexts.append(f"{module}.{cls}")
    if module:
        contexts.append(module)
    out = [target]
    for context in contexts:
        out += [f"{scope}.{target}" for scope in _scopes(context)]
    return [name for name in dict.fromkeys(out) if name.startswith("specgpu")]


def _defined_once(target: str) -> str | None:
    """``module.target`` for a specgpu module holding ``target``'s first name, when every specgpu module that holds
    that name holds the same object (an autosummary line is read on the room's page, away from the module its
    relative reference was written in), else None."""
    head = target.split(".", 1)[0]
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("specgpu.") and module is not None and head in vars(module):
            found.setdefault(id(vars(module)[head]), name)
    return f"{found.popitem()[1]}.{target}" if len(found) == 1 else None


def _documented(env) -> dict[int, tuple[str, str]]:
    """id(object) -> (docname, full name) of every object the reference documents."""
    cache = getattr(env, "_specgpu_documented", None)
    if cache is None:
        cache = {}
        for name, entry in env.get_domain("py").objects.items():
            obj = _import(name)
            if obj is not MISSING and obj is not None and not isinstance(obj, (int, float, str, tuple, bool)):
                cache.setdefault(id(obj), (entry.docname, entry.node_id))
        env._specgpu_documented = cache
    return cache


def resolve(app, env, node, contnode):
    if node.get("refdomain") != "py":
        return None
    fallback = _defined_once(node["reftarget"].lstrip("~."))
    for name in [*_candidates(node), *([fallback] if fallback else [])]:
        obj = _import(name)
        if obj is MISSING:
            continue
        found = None if obj is FIELD or obj is None else _documented(env).get(id(obj))
        if found is not None:
            docname, anchor = found
            return make_refnode(app.builder, node["refdoc"], docname, anchor, contnode, name)
        return nodes.literal(name, contnode.astext())  # exists, has no page of its own
    return None


def no_borrowed_docstring(app, what, name, obj, options, lines):
    """A module constant (an array, a dict) has no docstring of its own: autodoc would show its type's."""
    if what in ("data", "attribute") and lines and not inspect.isclass(obj) and not callable(obj):
        if inspect.getdoc(obj) == inspect.getdoc(type(obj)):
            lines[:] = []


def forget(app, env, *args):
    env.__dict__.pop("_specgpu_documented", None)


def setup(app):
    app.connect("missing-reference", resolve)
    app.connect("autodoc-process-docstring", no_borrowed_docstring)
    app.connect("env-updated", forget)
    app.connect("env-before-read-docs", forget)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
