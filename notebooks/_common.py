"""What every notebook sets up: headless matplotlib, where the checkout and the outputs
are, the fast mode of the tests, JAX's compilation cache and a markdown-table helper.

Imported by the notebooks as ``from _common import ...`` (their own folder is on
``sys.path`` both under ``python notebooks/NAME.py`` and under ``marimo edit``). Importing
it selects matplotlib's Agg backend, also when ``matplotlib.pyplot`` was imported first
(``matplotlib.use`` switches pyplot's backend while no figure exists).
"""

from __future__ import annotations

import os
import pathlib

import matplotlib

matplotlib.use("Agg")  # headless: figures are written to files, never shown in windows

import marimo as mo  # noqa: E402

import estim  # noqa: E402

# The checkout the notebooks belong to (data/, docs/ and ../shared/ are found from here).
ROOT = pathlib.Path(__file__).resolve().parent.parent
# Figures, GIFs and summary JSON: $ESTIM_NOTEBOOK_OUT (the tests) or notebooks/out/.
OUT = pathlib.Path(os.environ.get("ESTIM_NOTEBOOK_OUT") or ROOT / "notebooks" / "out")
OUT.mkdir(parents=True, exist_ok=True)
# Smaller GIFs and studies (the tests set ESTIM_NOTEBOOK_FAST=1).
FAST = os.environ.get("ESTIM_NOTEBOOK_FAST") == "1"
estim.enable_compilation_cache()  # later runs skip most of JAX's compile time


def md_table(header, rows):
    """A markdown table (its own ``mo.md``: tables must not be indented)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return mo.md("\n".join(lines))
