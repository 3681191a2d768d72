"""Every benchmark and study script under ``tools/`` still imports: they live outside the package and the suite
runs none of them whole, so a name moved or removed in the package would otherwise break them unseen."""

from __future__ import annotations

import pytest
from tool_helpers import TOOLS, load_tool

SCRIPTS = sorted(str(p.relative_to(TOOLS)) for folder in ("benchmarks", "studies")
                 for p in (TOOLS / folder).glob("*.py"))
#: Modules a study compares against and specgpu does not depend on (OpenCV's DIS flow)
OPTIONAL = {"cv2"}


@pytest.mark.parametrize("relative", SCRIPTS)
def test_the_script_imports(relative, monkeypatch):
    # as the scripts are run (``PYTHONPATH=. python tools/...``): the repository's root and the script's siblings
    # importable, whether specgpu is installed from it or not
    monkeypatch.syspath_prepend(str(TOOLS.parent))
    monkeypatch.syspath_prepend(str((TOOLS / relative).parent))
    try:
        load_tool(relative)
    except (ModuleNotFoundError, SystemExit) as exc:  # a script may say what to install and exit
        missing = exc if isinstance(exc, ModuleNotFoundError) else exc.__context__
        if not isinstance(missing, ModuleNotFoundError) or missing.name not in OPTIONAL:
            raise
        pytest.skip(f"tools/{relative} compares against {missing.name}, which is not installed")
