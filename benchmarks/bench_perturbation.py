"""The paper's perturbation study (section 4.1): 15 pairs x 25 runs.

Usage::

    python benchmarks/bench_perturbation.py            # full: 375 runs per material
    python benchmarks/bench_perturbation.py --quick    # 2 pairs x 3 x 3 runs
    python benchmarks/bench_perturbation.py --materials BaTiO3 --default-settings

The recorded study (benchmarks/README.md) ran with ``refine_geometry_dic``'s
defaults (the joint solver) from the paper's start, the truth plus a
centred 0.3 deg scatter with the matching orientation prior::

    python benchmarks/bench_perturbation.py --default-settings --workers 1 \
        --start centred --orientation-error 0.3

and from orientations indexed at the start geometry, as users have them::

    python benchmarks/bench_perturbation.py --default-settings --workers 1 \
        --materials BaTiO3 --levels -1 0 1 --start indexed --orientation-error 1 \
        --suffix _indexed

Writes ``benchmarks/results/perturbation_<material><suffix>.csv``, the
figures ``..._success.png``, ``..._ncc.png``, ``..._misorientation.png``,
``..._errors.png`` and ``..._nerr_<pair>.png``, and prints a summary table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")

from kikuchipy_geomdic.validation import scores, tables  # noqa: E402
from kikuchipy_geomdic.validation import study as st

RESULTS = Path(__file__).resolve().parent / "results"

#: Orientations per material, as in the paper: BaTiO3 single crystal
#: with its six ferroelectric variants, Si single crystal.
ORIENTATIONS = {"BaTiO3": "variants", "Si": "single"}


def fill_eq2(table, material, nav, shape, seed=0):
    """Compute ``initial_displacement_eq2`` where it is missing (tables
    written before the column existed); deterministic from the settings."""
    from kikuchipy_geomdic.validation import synthetic

    missing = ~np.isfinite(table["initial_displacement_eq2"])
    if not missing.any():
        return table
    base = st.paper_geometry(nav, shape)
    sm = synthetic.synthetic_map(
        material,
        nav,
        orientations=ORIENTATIONS.get(material, "random"),
        geometry=base,
        perturbation={},
        orientation_error=0,
        seed=seed,
    )
    pts = scores._all_points(nav)
    for i in np.flatnonzero(missing):
        r = table[i]
        delta = {str(r["param1"]): float(r["delta1"])}
        delta[str(r["param2"])] = delta.get(str(r["param2"]), 0.0) + float(r["delta2"])
        table["initial_displacement_eq2"][i] = scores.eq2_displacement(
            sm.master_pattern, sm.xmap.rotations, base, base.updated(delta), pts, sm.energy
        )[0]
    return table


def report(study, mat, tag, quick=False):
    """Write the figures and JSON summary and print the tables of a study."""
    s = study.summary()
    s_eq2 = study.summary(axis="initial_displacement_eq2")
    s["material"] = mat
    s["orientations"] = ORIENTATIONS.get(mat, "random")
    for k in (
        "min_failed_displacement",
        "max_success_displacement",
        "success_below_2%",
        "success_below_4%",
        "success_below_6%",
    ):
        s[f"{k}_eq2"] = s_eq2[k]
    with open(RESULTS / f"perturbation_{tag}_summary.json", "w") as f:
        json.dump(
            dict(
                summary=s,
                settings={k: str(v) for k, v in study.settings.items()},
                scale=study.scale,
                coupling=np.round(study.coupling, 3).tolist(),
            ),
            f,
            indent=1,
        )
    study.plot_success().savefig(RESULTS / f"perturbation_{tag}_success.png", dpi=110)
    study.plot_success(axis="initial_displacement_eq2").savefig(
        RESULTS / f"perturbation_{tag}_success_eq2.png", dpi=110
    )
    study.plot_heatmaps(metric="final_ncc").savefig(
        RESULTS / f"perturbation_{tag}_ncc.png", dpi=110
    )
    study.plot_heatmaps(metric="misorientation").savefig(
        RESULTS / f"perturbation_{tag}_misorientation.png", dpi=110
    )
    study.plot_errors().savefig(RESULTS / f"perturbation_{tag}_errors.png", dpi=110)
    pairs_done = tables.pairs_in(study.table)
    for pair in pairs_done[:2] if quick else [("pcz", "tilt"), ("azimuthal", "sample_tilt")]:
        if pair in pairs_done:
            study.plot_normalised_errors(pair).savefig(
                RESULTS / f"perturbation_{tag}_nerr_{pair[0]}_{pair[1]}.png", dpi=110
            )
    print(f"\n{mat}: {study.wall_time / 60:.1f} min wall for {study.table.size} runs")
    print(tables.format_table([s]))
    rows = []
    for p in pairs_done:
        t = study.table[(study.table["param1"] == p[0]) & (study.table["param2"] == p[1])]
        rows.append(
            dict(
                pair=f"{p[0]}-{p[1]}",
                runs=t.size,
                success_ncc=int(t["success_ncc"].sum()),
                success=int(t["success"].sum()),
                max_d0=float(t["initial_displacement"].max()),
                max_d0_eq2=float(t["initial_displacement_eq2"].max()),
            )
        )
    print(tables.format_table(rows))
    return s


def postprocess(args) -> int:
    """Re-read finished tables, fill the Eq. 2 axis, redo figures and summaries."""
    import matplotlib.pyplot as plt

    nav, shape = (args.map, args.map), (args.size, args.size)
    summaries = []
    for mat in args.materials:
        tag = f"{mat}{'_quick' if args.quick else ''}{args.suffix}"
        path = RESULTS / f"perturbation_{tag}.csv"
        if not path.exists():
            continue
        table = fill_eq2(tables.read_table(path), mat, nav, shape)
        tables.write_table(table, path)
        geo = st.paper_geometry(nav, shape)
        pts = scores._all_points(nav)
        scale, coupling = scores.sensitivities(geo, pts)
        old = {}
        jpath = RESULTS / f"perturbation_{tag}_summary.json"
        if jpath.exists():
            old = json.load(open(jpath)).get("summary", {})
        wall = args.wall.get(mat, old.get("wall_time", float("nan")))
        study = st.PerturbationStudy(
            table=table,
            scale=scale,
            coupling=coupling,
            settings=dict(material=mat, navigation_shape=nav, shape=shape),
            wall_time=wall,
        )
        summaries.append(report(study, mat, tag, args.quick))
        plt.close("all")
    print(tables.format_table(summaries, SUMMARY_COLUMNS))
    return 0


SUMMARY_COLUMNS = [
    "material",
    "orientations",
    "runs",
    "success_ncc",
    "success",
    "min_failed_displacement",
    "max_success_displacement",
    "success_below_4%",
    "success_below_6%",
    "min_failed_displacement_eq2",
    "max_success_displacement_eq2",
    "success_below_4%_eq2",
    "success_below_6%_eq2",
    "median_abs_pc_error",
    "median_misorientation",
    "mean_run_time",
    "wall_time",
]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="2 pairs, 3 x 3 grid")
    ap.add_argument("--materials", nargs="+", default=["BaTiO3", "Si"])
    ap.add_argument("--map", type=int, default=5, help="map side (points = side^2)")
    ap.add_argument("--size", type=int, default=60, help="pattern side in px")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-iterations", type=int, default=4)
    ap.add_argument(
        "--trust",
        type=float,
        default=1.0,
        help="orientation trust region (deg) of the orientation refinement; 0 for none",
    )
    ap.add_argument(
        "--default-settings",
        action="store_true",
        help="refine_geometry_dic defaults (no trust region, 10 iterations)",
    )
    ap.add_argument(
        "--pairs", nargs="*", default=None, help="pairs as name1,name2 (default all 15)"
    )
    ap.add_argument(
        "--levels",
        type=float,
        nargs="+",
        default=None,
        help="perturbation levels as fractions of d (default -1 -0.5 0 0.5 1)",
    )
    ap.add_argument("--suffix", default="")
    ap.add_argument(
        "--start",
        default="centred",
        choices=("centred", "uncentred", "indexed"),
        help="start model of the orientations (synthetic.START_MODELS)",
    )
    ap.add_argument(
        "--orientation-error",
        type=float,
        default=0.0,
        help="RMS start orientation error, deg (0: the true orientations)",
    )
    ap.add_argument(
        "--postprocess",
        action="store_true",
        help="only re-read the CSVs: fill the Eq. 2 axis, redo figures and tables",
    )
    ap.add_argument(
        "--wall", nargs="*", default=[], help="material=minutes of wall time, for --postprocess"
    )
    args = ap.parse_args(argv)
    args.wall = {w.split("=")[0]: 60 * float(w.split("=")[1]) for w in args.wall}
    if args.postprocess:
        return postprocess(args)

    pairs = [tuple(p.split(",")) for p in args.pairs] if args.pairs else None
    levels = st.PAPER_LEVELS
    if args.quick:
        pairs = pairs or [("pcz", "tilt"), ("azimuthal", "sample_tilt")]
        levels = (-1.0, 0.0, 1.0)
    if args.levels:
        levels = tuple(args.levels)
    if args.default_settings:
        rkw = {}
    else:
        rkw = dict(max_iterations=args.max_iterations)
        if args.trust > 0:
            rkw["refine_kwargs"] = dict(trust_region=[args.trust] * 3)
    nav = (args.map, args.map)
    shape = (args.size, args.size)
    RESULTS.mkdir(parents=True, exist_ok=True)
    print(
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs, "
        f"{platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}; workers {args.workers}"
    )
    print(
        f"Map {nav}, patterns {shape}, refine_kwargs {rkw}, levels {levels}, start "
        f"{args.start!r} with {args.orientation_error} deg"
    )
    summaries = []
    t_all = time.perf_counter()
    for mat in args.materials:
        geo = st.paper_geometry(nav, shape)
        tag = f"{mat}{'_quick' if args.quick else ''}{args.suffix}"
        # One Dask computation per pair, the table saved after each, so an
        # interrupted study keeps its finished pairs
        parts, t_mat = [], time.perf_counter()
        for pair in pairs or st.PAPER_PAIRS:
            part = st.perturbation_study(
                mat,
                pairs=[pair],
                levels=levels,
                navigation_shape=nav,
                shape=shape,
                orientations=ORIENTATIONS.get(mat, "random"),
                base_geometry=geo,
                refine_kwargs=rkw,
                n_workers=args.workers,
                verbose=True,
                start=args.start,
                orientation_error=args.orientation_error,
            )
            parts.append(part)
            study = st.PerturbationStudy(
                table=np.concatenate([p.table for p in parts]),
                scale=part.scale,
                coupling=part.coupling,
                settings=dict(part.settings, pairs=pairs or st.PAPER_PAIRS),
                wall_time=time.perf_counter() - t_mat,
            )
            study.save(RESULTS / f"perturbation_{tag}.csv")
            print(
                f"-- {mat} {pair}: {int(part.table['success'].sum())}/{part.table.size} "
                f"successes, {part.wall_time:.0f} s; "
                f"total {(time.perf_counter() - t_mat) / 60:.1f} min",
                flush=True,
            )
        summaries.append(report(study, mat, tag, args.quick))
    print(f"\nAll materials: {(time.perf_counter() - t_all) / 60:.1f} min")
    print(tables.format_table(summaries, SUMMARY_COLUMNS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
