"""Sphinx helpers for the kikuchipy-geomdic book (loaded from _config.yml).

Module docstrings of the package are narrative text with section titles
("The tilt degeneracy", "Parameters", ...). Inside an autodoc directive a
section title is not allowed, and napoleon would read a "Parameters" title
in a module docstring as a parameter list. Before napoleon sees them, the
titles of *module* docstrings are turned into rubrics.

The executed tutorials read third-party data (kikuchipy's silicon
moving-screen patterns) through ``kikuchipy.data``, which is not in the
repository. Unless ``KIKUCHIPY_DATA_DIR`` is set, it is pointed at the
kikuchipy data cache ``../shared/data/kikuchipy_cache`` beside the
repository when that exists, so that the build reads them offline: the
notebook kernels inherit the environment of the build.
"""

import os
import re
from pathlib import Path

_UNDERLINE = re.compile(r"^(-{3,}|={3,}|~{3,})\s*$")


def _titles_to_rubrics(app, what, name, obj, options, lines):
    if what != "module":
        return
    out = []
    i = 0
    while i < len(lines):
        line = lines[i]
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if line.strip() and _UNDERLINE.match(nxt) and len(nxt.strip()) >= len(line.strip()):
            out += [f".. rubric:: {line.strip()}", ""]
            i += 2
            continue
        out.append(line)
        i += 1
    lines[:] = out


def _kikuchipy_data_dir() -> None:
    cache = Path(__file__).resolve().parents[3] / "shared" / "data" / "kikuchipy_cache"
    if "KIKUCHIPY_DATA_DIR" not in os.environ and cache.is_dir():
        os.environ["KIKUCHIPY_DATA_DIR"] = str(cache)


def setup(app):
    _kikuchipy_data_dir()
    # Napoleon handles autodoc-process-docstring at priority 500: run first
    app.connect("autodoc-process-docstring", _titles_to_rubrics, priority=400)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
