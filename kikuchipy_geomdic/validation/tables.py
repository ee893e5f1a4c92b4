"""The table of a perturbation study: its columns, CSV, Markdown and summary.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS
from kikuchipy_geomdic.io.files import atomic_write_text, csv_text
from kikuchipy_geomdic.validation.scores import _PC

__all__ = ["pairs_in", "read_table", "write_table", "format_table", "summarise"]

_STUDY_COLUMNS = (
    [
        ("material", "U16"),
        ("param1", "U12"),
        ("param2", "U12"),
        ("level1", "f8"),
        ("level2", "f8"),
        ("delta1", "f8"),
        ("delta2", "f8"),
        ("initial_displacement", "f8"),
        ("initial_displacement_eq2", "f8"),
        ("initial_displacement_dic", "f8"),
        ("final_displacement", "f8"),
        ("final_displacement_model", "f8"),
        ("initial_ncc", "f8"),
        ("final_ncc", "f8"),
        ("misorientation", "f8"),
        ("max_misorientation", "f8"),
    ]
    + [(f"err_{k}", "f8") for k in DEFAULT_PARAMETERS + ("tilt_difference",)]
    + [(f"nerr_{k}", "f8") for k in DEFAULT_PARAMETERS]
    + [
        ("max_pc_error", "f8"),
        ("success_ncc", "?"),
        ("success", "?"),
        ("iterations", "i8"),
        ("converged", "?"),
        ("time", "f8"),
    ]
)


def _to_table(rows: Sequence[Mapping[str, Any]], columns) -> np.ndarray:
    dtype = np.dtype(columns)
    out = np.zeros(len(rows), dtype=dtype)
    for i, r in enumerate(rows):
        for name in dtype.names:
            out[name][i] = r.get(name, np.nan if dtype[name].kind == "f" else 0)
    return out


def pairs_in(table) -> list[tuple[str, str]]:
    """Return the parameter pairs of a study table, in order of appearance.

    Parameters
    ----------
    table
        Study table (:attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.table`).

    Returns
    -------
    pairs
        List of (param1, param2).

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.validation.tables import pairs_in
    >>> t = np.array([("pcx", "pcy"), ("pcx", "pcy"), ("pcz", "tilt")],
    ...              dtype=[("param1", "U12"), ("param2", "U12")])
    >>> pairs_in(t)
    [('pcx', 'pcy'), ('pcz', 'tilt')]
    """
    return list(dict.fromkeys(zip(map(str, table["param1"]), map(str, table["param2"]))))


def read_table(path) -> np.ndarray:
    """Read a table written by :func:`write_table` (CSV).

    Parameters
    ----------
    path
        CSV file with a header line.

    Returns
    -------
    table
        NumPy structured array with the study's columns.
    """
    raw = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    raw = np.atleast_1d(raw)
    dtype = np.dtype(_STUDY_COLUMNS)
    out = np.zeros(raw.size, dtype=dtype)
    for name in dtype.names:
        if dtype[name].kind == "f":
            out[name] = np.nan
        if name in raw.dtype.names:
            col = raw[name]
            if dtype[name].kind == "b":
                col = np.array([str(v).strip().lower() in ("true", "1") for v in col])
            out[name] = col
    return out


def write_table(table: np.ndarray, path) -> None:
    """Write a study table as CSV, atomically (read back with
    :func:`read_table`).

    Parameters
    ----------
    table
        NumPy structured array, e.g.
        :attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.table`.
    path
        CSV file to write; floats get 8 significant digits.
    """
    atomic_write_text(path, csv_text(table.dtype.names, table.tolist(), digits=8))


def format_table(
    rows: Sequence[Mapping[str, Any]] | np.ndarray, columns=None, floatfmt="{:.4g}"
) -> str:
    """Return rows (dicts or a structured array) as a Markdown table.

    Parameters
    ----------
    rows
        List of dicts or a NumPy structured array.
    columns
        Columns to show; default all (the first row's keys).
    floatfmt
        Format of floats.

    Returns
    -------
    text
        Header, separator and one line per row, without a final newline.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.tables import format_table
    >>> print(format_table([{"a": 1, "b": 0.5}]))
    | a | b |
    |---|---|
    | 1 | 0.5 |
    """
    if isinstance(rows, np.ndarray):
        names = rows.dtype.names
        rows = [{n: r[n] for n in names} for r in rows]
    if not rows:
        return ""
    columns = list(columns or rows[0].keys())

    def fmt(v):
        if isinstance(v, (bool, np.bool_)):
            return str(bool(v))
        if isinstance(v, (float, np.floating)):
            return floatfmt.format(float(v))
        return str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
    return "\n".join(lines)


def summarise(
    table: np.ndarray,
    limits=(0.02, 0.04, 0.06),
    wall_time=float("nan"),
    axis: str = "initial_displacement",
) -> dict:
    """Return the headline numbers of a study table.

    Parameters
    ----------
    table
        Study table (:attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.table`).
    limits
        Initial displacements (fractions of the width) below which the
        successes are counted (``success_below_<limit>``).
    wall_time
        Wall time of the study, s, copied into the summary.
    axis
        Displacement column the limits refer to: "initial_displacement"
        or the paper's "initial_displacement_eq2".

    Returns
    -------
    summary
        Run and success counts, the smallest failed and largest
        successful displacement, median and largest errors, run times
        (as :meth:`~kikuchipy_geomdic.validation.study.PerturbationStudy.summary`).
    """
    t = table
    d0 = t[axis]
    out: dict[str, Any] = {
        "runs": int(t.size),
        "success_ncc": int(t["success_ncc"].sum()),
        "success": int(t["success"].sum()),
    }
    fail = ~t["success"]
    out["min_failed_displacement"] = float(d0[fail].min()) if fail.any() else float("nan")
    fail_ncc = ~t["success_ncc"]
    out["min_failed_displacement_ncc"] = (
        float(d0[fail_ncc].min()) if fail_ncc.any() else float("nan")
    )
    out["max_success_displacement"] = (
        float(d0[t["success"]].max()) if t["success"].any() else float("nan")
    )
    for lim in limits:
        below = d0 < lim
        out[f"success_below_{100 * lim:g}%"] = (
            f"{int(t['success'][below].sum())}/{int(below.sum())}"
        )
    ok = t["success"]
    if ok.any():
        pc = np.abs(np.stack([t[f"err_{k}"][ok] for k in _PC]))
        out["median_abs_pc_error"] = float(np.median(pc))
        out["max_abs_pc_error"] = float(pc.max())
        out["median_abs_tilt_difference_error"] = float(
            np.median(np.abs(t["err_tilt_difference"][ok]))
        )
        out["median_abs_azimuthal_error"] = float(np.median(np.abs(t["err_azimuthal"][ok])))
        out["median_misorientation"] = float(np.median(t["misorientation"][ok]))
    out["mean_run_time"] = float(t["time"].mean()) if t.size else float("nan")
    out["wall_time"] = float(wall_time)
    return out
