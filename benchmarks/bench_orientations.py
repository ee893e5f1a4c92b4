"""Benchmark: reindex a map with the calibrated geometry, ours against kikuchipy.

Two experiments, each run side by side on the same map, detector, starts
and cores (one after the other in one process, numba compiled first):

``throughput``
    A synthetic polycrystalline silicon map (``orientations="grains"``,
    default 50 x 50 points, shot noise at dose 300) is reindexed with the
    true detector (one PC per point) from starts as a user has them after
    indexing at the nominal geometry: the truth times a common rotation of
    0.9 deg and a relative scatter of 0.1 deg (the figures measured on a
    Ni map indexed at the nominal geometry; see the reindexing issue).
    :func:`kikuchipy_geomdic.indexing.reindex.reindex` with ``method="geomdic"``
    (this package's Gauss-Newton solver, with DIC RMS) and with
    ``method="kikuchipy"`` (SciPy Nelder-Mead through
    ``EBSD.refine_orientation``). Printed: patterns per second, the
    ratio, mean misorientation to the truth (absolute, and relative: the
    common rotation removed), and the peak resident memory of each method's
    own process (``+MB``: above the peak after the map was built in memory
    and numba compiled).

``far``
    A polycrystal map whose starting geometry is about 4 % of the detector
    width off (PC and angles), orientations indexed by kikuchipy at that
    geometry (``start="indexed"`` of ``synthetic_map``) from starts a few
    degrees off, and a fraction of points misindexed (their start replaced
    by a random orientation, tens of degrees wrong, as indexing at a wrong
    geometry leaves them). The geometry is calibrated from that start with
    ``refine_geometry_dic`` (joint solver), then the map is reindexed with
    the calibrated detector by both methods. Printed: points more than
    1 deg wrong (relative) and not flagged (``converged`` = 0; kikuchipy
    flags nothing), points flagged, relative misorientation of the rest.

``levels``
    Every level of start error, the solver alone: a 10 x 10 map of random
    Si orientations (seed 5, dose 300) per ``--size``, its patterns
    refined (:func:`~kikuchipy_geomdic.indexing.orientation.refine_patterns`,
    no map: no reseeding, no flags but ``converged``) from the truth
    perturbed by ``--starts`` degrees (RMS, not centred). Printed: points
    within 0.1 deg of the truth, points further and ``converged``, the
    mean error of the right ones, evaluations and time.

``--repeat k`` reindexes k times with each method and reports the median
time (the load of a shared machine varies within seconds); ``far``
prints patterns per second and the speed-up too.

Usage::

    python benchmarks/bench_orientations.py throughput --size 120
    python benchmarks/bench_orientations.py throughput --size 60 240 --rows 30 --cols 30
    python benchmarks/bench_orientations.py far
    python benchmarks/bench_orientations.py far --size 96 --repeat 3
    python benchmarks/bench_orientations.py levels --size 60 96 120

Run it alone on the machine: both methods use every core dask gets.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import resource
import subprocess
import sys
import time
import warnings

import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.indexing.reindex import reindex
from kikuchipy_geomdic.validation import synthetic
from kikuchipy_geomdic.validation.orientations import common_rotation, perturb_rotations

MARK = "BENCH_RESULT "


def _peak_rss_mb() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 2**10


def misorientation(
    rotations: Rotation, truth: Rotation, symmetry, mask=None
) -> tuple[np.ndarray, np.ndarray]:
    """Misorientation to the truth (deg) of each point, with the crystal's
    *symmetry* (a start misindexed by a symmetry operator is right):
    absolute, and with the common rotation (over *mask*) removed."""
    t = truth.flatten()
    r = _closest_equivalent(rotations.flatten(), t, symmetry)
    if mask is None:
        mask = np.ones(r.size, dtype=bool)
    absolute = np.rad2deg((~t * r).angle)
    # The common rotation of the points within a few degrees: a wrong
    # point tens of degrees off would swing the mean rotation vector
    near = mask & (absolute < 5 * np.median(absolute[mask]) + 0.1)
    common = common_rotation(r[near], t[near])
    c = Rotation.from_axes_angles(common.axis, np.deg2rad(common.angle))
    relative = np.rad2deg((~t * (r * ~c)).angle)
    return absolute, relative


def _closest_equivalent(r: Rotation, t: Rotation, symmetry) -> Rotation:
    """Per point the equivalent ``op * r`` closest to *t* (crystal-frame
    operators of the proper point group)."""
    ops = Rotation(getattr(symmetry, "proper_subgroup", symmetry)).flatten()
    angles = np.stack([(~t * (op * r)).angle for op in ops], axis=1)
    return ops[np.argmin(angles, axis=1)] * r


def _reindex(method, sm, start_xmap, detector, repeat=1, **kw):
    """The reindexed map and the median time of *repeat* runs."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            out = reindex(
                sm.signal, start_xmap, detector, sm.master_pattern, sm.energy,
                method=method, show_progressbar=False, **kw,
            )  # fmt: skip
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def _warm_up(size: int) -> None:
    # numba compiles once per process; neither method is timed compiling
    sm = synthetic.synthetic_map("Si", (2, 2), shape=(size, size), seed=0)
    for method in ("geomdic", "kikuchipy"):
        _reindex(method, sm, sm.start_xmap, sm.detector)


