"""The README names, where it introduces the viewer extra, every system library .ci/run installs for Qt."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def ci_qt_packages() -> list[str]:
    text = (ROOT / ".ci" / "run").read_text()
    found = re.search(r'^qt_libs="(.*?)"', text, flags=re.S | re.M)
    assert found, ".ci/run no longer sets qt_libs"
    return found.group(1).replace("\\\n", " ").split()


def test_the_viewer_section_names_every_package_ci_installs_for_qt():
    readme = (ROOT / "README.md").read_text()
    section = readme.split("### Looking at cubes, captures and recordings: the napari viewer", 1)[1].split("\n## ")[0]
    named = set(re.findall(r"[\w.+-]+", section))
    packages = ci_qt_packages()
    assert len(packages) >= 10 and "libxcb-icccm4" in packages
    assert [p for p in packages if p not in named] == []
    # before any other prose of the section: a reader installing the extra meets it first
    assert section.index("libxcb-cursor0") < section.index("`specgpu view` opens napari")
