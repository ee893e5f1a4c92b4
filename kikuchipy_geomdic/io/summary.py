"""Summaries: a JSON file describing a whole calibration, with the
geometry in every PC convention (:func:`summary_from_result`,
:func:`write_summary`, :func:`read_summary`,
:func:`geometry_from_summary`, :func:`format_summary`).

Layer 2 (io): may import geometry.
"""

from __future__ import annotations

import json
import math
import platform
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import kikuchipy
import numpy as np
import orix

from kikuchipy_geomdic.geometry import PARAMETERS, MapGeometry
from kikuchipy_geomdic.io.conventions import (
    _ANGLES,
    CONVENTIONS,
    convention_name,
    export_geometry,
    import_geometry,
)
from kikuchipy_geomdic.io.files import atomic_write_text

__all__ = [
    "SUMMARY_FORMAT",
    "SUMMARY_VERSION",
    "summary_from_result",
    "write_summary",
    "read_summary",
    "geometry_from_summary",
    "format_summary",
]

#: Format name and version of the JSON summary.
SUMMARY_FORMAT = "kikuchipy-geomdic calibration summary"
SUMMARY_VERSION = 1


def _plain(value):
    """JSON-ready copy: numpy to Python, NaN and inf to None."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, Path):
        return str(value)
    return value


def _versions() -> dict[str, str]:
    from kikuchipy_geomdic._version import __version__

    return {
        "kikuchipy": kikuchipy.__version__,
        "orix": orix.__version__,
        "kikuchipy_geomdic": __version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def _geometry_dict(geometry: MapGeometry) -> dict[str, Any]:
    return {
        **geometry.as_dict(),
        "reference": list(geometry.reference),
        "step_sizes": list(geometry.step_sizes),
        "navigation_shape": list(geometry.navigation_shape),
        "shape": list(geometry.shape),
        "px_size": geometry.px_size,
        "binning": geometry.binning,
    }


def summary_from_result(result, **inputs) -> dict[str, Any]:
    """Return the JSON-ready summary of a calibration.

    Parameters
    ----------
    result
        :class:`~kikuchipy_geomdic.calibration.result.GeometryRefinementResult`.
    **inputs
        What was calibrated (file names, energy, ...), stored under
        ``"inputs"``.

    Returns
    -------
    summary
        Dict with ``format``, ``format_version``, ``created``,
        ``versions`` (kikuchipy, orix, kikuchipy-geomdic, ...),
        ``geometry`` (Bruker PC at ``reference``, angles, step sizes in
        um, shapes, pixel size, binning), ``start_geometry``,
        ``conventions`` (one
        :func:`~kikuchipy_geomdic.io.conventions.export_geometry` record per
        convention), ``refined_parameters``, ``degenerate``,
        ``converged``, ``orientation_model``, ``standard_errors`` (each
        refined parameter's and ``tilt-sample_tilt``'s, in its unit; None
        where the map does not determine it: kept at its start, or only
        a difference determined), ``undetermined`` (above
        ``DETERMINACY_LIMITS``), ``adequacy`` (the check of the full field
        against the DIC stage: ``verdict``, ``consistent``, the
        ``systematic`` part of each standard error and the ``lattice``
        fitted, if it was; empty without a full field), ``calibration``
        (points, NCC, displacement), ``history`` and ``inputs``.

    Examples
    --------
    >>> from kikuchipy_geomdic import refine_geometry_dic
    >>> from kikuchipy_geomdic.io.summary import summary_from_result
    >>> from kikuchipy_geomdic.validation.synthetic import synthetic_map
    >>> res = refine_geometry_dic(
    ...     *synthetic_map("Si", (3, 3), shape=(40, 40), seed=0).start_inputs,
    ...     parameters=["pcx", "pcy", "pcz"], points=9, rois=(4, 4),
    ...     max_iterations=1, show_progressbar=False,
    ... )
    >>> s = summary_from_result(res, energy=20)
    >>> sorted(s["conventions"])
    ['bruker', 'emsoft4', 'emsoft5', 'oxford', 'tsl']
    """
    geo = result.geometry
    hist = result.history
    scores = np.asarray(result.xmap.prop["scores"], dtype=float) if result.xmap.size else []
    summary = {
        "format": SUMMARY_FORMAT,
        "format_version": SUMMARY_VERSION,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "versions": _versions(),
        "geometry": _geometry_dict(geo),
        "start_geometry": _geometry_dict(result.start_geometry),
        "conventions": {c: export_geometry(geo, c) for c in CONVENTIONS},
        "refined_parameters": list(result.parameter_names),
        "degenerate": list(result.degenerate),
        "converged": bool(result.converged),
        "orientation_model": getattr(result, "orientation_model", "free"),
        "standard_errors": dict(result.standard_errors),
        "undetermined": list(result.undetermined),
        "adequacy": {
            k: result.adequacy[k]
            for k in ("verdict", "consistent", "systematic", "lattice")
            if k in result.adequacy
        },
        "calibration": {
            "points": len(result.points),
            "points_row_col": np.asarray(result.points).tolist(),
            "mean_ncc": float(np.mean(scores)) if len(scores) else None,
            "displacement_before": hist[0]["displacement_before"] if hist else None,
            "displacement_after": (
                [h for h in hist if h["accepted"]][-1]["displacement_after"]
                if any(h["accepted"] for h in hist)
                else (hist[0]["displacement_before"] if hist else None)
            ),
            "displacement_unit": "mean ROI displacement, fraction of the detector width",
            "iterations": len(hist),
        },
        "history": list(hist),
        "inputs": dict(inputs),
    }
    return _plain(summary)


def write_summary(summary: Mapping[str, Any], path: str | Path) -> Path:
    """Write a summary as indented JSON, atomically.

    Parameters
    ----------
    summary
        From :func:`summary_from_result`.
    path
        JSON file to write.

    Returns
    -------
    path
    """
    text = json.dumps(_plain(summary), indent=2, allow_nan=False) + "\n"
    return atomic_write_text(path, text)


def read_summary(path: str | Path) -> dict[str, Any]:
    """Read a summary written by :func:`write_summary`.

    Parameters
    ----------
    path
        JSON file.

    Returns
    -------
    summary

    Raises
    ------
    FileNotFoundError, ValueError
        If the file is missing or is not such a summary.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"No summary file {str(path)!r}")
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{str(path)!r} is not a JSON file: {e}") from None
    if not isinstance(summary, dict) or summary.get("format") != SUMMARY_FORMAT:
        raise ValueError(f"{str(path)!r} is not a {SUMMARY_FORMAT}")
    if int(summary.get("format_version", 0)) > SUMMARY_VERSION:
        raise ValueError(
            f"{str(path)!r} has summary format {summary['format_version']}; this "
            f"version of kikuchipy-geomdic reads up to {SUMMARY_VERSION}"
        )
    return summary


