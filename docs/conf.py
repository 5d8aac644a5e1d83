"""Sphinx configuration of the piezo injector estimator's documentation (``make docs``)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent / "_ext"))

import estimator  # noqa: E402

project = "Piezo injector estimator"
author = "The piezo injector estimator developers"
copyright = "2026, " + author
version = release = estimator.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinxarg.ext",
    "injector_docs",
    "doc_figures",
]
myst_enable_extensions = ["colon_fence", "dollarmath", "deflist"]
myst_heading_anchors = 3
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build"]
html_theme = "furo"
html_title = f"Piezo injector estimator {release}"
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options: dict[str, object] = {}
napoleon_use_ivar = True
napoleon_google_docstring = False
napoleon_numpy_docstring = True
nitpicky = False