def _throughput_map(args, size):
    sm = synthetic.synthetic_map(
        "Si", (args.rows, args.cols), orientations="grains", shape=(size, size),
        dose=args.dose, seed=args.seed,
    )  # fmt: skip
    rng = np.random.default_rng(args.seed)
    axis = rng.normal(size=3)
    common = Rotation.from_axes_angles(axis / np.linalg.norm(axis), np.deg2rad(0.9))
    start = perturb_rotations(sm.xmap.rotations, 0.1, rng) * common
    return sm, start


def one_run(args) -> None:
    """One method on one map, in its own process: its peak memory is its own."""
    size = args.size[0]
    _warm_up(size)
    t0 = time.perf_counter()
    sm, start = _throughput_map(args, size)
    made = time.perf_counter() - t0
    before = _peak_rss_mb()
    n = args.rows * args.cols
    start_xmap = _with_rotations(sm.xmap, start)
    out, sec = _reindex(args.methods[0], sm, start_xmap, sm.detector, args.repeat)
    pg = sm.master_pattern.phase.point_group
    a, r = misorientation(out.rotations, sm.xmap.rotations, pg)
    a0, r0 = misorientation(start, sm.xmap.rotations, pg)
    print(
        MARK
        + json.dumps(
            dict(
                made=made,
                seconds=sec,
                rate=n / sec,
                abs=a.mean(),
                rel=r.mean(),
                med_rel=float(np.median(r)),
                max_rel=r.max(),
                flagged=int((out.prop.get("converged", np.ones(n)) == 0).sum()),
                peak_mb=_peak_rss_mb(),
                before_mb=before,
                start_abs=a0.mean(),
                start_rel=r0.mean(),
                data_mb=sm.signal.data.nbytes / 2**20,
            )  # fmt: skip
        )
    )


def throughput(args) -> None:
    for size in args.size:
        rows = {}
        for method in args.methods:
            cmd = [
                sys.executable, __file__, "_run", "--size", str(size), "--rows", str(args.rows),
                "--cols", str(args.cols), "--dose", str(args.dose), "--seed", str(args.seed),
                "--methods", method, "--repeat", str(args.repeat),
            ]  # fmt: skip
            done = subprocess.run(cmd, capture_output=True, text=True, check=True)
            line = [x for x in done.stdout.splitlines() if x.startswith(MARK)][-1]
            rows[method] = json.loads(line[len(MARK) :])
        first = next(iter(rows.values()))
        print(
            f"\n{args.rows} x {args.cols} Si polycrystal, {size} x {size} px, dose {args.dose} "
            f"(patterns {first['data_mb']:.0f} MB in memory); start "
            f"{first['start_abs']:.3f} deg absolute, {first['start_rel']:.3f} relative"
        )
        print(f"{'method':10s} {'time s':>8s} {'pat/s':>8s} {'abs deg':>9s} {'rel deg':>9s} "
              f"{'med rel':>8s} {'max rel':>8s} {'flagged':>8s} {'peak MB':>8s} "
              f"{'+MB':>6s}")  # fmt: skip
        for method, x in rows.items():
            print(
                f"{method:10s} {x['seconds']:8.2f} {x['rate']:8.1f} {x['abs']:9.4f} "
                f"{x['rel']:9.4f} {x['med_rel']:8.4f} {x['max_rel']:8.3f} {x['flagged']:8d} "
                f"{x['peak_mb']:8.0f} {x['peak_mb'] - x['before_mb']:6.0f}"
            )
        if len(rows) == 2:
            ratio = rows["geomdic"]["rate"] / rows["kikuchipy"]["rate"]
            print(f"speed-up geomdic / kikuchipy: {ratio:.1f}x")


def _with_rotations(xmap, rotations):
    from orix.crystal_map import CrystalMap

    return CrystalMap(
        rotations=rotations.flatten(),
        phase_id=xmap.phase_id.copy(),
        x=xmap.x,
        y=xmap.y,
        phase_list=xmap.phases.deepcopy(),
        prop={k: np.asarray(v).copy() for k, v in xmap.prop.items()},
        scan_unit=xmap.scan_unit,
    )


