"""Sphinx configuration of the torchskin documentation (``make docs``; ``tests/test_docs.py`` builds it with
warnings as errors)."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent / "_ext"))

import torchskin  # noqa: E402

project = "torchskin"
author = "torchskin developers"
copyright = "torchskin developers, Apache-2.0"
release = version = torchskin.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx-mathjax-offline",  # MathJax 3 copied into _static: the equations render without a network
    "sphinx.ext.viewcode",
    "cli_reference",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "_templates"]
templates_path = ["_templates"]
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

autosummary_generate = True
autosummary_ignore_module_all = True  # every public module gets a page (a package's __all__ may list only some)
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "signature"  # "description" would add a second Parameters list after each "Shape:" section
autodoc_typehints_format = "short"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_custom_sections = ["Shape"]  # the docstrings' "Shape:" sections, rendered like "Returns:"
napoleon_use_rtype = False  # "Returns: NDGRI in [-1, 1]: ..." stays one line, not a return type
nitpicky = False
smartquotes = False  # "--option" stays two hyphens (the CLI reference's help texts are plain text)

html_theme = "furo"
html_title = f"torchskin {release}"
html_static_path = ["_static"]
html_css_files = ["custom.css"]
