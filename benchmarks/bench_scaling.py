"""Scaling of one refinement: time and peak memory against the number of
calibration points N and the pattern size, with a per-stage profile.

Usage::

    python benchmarks/bench_scaling.py   # N = 25, 100, 400 at 60 px; 60, 120, 240 px at N = 25
    python benchmarks/bench_scaling.py --quick    # N = 9, 25 at 40 px

Each configuration runs ``refine_geometry_dic`` once (Si polycrystal, the
default start: about 2 % of the width mean displacement, 0.3 deg orientation
error, all six parameters, ``max_iterations=4``) under cProfile and
tracemalloc, with Dask's synchronous scheduler (one CPU). Stages are the
cumulative times of: ``simulate_patterns`` (simulation),
``measure_displacements`` (DIC), ``analytic_jacobian`` (Jacobian),
``solve_update`` (solve) and kikuchipy's ``refine_orientation``
(orientation refinement). Peak memory is the tracemalloc peak (NumPy
buffers included) during the refinement. Profiling adds some overhead to
the wall times. Writes ``benchmarks/results/scaling.csv``.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
import time
import tracemalloc
import warnings
from pathlib import Path

import dask

from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
from kikuchipy_geomdic.validation import scores, synthetic, tables

RESULTS = Path(__file__).resolve().parent / "results"
STAGES = {
    "simulation": ("simulation.py", "simulate_patterns"),
    "dic": ("displacement.py", "measure_displacements"),
    "jacobian": ("jacobian.py", "analytic_jacobian"),
    "solve": ("solve.py", "solve_update"),
    "orientations": ("ebsd.py", "refine_orientation"),
}


def run(side: int, size: int, max_iterations: int = 4) -> dict:
    sm = synthetic.synthetic_map(
        "Si", (side, side), orientations="random", shape=(size, size), seed=0
    )
    prof = cProfile.Profile()
    tracemalloc.start()
    t0 = time.perf_counter()
    with dask.config.set(scheduler="synchronous"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prof.enable()
        res = refine_geometry_dic(
            sm.signal,
            sm.start_xmap,
            sm.start_detector,
            sm.master_pattern,
            sm.energy,
            points=side * side,
            max_iterations=max_iterations,
            show_progressbar=False,
        )
        prof.disable()
    wall = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    stats = pstats.Stats(prof)
    row = dict(
        points=side * side,
        size=size,
        time=wall,
        iterations=len(res.history),
        peak_mib=peak / 2**20,
    )
    for stage, (fname, func) in STAGES.items():
        cum = sum(v[3] for k, v in stats.stats.items() if k[0].endswith(fname) and k[2] == func)
        row[f"t_{stage}"] = cum
    row["t_other"] = wall - sum(row[f"t_{s}"] for s in STAGES)
    dom = max(STAGES, key=lambda s: row[f"t_{s}"])
    row["dominant"] = dom
    row["dominant_share"] = row[f"t_{dom}"] / wall
    err = scores._geometry_errors(res.geometry, sm.geometry)
    row["max_pc_error"] = max(abs(err[k]) for k in ("pcx", "pcy", "pcz"))
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass
    if args.quick:
        configs = [(3, 40), (5, 40)]
    else:
        configs = [(5, 60), (10, 60), (20, 60), (5, 120), (5, 240)]
    print(
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs (shared), Python "
        f"{platform.python_version()}; one CPU (dask synchronous), cProfile + tracemalloc on"
    )
    # Warm-up (numba compilation) outside the timings
    run(3, 40, max_iterations=1)
    rows = []
    t_all = time.perf_counter()
    for side, size in configs:
        rows.append(run(side, size))
        r = rows[-1]
        print(
            f"N={r['points']} size={r['size']}: {r['time']:.1f} s, peak {r['peak_mib']:.0f} MiB, "
            f"{r['dominant']} {100 * r['dominant_share']:.0f} %",
            flush=True,
        )
    cols = (
        ["points", "size", "time", "iterations", "peak_mib"]
        + [f"t_{s}" for s in STAGES]
        + ["t_other", "dominant", "dominant_share", "max_pc_error"]
    )
    print(tables.format_table(rows, cols))
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / f"scaling{'_quick' if args.quick else ''}.csv", "w") as f:
        f.write(",".join(cols) + "\n")
        for r in rows:
            f.write(",".join(str(r[c]) for c in cols) + "\n")
    print(f"Total {(time.perf_counter() - t_all) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
