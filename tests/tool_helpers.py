"""Load a module of ``tools/`` from its file: ``tools/`` is outside the package and not a package itself."""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[1] / "tools"


@functools.cache
def load_tool(relative: str):
    """The module of ``tools/<relative>`` (``"studies/estimator_rows.py"``), executed once per test session.

    Parameters
    ----------
    relative : str
        The file's path under ``tools/``.

    Returns
    -------
    module
        The loaded module, named after the file's stem.
    """
    path = TOOLS / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
