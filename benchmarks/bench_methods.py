"""Method comparison (paper section 3.1): DIC geometry refinement vs
kikuchipy's pattern-wise PC + orientation refinement (Nelder-Mead and
differential evolution, PCs then averaged), on one CPU.

Usage::

    python benchmarks/bench_methods.py            # N = 100 points, 120 x 120 px
    python benchmarks/bench_methods.py --quick    # N = 16, 60 x 60 px

All methods run on the same synthetic map and start (true geometry plus
``synthetic.DEFAULT_PERTURBATION``, orientations with 0.3 deg RMS error,
like Hough indexing) under Dask's synchronous scheduler and with OpenCV
limited to one thread, so times are single-CPU times as in the paper.
Differential evolution runs on fewer points (``--de-points``) and with
``maxiter=50`` (SciPy's default, 1000 generations of 90 candidates, took
about 290 s per 60 x 60 pattern here); its time at N points is extrapolated
from its time per point and labelled so. Nelder-Mead is SciPy's with
kikuchipy's defaults. Both use the paper's trust region (3 deg, 5 %).
Writes ``benchmarks/results/methods_<case>.csv`` and prints tables.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from kikuchipy_geomdic import study as st
from kikuchipy_geomdic import synthetic
from kikuchipy_geomdic.comparison import compare_methods

RESULTS = Path(__file__).resolve().parent / "results"
COLUMNS = [
    "method",
    "n_points",
    "time",
    "time_per_point",
    "time_at_n",
    "extrapolated",
    "iterations",
    "max_pc_error",
    "err_pcx",
    "err_pcy",
    "err_pcz",
    "err_tilt_difference",
    "err_azimuthal",
    "pc_scatter",
    "misorientation",
    "misorientation_rerefined",
    "time_rerefine",
    "disorientation",
    "ncc",
]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--points", type=int, default=100)
    ap.add_argument("--size", type=int, default=120)
    ap.add_argument("--de-points", type=int, default=10)
    ap.add_argument(
        "--de-maxiter",
        type=int,
        default=50,
        help="SciPy differential_evolution maxiter (default 1000 took ~290 s per "
        "60 x 60 pattern here)",
    )
    ap.add_argument("--cases", nargs="+", default=["Si-single"])
    args = ap.parse_args(argv)
    if args.quick:
        args.points, args.size, args.de_points = 16, 60, 2
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass
    RESULTS.mkdir(parents=True, exist_ok=True)
    side = int(round(np.sqrt(args.points)))
    print(
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs (shared), Python "
        f"{platform.python_version()}; single-CPU timing (dask synchronous)"
    )
    t_all = time.perf_counter()
    for case in args.cases:
        mat, orient = case.split("-")
        sm = synthetic.synthetic_map(
            mat,
            (side, side),
            orientations=orient,
            shape=(args.size, args.size),
            orientation_error=0.3,
            seed=0,
        )
        d0 = st.mean_displacement(sm.start_geometry, sm.geometry)
        print(
            f"\n## {case}: {side} x {side} map, {args.size} x {args.size} px, start "
            f"displacement {100 * d0:.2f} % of width, start orientation error 0.3 deg RMS"
        )
        rows = compare_methods(
            sm,
            points=side * side,
            methods=("dic", "dic-fast", "nelder-mead", "differential-evolution"),
            method_points={"differential-evolution": args.de_points},
            dic_configs={
                "dic-fast": dict(max_iterations=3, refine_kwargs=dict(trust_region=[1, 1, 1]))
            },
            de_kwargs=dict(seed=0, maxiter=args.de_maxiter),
            verbose=True,
        )
        print(st.format_table(rows, COLUMNS))
        by = {r["method"]: r for r in rows}
        ratios = []
        for fast in ("dic", "dic-fast"):
            ratios.append(
                dict(
                    dic=fast,
                    de_over_dic=by["differential-evolution"]["time_at_n"] / by[fast]["time"],
                    nm_over_dic=by["nelder-mead"]["time_at_n"] / by[fast]["time"],
                    de_extrapolated=by["differential-evolution"]["extrapolated"],
                )
            )
        print("\nSpeed-up (time ratios, same run; DE extrapolated from its time per point):")
        print(st.format_table(ratios))
        with open(RESULTS / f"methods_{case}{'_quick' if args.quick else ''}.csv", "w") as f:
            f.write(",".join(COLUMNS) + "\n")
            for r in rows:
                f.write(",".join(str(r.get(c, "")) for c in COLUMNS) + "\n")
    print(f"\nTotal {(time.perf_counter() - t_all) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