def far(args) -> None:
    from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic

    size = args.size[0]
    _warm_up(size)
    # About 4 % of the detector width at the map's centre
    perturbation = {"pcx": 0.025, "pcy": -0.025, "pcz": 0.02, "tilt": 1.0, "azimuthal": 0.7}
    t0 = time.perf_counter()
    sm = synthetic.synthetic_map(
        "Si", (args.rows, args.cols), orientations="grains", shape=(size, size),
        dose=args.dose, seed=args.seed, perturbation=perturbation, start="indexed",
        orientation_error=args.orientation_error,
    )  # fmt: skip
    n = args.rows * args.cols
    rng = np.random.default_rng(args.seed + 1)
    wrong = rng.choice(n, int(round(args.misindexed * n)), replace=False)
    start = sm.start_xmap.rotations.flatten().data.copy()
    # Uniformly random orientations, from the seeded generator
    start[wrong] = Rotation(rng.normal(size=(len(wrong), 4))).data
    start = Rotation(start)
    start_xmap = _with_rotations(sm.start_xmap, start)
    pg = sm.master_pattern.phase.point_group
    a0, r0 = misorientation(start, sm.xmap.rotations, pg)
    print(
        f"{args.rows} x {args.cols} Si polycrystal, {size} px, dose {args.dose}, start geometry "
        f"{perturbation}, indexed there by kikuchipy, {len(wrong)} starts misindexed "
        f"(made in {time.perf_counter() - t0:.0f} s)"
    )
    print(f"start: {(a0 > 5).sum()} points > 5 deg off; median {np.median(a0):.2f} deg absolute")
    t0 = time.perf_counter()
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        res = refine_geometry_dic(
            sm.signal, start_xmap, sm.start_detector, sm.master_pattern, sm.energy,
            show_progressbar=False,
        )  # fmt: skip
    pc_err = np.abs(res.detector.pc - sm.detector.pc.reshape(res.detector.pc.shape)).max()
    print(f"calibrated in {time.perf_counter() - t0:.0f} s: largest PC error {pc_err:.2e}")
    print(
        f"{'method':10s} {'time s':>7s} {'pat/s':>7s} {'>1deg unflagged':>16s} {'flagged':>8s} "
        f"{'rel deg (rest)':>15s} {'median':>7s} {'>1deg':>6s} {'median abs':>11s} {'NCC':>6s}"
    )
    rate = {}
    for method in args.methods:
        out, sec = _reindex(method, sm, start_xmap, res.detector, args.repeat)
        rate[method] = n / sec
        ok = out.prop.get("converged", np.ones(n)).astype(bool)
        a, r = misorientation(out.rotations, sm.xmap.rotations, pg, mask=ok)
        bad = r > 1.0
        rest = r[ok & ~bad]
        print(
            f"{method:10s} {sec:7.2f} {n / sec:7.1f} {int((bad & ok).sum()):16d} "
            f"{int((~ok).sum()):8d} {_mean(rest):15.4f} "
            f"{np.median(rest) if rest.size else float('nan'):7.4f} {int(bad.sum()):6d} "
            f"{np.median(a):11.3f} {np.median(out.scores):6.3f}"
        )
    if len(rate) == 2:
        print(f"speed-up geomdic / kikuchipy: {rate['geomdic'] / rate['kikuchipy']:.1f}x")


def levels(args) -> None:
    from kikuchipy_geomdic.indexing.orientation import refine_patterns

    for size in args.size:
        sm = synthetic.synthetic_map(
            "Si", (10, 10), orientations="random", shape=(size, size), dose=args.dose, seed=5
        )
        patterns = sm.signal.data.reshape(-1, size, size)
        # Untimed from the truth first: numba compiles or loads its cache
        refine_patterns(patterns, sm.xmap.rotations, sm.detector, sm.master_pattern, sm.energy)
        for deg in args.starts:
            rng = np.random.default_rng(int(deg * 10))
            start = perturb_rotations(sm.xmap.rotations, deg, rng, centred=False)
            t0 = time.perf_counter()
            res = refine_patterns(patterns, start, sm.detector, sm.master_pattern, sm.energy)
            sec = time.perf_counter() - t0
            err = np.rad2deg((~sm.xmap.rotations.flatten() * res.rotations.flatten()).angle)
            ok = err < 0.1
            print(
                f"{size:4d} px, start {deg:4.1f} deg: right {ok.sum():3d}/100, wrong and "
                f"converged {int((~ok & res.converged).sum()):3d}, mean error of the right "
                f"{_mean(err[ok]):.4f} deg, evaluations {res.evaluations.mean():5.2f}, {sec:.2f} s"
            )


def _mean(a: np.ndarray) -> float:
    return float(a.mean()) if a.size else float("nan")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment", choices=["throughput", "far", "levels", "_run"])
    p.add_argument("--size", type=int, nargs="+", default=[120])
    p.add_argument("--rows", type=int, default=None)
    p.add_argument("--cols", type=int, default=None)
    p.add_argument("--dose", type=float, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--methods", nargs="+", default=["geomdic", "kikuchipy"])
    p.add_argument("--misindexed", type=float, default=0.1, help="far: fraction misindexed")
    p.add_argument("--orientation-error", type=float, default=2.0, help="far: start error, deg")
    p.add_argument("--repeat", type=int, default=1, help="runs per method; the median time")
    p.add_argument(
        "--starts", type=float, nargs="+", default=[0.5, 1, 2, 3, 5, 8], help="levels: deg"
    )
    args = p.parse_args(argv)
    default = 50 if args.experiment == "throughput" else 15
    args.rows = args.rows or default
    args.cols = args.cols or default
    if args.experiment != "_run":
        print(f"command: {' '.join(sys.argv)}")
    run = {"throughput": throughput, "far": far, "levels": levels, "_run": one_run}
    run[args.experiment](args)


if __name__ == "__main__":
    main()
