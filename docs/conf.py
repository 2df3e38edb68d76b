"""Sphinx configuration of the affinebody documentation site (``make docs``).

The pages are Markdown (MyST); the tutorials are MyST notebooks executed at build time (myst-nb),
so a broken example fails the build; the API reference is generated from the docstrings
(autodoc/autosummary) and the command-line reference from the click commands (sphinx-click).
How to add a page: docs/architecture.md, "The documentation site".
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The package from this checkout (also when it is not installed in editable mode).
sys.path.insert(0, str(ROOT / "src"))
# The tutorials' kernels and the commands they run inherit it, with docs/_ext (their %%bash).
os.environ["PYTHONPATH"] = os.pathsep.join(
    p for p in (str(ROOT / "src"), str(ROOT / "docs" / "_ext"), os.environ.get("PYTHONPATH"))
    if p)

# The commands run by the tutorials print as to a file, not a terminal: Jupyter kernels set
# FORCE_COLOR for their subprocesses, which would make rich draw live progress bars and colour
# codes into the pages (TTY_COMPATIBLE=0 takes precedence); tables get 100 columns.
os.environ["TTY_COMPATIBLE"] = "0"
os.environ.setdefault("COLUMNS", "100")

import affinebody  # noqa: E402

project = "affinebody"
author = "affinebody developers"
copyright = "affinebody developers"
release = version = affinebody.__version__

sys.path.insert(0, str(Path(__file__).parent / "_ext"))

extensions = [
    "plaintext_docstrings",
    "myst_nb",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinx_click",
]

exclude_patterns = ["_build", "README.md", "**/.ipynb_checkpoints", "figures/*.toml"]
templates_path = ["_templates"]
# .rst first: autosummary writes its generated stubs with the first suffix.
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb"}

# Markdown: $...$ math rendered by MathJax, anchors for "page.md#section" links.
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# Executed tutorials: every build runs every code cell in a fresh kernel in a temporary
# directory. An exception (a failing command: %%bash raises on a non-zero exit) is reported as
# a warning with the cell's traceback and output in the build log, and -W (make docs) turns it
# into a failed build.
nb_execution_mode = "force"
nb_execution_in_temp = True
nb_execution_raise_on_error = False
nb_execution_show_tb = True
nb_execution_timeout = 300
nb_merge_streams = True

# Unlabelled literal blocks (the docstrings' display formulas) are plain text, not Python.
highlight_language = "text"

# API reference from the docstrings.
autosummary_generate = True
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
add_module_names = False

# The command reference (docs/cli.rst): the group imports its subcommands on first use
# (cli.COMMANDS); register them all here so that sphinx-click lists every one.
from affinebody.cli import COMMANDS, main  # noqa: E402

for _name in COMMANDS:
    main.add_command(main.get_command(None, _name), _name)

html_theme = "furo"
html_title = f"affinebody {release}"
html_static_path: list[str] = []