def geometry_from_summary(summary: Mapping[str, Any], convention: str = "bruker") -> MapGeometry:
    """Rebuild the calibrated map geometry from a summary.

    Parameters
    ----------
    summary
        From :func:`read_summary` or :func:`summary_from_result`.
    convention
        Which of the summary's convention records to take the PC and the
        angles from; all give the same geometry (that is what the
        round-trip tests check).

    Returns
    -------
    geometry
        :class:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry`; its
        ``detector()`` is the calibrated detector of the whole map.
    """
    conv = convention_name(convention)
    try:
        g = summary["geometry"]
        record = summary["conventions"][conv]
    except KeyError as e:
        raise ValueError(f"The summary lacks {e}") from None
    det = import_geometry(record)
    return MapGeometry(
        pc=det.pc.reshape(3),
        shape=tuple(g["shape"]),
        px_size=float(g["px_size"]),
        binning=float(g["binning"]),
        step_sizes=tuple(g["step_sizes"]),
        navigation_shape=tuple(g["navigation_shape"]),
        tilt=det.tilt,
        azimuthal=det.azimuthal,
        sample_tilt=det.sample_tilt,
        twist=det.twist,
        reference=tuple(g["reference"]),
    )


def format_summary(summary: Mapping[str, Any]) -> str:
    """Return a human-readable table of a summary.

    Parameters
    ----------
    summary
        From :func:`summary_from_result`.

    Returns
    -------
    text
        Start and refined values of each parameter with its standard
        error ("-" where the map does not determine it), the PC at the
        reference map position in every convention, the angles, and what
        the standard errors include.
    """
    g, s = summary["geometry"], summary["start_geometry"]
    refined = set(summary.get("refined_parameters", ()))
    se = summary.get("standard_errors", {})
    loose = set(summary.get("undetermined", ()))

    def sigma(key):
        # se holds the refined parameters and, with a tilt, their difference
        if key not in se:
            return ""
        return "-" if se[key] is None else f"{se[key]:.1e}"

    lines = [f"{'parameter':<13}{'start':>13}{'calibrated':>13}{'change':>13}{'sigma':>10}  unit"]
    for name in PARAMETERS:
        unit = "deg" if name in _ANGLES else "PC (Bruker)"
        d = 4 if unit == "deg" else 6
        mark = "" if name in refined else "  (fixed)"
        mark += "  poorly determined" if name in loose else ""
        lines.append(
            f"{name:<13}{s[name]:>13.{d}f}{g[name]:>13.{d}f}{g[name] - s[name]:>+13.{d}f}"
            f"{sigma(name):>10}  {unit}{mark}"
        )
    lines.append(
        f"{'tilt-s_tilt':<13}{s['tilt'] - s['sample_tilt']:>13.4f}"
        f"{g['tilt'] - g['sample_tilt']:>13.4f}"
        f"{(g['tilt'] - g['sample_tilt']) - (s['tilt'] - s['sample_tilt']):>+13.4f}"
        f"{sigma('tilt-sample_tilt'):>10}  deg"
    )
    if any(v is None for v in se.values()):
        lines.append(
            "sigma '-': not determined by the map (kept at its start, or only the tilt "
            "difference determined)"
        )
    adequacy = summary.get("adequacy", {})
    if adequacy.get("verdict"):
        lines.append(adequacy["verdict"])
    parts = {k: v for k, v in adequacy.get("systematic", {}).items() if v}
    if parts:
        lines.append(
            "sigma includes a systematic part (what the patterns share): "
            + ", ".join(f"{k} {v:.1e}" for k, v in parts.items())
        )
    lattice = adequacy.get("lattice")
    if lattice:
        lines.append(
            f"c/a {lattice['c_over_a']:.5f} +- {lattice['c_over_a_se']:.5f} (the CIF's "
            f"{lattice['phase_c_over_a']:.5f})"
            + ("" if lattice["determined"] else ": not determined, the PC's sigma carries it")
        )
    ref = ", ".join(f"{v:g}" for v in g["reference"])
    lines.append("")
    lines.append(
        f"PC at map position (row, col) = ({ref}); detector {g['shape'][0]} x "
        f"{g['shape'][1]} px, px_size {g['px_size']:g} um, binning {g['binning']:g}:"
    )
    for conv, rec in summary["conventions"].items():
        names = ", ".join(rec["pc_names"])
        vals = ", ".join(f"{v:.6f}" if abs(v) < 100 else f"{v:.2f}" for v in rec["pc"])
        lines.append(f"  {conv:<8} ({names}) = ({vals})")
    lines.append(
        "Angles (deg, kikuchipy): "
        + ", ".join(f"{a} {g[a]:.4f}" for a in ("tilt", "azimuthal", "sample_tilt", "twist"))
    )
    for d in summary.get("degenerate", []):
        combo = " ".join(f"{c:+.2f} {n}" for n, c in d.items())
        lines.append(f"Not determined by the data (minimum-norm split): {combo}")
    return "\n".join(lines)
