"""Sphinx configuration: MyST Markdown, numpydoc docstrings through napoleon, the furo theme.

The reference pages (integrators, problems, command line, performance) are generated from
the registries and the perf outputs by ``docs/generate.py`` before every build, so that
they describe the code being documented.
"""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "docs"))

import generate  # noqa: E402

generate.write_docs()

project = "driftbench"
author = "driftbench contributors"
copyright = "driftbench contributors, MIT licence"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build"]
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

napoleon_numpy_docstring = True
napoleon_google_docstring = False
autodoc_member_order = "bysource"
autodoc_typehints = "none"
autodoc_default_options = {"members": False}

html_theme = "furo"
html_title = "driftbench"
html_static_path = ["_static"]
