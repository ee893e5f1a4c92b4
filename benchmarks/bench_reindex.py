"""Benchmark: reindex a large map lazily, in bounded memory.

A synthetic silicon map (default 200 x 200 patterns of 60 x 60 px, known
geometry, starting orientations 0.3 deg off) is simulated lazily and
written chunk by chunk to a kikuchipy h5ebsd file as 8-bit patterns, as a
microscope would write it. The file is then opened lazily and every
orientation is refined with the true (calibrated) detector, one PC per
pattern, by :func:`kikuchipy_geomdic.indexing.reindex.reindex` through dask
(``--method geomdic``, the default: this package's solver; ``--method
kikuchipy``: kikuchipy's ``refine_orientation``).

Each stage runs in its own process, so the peak resident memory reported
(``ru_maxrss``) is that stage's alone; the baseline stage only imports the
packages and loads the master pattern. Memory is bounded when the reindex
peak stays far below the size of the patterns in memory (float32) and does
not grow with the map.

Usage::

    python benchmarks/bench_reindex.py                  # 200 x 200, 60 x 60
    python benchmarks/bench_reindex.py --rows 50 --cols 50 --json out.json
    python benchmarks/bench_reindex.py --rows 50 --cols 50 --method kikuchipy

Run it alone on the machine: it uses every core dask gets.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

MARK = "BENCH_RESULT "


def _peak_rss_mb() -> float:
    # ru_maxrss is in KiB on Linux, bytes on macOS
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 2**10


def _report(**values) -> None:
    values["peak_rss_mb"] = round(_peak_rss_mb(), 1)
    print(MARK + json.dumps(values), flush=True)


def stage_baseline(args) -> None:
    from kikuchipy_geomdic.validation import master_patterns

    master_patterns.master_pattern("Si")
    _report()


def stage_generate(args) -> None:
    import dask.array as da
    import numpy as np
    from orix import io as orix_io

    from kikuchipy_geomdic.io.conventions import save_detector
    from kikuchipy_geomdic.validation import synthetic

    work = Path(args.workdir)
    t0 = time.perf_counter()
    sm = synthetic.synthetic_map(
        "Si", (args.rows, args.cols), shape=(args.size, args.size), lazy=True, seed=0
    )
    s = sm.signal
    d = s.data
    lo = d.min(axis=(2, 3), keepdims=True)
    hi = d.max(axis=(2, 3), keepdims=True)
    s.data = da.round((d - lo) / da.maximum(hi - lo, 1e-12) * 255).astype(np.uint8)
    quiet = contextlib.redirect_stdout(io.StringIO()) if args.quiet else _null()
    with quiet:  # the writer's progress bar
        s.save(work / "map.h5", overwrite=True)
    orix_io.save(str(work / "start.h5"), sm.start_xmap, overwrite=True)
    orix_io.save(str(work / "truth.h5"), sm.xmap, overwrite=True)
    save_detector(sm.detector, work / "detector.txt")
    _report(
        seconds=round(time.perf_counter() - t0, 1),
        file_mb=round((work / "map.h5").stat().st_size / 2**20, 1),
    )


def stage_reindex(args) -> None:
    import dask
    import kikuchipy as kp
    import numpy as np
    from orix import io as orix_io

    from kikuchipy_geomdic.indexing.reindex import reindex
    from kikuchipy_geomdic.io.conventions import load_detector
    from kikuchipy_geomdic.validation import master_patterns

    work = Path(args.workdir)
    signal = kp.load(work / "map.h5", lazy=True)
    start = orix_io.load(str(work / "start.h5"))
    truth = orix_io.load(str(work / "truth.h5"))
    det = load_detector(work / "detector.txt")
    mp = master_patterns.master_pattern("Si")
    t0 = time.perf_counter()
    with dask.config.set(num_workers=args.workers) if args.workers else _null():
        out = reindex(
            signal, start, det, mp, 20, method=args.method, show_progressbar=not args.quiet
        )
    seconds = time.perf_counter() - t0
    mis = np.rad2deg((out.rotations * ~truth.rotations).angle)
    mis0 = np.rad2deg((start.rotations * ~truth.rotations).angle)
    _report(
        seconds=round(seconds, 1),
        patterns=int(out.size),
        patterns_per_second=round(out.size / seconds, 1),
        method=args.method,
        flagged=int((out.prop.get("converged", np.ones(out.size)) == 0).sum()),
        still_lazy=bool(signal._lazy),
        chunks=str(signal.data.chunksize),
        mean_ncc=round(float(out.scores.mean()), 5),
        misorientation_start_deg=round(float(mis0.mean()), 4),
        misorientation_after_deg=round(float(mis.mean()), 4),
    )


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


STAGES = {"baseline": stage_baseline, "generate": stage_generate, "reindex": stage_reindex}


def _run_stage(name: str, args) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--stage",
        name,
        "--rows",
        str(args.rows),
        "--cols",
        str(args.cols),
        "--size",
        str(args.size),
        "--workdir",
        args.workdir,
    ]
    cmd += ["--method", args.method]
    if args.workers:
        cmd += ["--workers", str(args.workers)]
    if args.quiet:
        cmd.append("--quiet")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith(MARK):
            result = json.loads(line[len(MARK) :])
            break
        print(line)
    else:
        raise SystemExit(f"stage {name} failed (exit code {proc.returncode})")
    result["process_seconds"] = round(time.perf_counter() - t0, 1)
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", type=int, default=200)
    p.add_argument("--cols", type=int, default=200)
    p.add_argument("--size", type=int, default=60, help="pattern side in px")
    p.add_argument("--workdir", help="folder for the map file (default: a temporary one)")
    p.add_argument("--workers", type=int, help="dask threads (default: dask's)")
    p.add_argument(
        "--method", choices=("geomdic", "kikuchipy"), default="geomdic", help="reindex method"
    )
    p.add_argument("--json", help="also write the results to this JSON file")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--stage", choices=STAGES, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.stage:
        STAGES[args.stage](args)
        return 0

    with tempfile.TemporaryDirectory(prefix="bench_reindex_") as tmp:
        if args.workdir is None:
            args.workdir = tmp
        Path(args.workdir).mkdir(parents=True, exist_ok=True)
        results = {name: _run_stage(name, args) for name in ("baseline", "generate", "reindex")}
    n = args.rows * args.cols
    float32_mb = n * args.size**2 * 4 / 2**20
    summary = {
        "map": [args.rows, args.cols],
        "pattern_shape": [args.size, args.size],
        "patterns_float32_mb": round(float32_mb, 1),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        **results,
    }
    r, b = results["reindex"], results["baseline"]
    print(
        f"\nMap {args.rows} x {args.cols} of {args.size} x {args.size} px: "
        f"{float32_mb:.0f} MB as float32, {results['generate']['file_mb']:.0f} MB on disk (uint8)."
    )
    print(
        f"  generate + write (lazy):  {results['generate']['seconds']:8.1f} s, "
        f"peak RSS {results['generate']['peak_rss_mb']:7.0f} MB"
    )
    print(
        f"  reindex (lazy):           {r['seconds']:8.1f} s, peak RSS {r['peak_rss_mb']:7.0f} MB "
        f"({r['patterns_per_second']:.1f} patterns/s)"
    )
    print(f"  baseline (imports + MP):  {'':8} peak RSS {b['peak_rss_mb']:7.0f} MB")
    print(
        f"  orientation error: {r['misorientation_start_deg']:.3f} deg -> "
        f"{r['misorientation_after_deg']:.4f} deg, mean NCC {r['mean_ncc']:.4f}, "
        f"still lazy: {r['still_lazy']}"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
