"""Sphinx helpers for the kikuchipy-geomdic book (loaded from _config.yml).

Module docstrings of the package are narrative text with section titles
("The tilt degeneracy", "Parameters", ...). Inside an autodoc directive a
section title is not allowed, and napoleon would read a "Parameters" title
in a module docstring as a parameter list. Before napoleon sees them, the
titles of *module* docstrings are turned into rubrics.
"""

import re

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


def setup(app):
    # Napoleon handles autodoc-process-docstring at priority 500: run first
    app.connect("autodoc-process-docstring", _titles_to_rubrics, priority=400)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
