"""Sphinx configuration of the sb3_hhp documentation: ``sphinx-build -W -b html docs docs/_build/html``."""

import os
import sys

sys.path.insert(0, os.path.abspath(".."))

import sb3_hhp  # noqa: E402

project = "sb3_hhp"
author = "sb3_hhp contributors"
copyright = "sb3_hhp contributors"
version = release = sb3_hhp.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
myst_heading_anchors = 3

autodoc_member_order = "bysource"
autodoc_typehints = "description"
# Only the package's own docstrings: methods inherited from gymnasium or SB3 keep their own documentation.
autodoc_inherit_docstrings = False
autodoc_default_options = {"members": True, "show-inheritance": True}

html_theme = "sphinx_rtd_theme"
html_title = f"sb3_hhp {release}"

# Every cross-reference must resolve (sphinx-build -n -W): the project's own names always do. Third-party names would
# need intersphinx inventories, which a build without network access cannot fetch: they are listed here by package.
nitpicky = True
THIRD_PARTY = ("numpy", "torch", "gymnasium", "stable_baselines3", "sb3_contrib", "rl_zoo3", "minigrid", "gymnasium_robotics",
               "ale_py", "optuna", "fastapi", "starlette", "uvicorn", "sqlite3", "collections", "pathlib", "os", "io", "abc",
               "enum", "types", "contextlib", "typing", "argparse", "json", "concurrent", "threading", "queue", "logging", "dataclasses")
nitpick_ignore_regex = [(r"py:.*", rf"{package}(\..*)?") for package in THIRD_PARTY]
# SB3's VecEnv as its type aliases (GymEnv) name it, unqualified
nitpick_ignore = [("py:class", "VecEnv")]
