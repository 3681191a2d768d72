"""Sphinx configuration of the specgpu documentation.

Build it from the repository root (``pip install '.[docs]'`` first)::

    sphinx-build -W -n -b html docs docs/_build/html

``-W -n``: every warning is an error and every cross-reference must resolve. The build needs no network: no
intersphinx inventories are fetched, and the types of NumPy, colour-science and the standard library are plain
text in the API reference.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE / "_ext"))
sys.path.insert(0, str(ROOT))  # the source tree's specgpu, also when an older one is installed

from api_pages import write_api_pages  # noqa: E402

import specgpu  # noqa: E402

project = "specgpu"
author = "specgpu developers"
copyright = "specgpu developers, BSD-3-Clause"
version = release = specgpu.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "numpydoc",
    "sphinx_click",
    "sphinx_gallery.gen_gallery",
    "results",  # docs/_ext/results.py: tables from docs/results/*.json
    "api_aliases",  # docs/_ext/api_aliases.py: a room's re-export resolves to the documented object
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "examples/README.rst", "auto_examples/*.ipynb", "auto_examples/*.py",
                    "auto_examples/*.zip", "auto_examples/*.md5", "auto_examples/*.json"]
templates_path = ["_templates"]
nitpicky = True
# the user guide's toctree globs docs/guide/ for the pages other changes add; none yet is no fault
suppress_warnings = ["toc.empty_glob"]

# MyST: Markdown pages, with fenced directives and heading anchors for in-page links
myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3

# The API reference: one page per room, listing the room's __all__ (written before the build reads its sources)
write_api_pages(HERE / "api")
autosummary_generate = True
autosummary_imported_members = True
autodoc_typehints = "none"  # types are in the numpydoc sections, where they need no import to resolve
autodoc_member_order = "bysource"
autodoc_default_options = {"members": False}

numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = True
# the project's own types link to their page; every other type name (NumPy, colour-science, the standard
# library: no inventory is fetched offline) is plain text
numpydoc_xref_aliases = {
    "Plan": "specgpu.planning.Plan",
    "CalibrationBundle": "specgpu.calibration.CalibrationBundle",
    "RigDescription": "specgpu.rig.RigDescription",
    "SequenceFolder": "specgpu.pipeline.SequenceFolder",
}
numpydoc_xref_ignore = "all"
# What no offline build can resolve: the standard library's, NumPy's and the other packages' own names (numpydoc
# writes builtins as python:int, array_like as a NumPy glossary term); the project's own names must all resolve.
_EXTERNAL = r"(python:|numpy[:.]|pyopencl\.|colour\.|zarr\.|dask\.|tempfile\.|click\.|threading\.|pathlib\.)\S*"
nitpick_ignore_regex = [
    (r"py:.*", _EXTERNAL),
    (r"py:.*", r"numpy|ndarray|'?dict\[.*|'?list\[.*|'?tuple\[.*|.*\]'?|array|zeros|empty|dtype"),
    (r"std:term", r"numpy:.*|python:.*|generic type"),
    (r"std:ref", r"python:.*"),
]
numpydoc_validation_checks: set[str] = set()

# The gallery: each example runs at build time on the digital twin, at small sizes
sphinx_gallery_conf = {
    "examples_dirs": str(HERE / "examples"),
    "gallery_dirs": str(HERE / "auto_examples"),
    "filename_pattern": r"/plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "matplotlib_animations": False,
    "within_subsection_order": "FileNameSortKey",
    "show_memory": False,
    "min_reported_time": 1,
}

html_theme = "pydata_sphinx_theme"
html_title = "specgpu"
html_static_path: list[str] = []
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "header_links_before_dropdown": 8,
    "icon_links": [],
}
html_show_sourcelink = False
