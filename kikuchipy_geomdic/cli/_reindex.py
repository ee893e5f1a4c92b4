"""The ``reindex`` command: refine every orientation of a map with a
calibrated detector and write an orix crystal map (``.ang`` and orix h5),
with the variants of a pseudo-symmetric material and their domain figure.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from kikuchipy_geomdic.cli._load import (
    _GEOMETRY_OPTIONS,
    _check_detector,
    _check_pseudo_symmetry,
    _existing,
    _load_map,
    _pseudo_symmetry,
    start_detector,
)
from kikuchipy_geomdic.cli._output import _inputs, _one_or_list, _Staging
from kikuchipy_geomdic.cli._parser import _command_output
from kikuchipy_geomdic.cli._run import CLIError, _run_on_map

#: Files ``reindex`` writes, the summary last.
REINDEX_OUTPUTS = ("xmap_refined.ang", "xmap_refined.h5", "reindex.json")
#: The domain figure ``reindex --pseudo-symmetry`` writes besides them.
DOMAIN_FIGURE = "domains.png"
#: The phase map ``reindex`` writes with several ``--master-pattern``.
PHASE_FIGURE = "phases.png"


def _reindex_detector(args: argparse.Namespace, signal):
    """The detector to reindex with, and where it came from."""
    from kikuchipy_geomdic.geometry.maps import navigation_shape
    from kikuchipy_geomdic.io import conventions as cv
    from kikuchipy_geomdic.io import summary as su

    overrides = [k for k in _GEOMETRY_OPTIONS + ("convention",) if getattr(args, k) is not None]
    if args.detector is None:
        return start_detector(signal, args), "the pattern file's metadata" + (
            f" with {', '.join(overrides)} from the command line" if overrides else ""
        )
    if overrides:
        raise CLIError(
            f"--detector gives the whole geometry: leave out --{overrides[0].replace('_', '-')}"
        )
    p = _existing(args.detector, "detector")
    if p.is_dir():
        for name in ("detector.txt", "summary.json"):
            if (p / name).is_file():
                p = p / name
                break
        else:
            raise CLIError(f"{str(p)!r} holds neither detector.txt nor summary.json")
    if p.suffix.lower() == ".json":
        geo = su.geometry_from_summary(su.read_summary(p))
        nav = navigation_shape(signal)
        if tuple(geo.navigation_shape) != nav:
            raise CLIError(
                f"{str(p)!r} was calibrated on a map of {tuple(geo.navigation_shape)} "
                f"points, the patterns are {nav}"
            )
        det = geo.detector()
    else:
        det = cv.load_detector(p)
    return det, str(p)


def _reindex(args: argparse.Namespace) -> int:
    import numpy as np
    from orix import io as orix_io

    from kikuchipy_geomdic.geometry.maps import navigation_shape, usable_points
    from kikuchipy_geomdic.indexing.reindex import reindex
    from kikuchipy_geomdic.io import conventions as cv
    from kikuchipy_geomdic.io import summary as su

    ops = _pseudo_symmetry(args)
    figure = ops is not None and args.method == "geomdic"
    several = len(args.master_pattern) > 1
    names = (
        REINDEX_OUTPUTS[:-1]
        + (DOMAIN_FIGURE,) * figure
        + (PHASE_FIGURE,) * several
        + REINDEX_OUTPUTS[-1:]
    )
    staging = _Staging(args.out, names, args.overwrite)
    say = (lambda *a: None) if args.quiet else print
    signal, xmap, mp, phases = _load_map(args)
    if not several:
        _check_pseudo_symmetry(ops, mp)
    if args.decide_phase and not several:
        raise CLIError("--decide-phase needs two --master-pattern or more (one per phase)")
    det, source = _reindex_detector(args, signal)
    _check_detector(det, signal)
    kw = _method_kwargs(args, ops)
    if several:
        kw["decide_phase"] = args.decide_phase
    else:
        kw["phase"] = phases[0].phase_id

    todo = np.any([usable_points(xmap, p.phase_id) for p in phases], axis=0)
    say(
        f"Reindexing {int(todo.sum())} point(s) of {str(args.patterns)!r} "
        f"({navigation_shape(signal)} map, "
        f"{', '.join(xmap.phases[p.phase_id].name for p in phases)}) with the detector "
        f"from {source}" + (", each point's phase decided" if args.decide_phase else "")
    )
    out, seconds = _run_on_map(reindex, args, (signal, xmap, det, mp), **kw)
    stats = _stats(out, todo, ops, seconds, args.method)
    if several:
        stats.update(_phase_stats(out, todo))
    summary = {
        "format": "kikuchipy-geomdic reindex summary",
        "format_version": 1,
        "versions": su._versions(),
        "detector_source": source,
        "detector_reference_pc": {c: cv.export_geometry(_one_pc(det), c) for c in cv.CONVENTIONS},
        "refine_kwargs": {k: v for k, v in kw.items() if k != "pseudo_symmetry_ops"},
        "pseudo_symmetry": None
        if ops is None
        else {"source": args.pseudo_symmetry, "operators": ops.data.tolist()},
        "result": stats,
        "inputs": _inputs(
            args, signal, mp, phase=_one_or_list([out.phases[p.phase_id].name for p in phases])
        ),
    }
    with staging as st:
        _write_ang(st.path("xmap_refined.ang"), out, det)
        orix_io.save(str(st.path("xmap_refined.h5")), out, overwrite=True)
        if figure:
            _domain_figure(out, ops, st.path(DOMAIN_FIGURE))
        if several:
            _phase_figure(out, st.path(PHASE_FIGURE))
        su.write_summary(summary, st.path("reindex.json"))
        st.commit()
    say(
        f"Refined {stats['refined']} of {stats['points']} points in {seconds:.1f} s"
        + (
            f"; mean NCC {stats['mean_ncc']:.4f} (min {stats['min_ncc']:.4f})"
            if stats["mean_ncc"] is not None
            else ""
        )
        + f"; {stats['not_refined_unusable']} not indexed or unusable, "
        f"{stats['not_refined_nan_patterns']} with NaN patterns"
        + (
            f"; {stats['flagged']} flagged as not converged (property 'converged' = 0)."
            if args.method == "geomdic"
            else "."
        )
    )
    if several:
        say("Points per phase: " + ", ".join(f"{k} {v}" for k, v in stats["phases"].items()))
    if "domains" in stats:
        say("Points per domain (c axis in the parent frame): " + ", ".join(
            f"{k} {v}" for k, v in stats["domains"].items()
        ))  # fmt: skip
    say(f"Results written to {str(staging.out)!r}: {', '.join(staging.names)}")
    return 0


def _method_kwargs(args: argparse.Namespace, ops) -> dict[str, Any]:
    """The keyword arguments of :func:`~kikuchipy_geomdic.indexing.reindex.reindex`
    that ``--method`` and its options give."""
    kw: dict[str, Any] = {"method": args.method}
    if ops is not None:
        kw["pseudo_symmetry_ops"] = ops
    if args.method == "kikuchipy":
        kw["kikuchipy_method"] = args.kikuchipy_method
    elif args.method_kwargs or args.trust_region is not None:
        raise CLIError("--method-kwargs and --trust-region are options of --method kikuchipy")
    if args.method_kwargs:
        try:
            kw["method_kwargs"] = json.loads(args.method_kwargs)
        except json.JSONDecodeError as e:
            raise CLIError(f"--method-kwargs is not JSON: {e}") from None
        if not isinstance(kw["method_kwargs"], dict):
            raise CLIError('--method-kwargs must be a JSON object, e.g. \'{"method": "Powell"}\'')
    if args.trust_region is not None:
        kw["trust_region"] = list(args.trust_region)
    return kw


def _stats(out, todo, ops, seconds: float, method: str) -> dict[str, Any]:
    """The numbers ``reindex.json`` reports of a reindexed map."""
    import numpy as np

    refined = out.prop["refined"].astype(bool)
    scores = out.prop["scores"][refined]
    evals = "iterations" if method == "geomdic" else "num_evals"
    stats = {
        "points": int(out.size),
        "refined": int(refined.sum()),
        "not_refined_unusable": int((~todo.ravel()).sum()),
        "not_refined_nan_patterns": int((todo.ravel() & ~refined).sum()),
        "mean_ncc": float(scores.mean()) if scores.size else None,
        "median_ncc": float(np.median(scores)) if scores.size else None,
        "min_ncc": float(scores.min()) if scores.size else None,
        "mean_evaluations": float(out.prop[evals][refined].mean()) if scores.size else None,
        # Refined but not to be trusted (geomdic: poor for where they are)
        "flagged": int((refined & (out.prop.get("converged", refined) == 0)).sum()),
        "seconds": round(seconds, 3),
        "patterns_per_second": float(refined.sum() / seconds) if seconds > 0 else None,
    }
    if "domain" in out.prop:
        from kikuchipy_geomdic.indexing.variants import variant_names

        counts = np.bincount(out.prop["domain"][out.prop["domain"] >= 0], minlength=ops.size + 1)
        stats["domains"] = dict(zip(variant_names(ops), counts.tolist()))
    return stats


def _domain_figure(xmap, ops, path: Path) -> None:
    """The domain map, margin map and score histograms (the paper's Fig. 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kikuchipy_geomdic.indexing.variants import variant_names
    from kikuchipy_geomdic.plotting import plot_variants

    fig = plot_variants(xmap, names=variant_names(ops))
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: Properties of a reindexing with --pseudo-symmetry written as extra
#: columns of the .ang file (the orix h5 file holds every property).
ANG_VARIANT_COLUMNS = (
    "variant",
    "domain",
    "confidence",
    "cross_variant_margin",
    "variant_significance",
)


def _write_ang(path: Path, xmap, detector) -> None:
    """Write an .ang file (orix) with NCC as confidence index, the input's
    image quality if it has one, the variant properties as extra columns
    (:data:`ANG_VARIANT_COLUMNS`, those the map has) and the detector's
    mean PC (EDAX TSL convention) in the header, where OIM Analysis looks
    for it."""
    from orix import io as orix_io

    kw = {"confidence_index_prop": "scores"}
    extra = [k for k in ANG_VARIANT_COLUMNS if k in xmap.prop]
    if extra:
        kw["extra_prop"] = extra
    if "iq" in xmap.prop:
        kw["image_quality_prop"] = "iq"
    orix_io.save(str(path), xmap, overwrite=True, **kw)
    pc = _one_pc(detector).pc_tsl().reshape(3)
    lines = path.read_text().split("\n")
    for i, line in enumerate(lines):
        if not line.startswith("#"):
            break
        for key, value in zip(("x-star", "y-star", "z-star"), pc, strict=True):
            if line.split()[1:2] == [key]:
                lines[i] = f"# {key:<22} {value:.6f}"
    path.write_text("\n".join(lines))


def _one_pc(det):
    """The detector with its mean PC (for the summary)."""
    new = det.deepcopy()
    new.pc = det.pc_average
    return new


def _reindex_parser(sub, common: argparse.ArgumentParser) -> None:
    """The ``reindex`` command's options."""
    reidx = sub.add_parser(
        "reindex",
        parents=[common],
        help="refine every orientation of a map with a calibrated detector",
        description=(
            "Refine the orientation of every indexed point of the map with a calibrated "
            "detector (this package's Gauss-Newton solver, or kikuchipy's "
            "refine_orientation with --method kikuchipy; through dask: lazy, chunk by "
            "chunk, on a dask.distributed cluster with --scheduler). Writes to --out "
            "xmap_refined.ang, xmap_refined.h5 (orix) and reindex.json; with "
            "--pseudo-symmetry each point's variant, domain, confidence, margin and "
            "significance in both "
            "maps and the domain figure domains.png."
        ),
        epilog=(
            "example: kikuchipy-geomdic reindex map.h5 --orientations map.ang "
            "--master-pattern Si --energy 20 --detector calibration --out reindexed"
        ),
    )
    reidx.add_argument(
        "--detector",
        metavar="CAL",
        help="calibrated detector: a refine output folder, its detector*.txt or "
        "summary.json (default: the pattern file's detector with the geometry options)",
    )
    reidx.add_argument(
        "--method",
        choices=("geomdic", "kikuchipy"),
        default="geomdic",
        help="geomdic (default): this package's Gauss-Newton solver, poor points "
        "re-seeded from their neighbours and flagged; kikuchipy: kikuchipy's "
        "refine_orientation",
    )
    reidx.add_argument(
        "--kikuchipy-method",
        default="minimize",
        help="with --method kikuchipy: its optimisation method (default minimize: Nelder-Mead)",
    )
    reidx.add_argument(
        "--method-kwargs",
        metavar="JSON",
        help="with --method kikuchipy: keyword arguments of its method as JSON, e.g. "
        '\'{"method": "Powell"}\'',
    )
    reidx.add_argument(
        "--trust-region",
        type=float,
        nargs=3,
        metavar=("D1", "D2", "D3"),
        help="with --method kikuchipy: +- bounds in degrees on the three Euler angles",
    )
    reidx.add_argument(
        "--decide-phase",
        action="store_true",
        help="with several --master-pattern: refine every point against every phase and keep "
        "the one its pattern shows (phase_margin: its significance; below 2.5 converged 0); "
        "phases.png marks the points not decided",
    )
    _command_output(reidx, "reindex", _reindex)


def _phase_stats(out, todo) -> dict[str, Any]:
    """What ``reindex.json`` reports of a map of several phases: the points
    per phase and, with ``--decide-phase``, those whose phase changed and
    those not decided (``phase_margin`` below the threshold)."""
    import numpy as np

    ids, counts = np.unique(out.phase_id[todo.ravel()], return_counts=True)
    stats = {"phases": {out.phases[int(i)].name: int(c) for i, c in zip(ids, counts) if i >= 0}}
    if "phase_margin" in out.prop:
        stats["phase_changed"] = int(out.prop["phase_changed"].sum())
        stats["phase_not_decided"] = int((todo.ravel() & (out.prop["converged"] == 0)).sum())
    return stats


def _phase_figure(xmap, path: Path) -> None:
    """The phase map, the points not to trust (``converged`` 0: with
    ``--decide-phase`` those whose phase is not decided too) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kikuchipy_geomdic.plotting import plot_phases

    fig = plot_phases(xmap)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
