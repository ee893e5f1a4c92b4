"""Joint DIC solver vs the paper's DIC solver vs kikuchipy's pattern-wise
refiners (Nelder-Mead, differential evolution), on one CPU, two starts.

Usage::

    python benchmarks/bench_joint.py            # 10 x 10 Si map, 120 x 120 px, N = 100
    python benchmarks/bench_joint.py --quick    # 4 x 4 map, 60 x 60 px, DE on 2 points
    # realistic patterns (Camera, 150 counts/px), indexed start
    python benchmarks/bench_joint.py --starts indexed --camera 150 \
        --out benchmarks/results/realistic
    # noise study: real-Ni noise, against Nelder-Mead and the oracle, one seed
    python benchmarks/bench_joint.py --starts indexed --dose 10 --methods dic nelder-mead \
        --oracle --seed 0 --suffix _dose10_seed0

The oracle (``--oracle``) calibrates the same map with the true
orientations held fixed (``orientation_prior`` of 1e-4 deg): the noise
floor of the data, against which the joint solve from indexed starts is
judged.

Per start, one synthetic Si map (``master_patterns.master_pattern("Si")``,
orientations ``--orientations``, default "random"; true geometry
``synthetic.default_geometry``; start geometry = truth +
``synthetic.DEFAULT_PERTURBATION``) and one call of
``comparison.compare_methods`` with the Dask synchronous scheduler (and
OpenCV / BLAS / numba limited to one thread), so every time is a
single-CPU time as in the paper (each method first run once untimed on
a few points, so that no time includes a process's first-call costs):

- ``dic``: ``refine_geometry_dic`` defaults (joint solver: the DIC stage,
  then the full field, Gauss-Newton on the intensities; for the centred
  start ``compare_methods`` adds ``orientation_prior=0.3``);
- ``dic-only``: the same with ``full_field=False`` (the DIC stage alone);
- ``dic-paper``: the same with ``solver="paper"``;
- ``nelder-mead``: kikuchipy ``refine_orientation_projection_center`` per
  pattern, SciPy Nelder-Mead, trust region 3 deg / 0.05, PCs averaged,
  orientations re-refined at the averaged geometry (``time_rerefine``, not
  in ``time``);
- ``differential-evolution``: the same with SciPy DE (``--de-maxiter``,
  default 50) on ``--de-points`` points (default 10): its ``time_at_n`` is
  **extrapolated** from its time per point (``extrapolated`` column).

Starts:

- ``indexed`` (A, realistic): orientations refined by kikuchipy at the
  wrong start geometry, 1.0 deg RMS random error before that, dose 300
  (Poisson shot noise);
- ``centred`` (B, the paper's): 0.3 deg RMS random error centred to zero
  mean, no noise.

Besides ``compare_methods``' columns, the final rotations of every method
are recorded (by wrapping the three functions ``compare_methods`` calls,
in this script only) to give the misorientation with the rotation common
to all points removed (as ``common_rotation``, the mean rotation
vector of ``~truth * rotation``, but over the points within 1 deg of the
median vector: see :func:`misorientations`), which is what no calibration
can tell from a detector-angle error; its mean and median over the points,
``n_off`` the points still more than 1 deg off, ``common_rotation`` its
angle. ``misorientation_rerefined*``: NM/DE orientations re-refined at the
averaged geometry (DIC: its own). ``speedup`` is ``time_at_n`` of the method
over ``time_at_n`` of ``dic``; ``undetermined`` lists the parameters the
DIC refinement kept at their start value (NM and DE cannot refine the
angles at all).

Writes ``<out>/joint_<start>.csv`` (``_quick`` suffix with --quick) and
``<out>/joint_bench.log`` (everything printed).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _tee import Tee  # noqa: E402
from orix.quaternion import Rotation  # noqa: E402

from kikuchipy_geomdic.calibration.refinement import calibration_points  # noqa: E402
from kikuchipy_geomdic.geometry import rotation_vectors  # noqa: E402
from kikuchipy_geomdic.geometry.maps import flat_index  # noqa: E402
from kikuchipy_geomdic.validation import comparison, master_patterns, scores, synthetic, tables  # noqa: E402
from kikuchipy_geomdic.validation.camera import Camera  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
#: A point further than this (deg) from the common rotation counts as off
OFF = 1.0
METHODS = ("dic", "dic-only", "dic-paper", "nelder-mead", "differential-evolution")
#: Prior (deg) that holds the true orientations of the oracle fixed
ORACLE_PRIOR = 1e-4
STARTS = {
    "indexed": dict(start="indexed", orientation_error=1.0, dose=300),
    "centred": dict(start="centred", orientation_error=0.3, dose=None),
}
COLUMNS = [
    "method",
    "n_points",
    "time",
    "time_per_point",
    "time_at_n",
    "extrapolated",
    "speedup",
    "iterations",
    "max_pc_error",
    "err_pcx",
    "err_pcy",
    "err_pcz",
    "err_tilt_difference",
    "err_azimuthal",
    "misorientation",
    "misorientation_nocommon",
    "misorientation_nocommon_median",
    "n_off",
    "common_rotation",
    "misorientation_rerefined",
    "misorientation_rerefined_nocommon",
    "misorientation_rerefined_nocommon_median",
    "time_rerefine",
    "ncc",
    "undetermined",
]
#: Columns of the printed table: the CSV's without the details
SHOW = [
    c
    for c in COLUMNS
    if c
    not in (
        "iterations",
        "err_pcx",
        "err_pcy",
        "err_pcz",
        "misorientation_rerefined_nocommon",
        "time_rerefine",
        "ncc",
    )
]


def _angles(a: Rotation, b: Rotation) -> np.ndarray:
    return np.rad2deg((a * ~b).angle).ravel()


def misorientations(rot: Rotation, truth: Rotation) -> dict[str, float]:
    """Misorientation (deg) to the truth, with and without the common rotation.

    The common rotation is the mean rotation vector of the deviations
    ``T = ~truth * rot`` (as ``common_rotation``) taken over the
    points within :data:`OFF` deg of the component-wise median vector, so
    that one mis-indexed point (13 deg off here) does not shift it for all
    the others; it is removed as a right factor (``rot * ~C``).
    """
    rot, truth = rot.flatten(), truth.flatten()
    v = np.rad2deg(rotation_vectors(~truth * rot))
    inl = np.linalg.norm(v - np.median(v, axis=0), axis=1) < OFF
    cv = v[inl].mean(axis=0) if inl.any() else np.zeros(3)
    angle = float(np.linalg.norm(cv))
    axis = cv / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    c = Rotation.from_axes_angles(axis, np.deg2rad(angle))
    m = _angles(rot, truth)
    mc = _angles(rot * ~c, truth)
    return dict(
        mean=float(m.mean()),
        nocommon=float(mc.mean()),
        nocommon_median=float(np.median(mc)),
        n_off=int((mc > OFF).sum()),
        common=angle,
    )


class _Recorder:
    """Wrap the functions compare_methods calls to keep each method's final
    rotations and points (in call order, one record per method)."""

    def __init__(self):
        self.records: list[dict] = []
        self._orig = {}

    def __enter__(self):
        o = self._orig
        o["dic"] = comparison.refine_geometry_dic
        o["pw"] = comparison._pattern_wise
        o["ref"] = comparison.refine_orientations

        def dic(*a, **k):
            res = o["dic"](*a, **k)
            rot = res.xmap.rotations
            self.records.append(
                dict(
                    points=np.asarray(res.points),
                    own=rot,
                    rerefined=rot,
                    undetermined=" ".join(getattr(res, "undetermined", ()) or ()) or "-",
                )
            )
            return res

        def pw(*a, **k):
            xmap_r, det_r = o["pw"](*a, **k)
            self.records.append(
                dict(points=np.asarray(a[4]), own=xmap_r.rotations, undetermined="angles (fixed)")
            )
            return xmap_r, det_r

        def ref(*a, **k):
            out = o["ref"](*a, **k)
            self.records[-1]["rerefined"] = out.rotations
            return out

        comparison.refine_geometry_dic = dic
        comparison._pattern_wise, comparison.refine_orientations = pw, ref
        return self

    def __exit__(self, *exc):
        o = self._orig
        comparison.refine_geometry_dic = o["dic"]
        comparison._pattern_wise, comparison.refine_orientations = o["pw"], o["ref"]


def run_oracle(sm, points, dic_kwargs=None):
    """The geometry calibrated with the true orientations held fixed (a
    prior of :data:`ORACLE_PRIOR`): the noise floor of the data."""
    from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic

    t0 = time.perf_counter()
    res = refine_geometry_dic(
        sm.signal,
        sm.xmap,
        sm.start_detector,
        sm.master_pattern,
        sm.energy,
        points=points,
        orientation_prior=ORACLE_PRIOR,
        dic_kwargs=dic_kwargs,
        show_progressbar=False,
    )
    return dict(
        method="oracle",
        n_points=len(res.points),
        time=time.perf_counter() - t0,
        max_pc_error=float(np.abs(res.detector.pc - sm.detector.pc).max()),
        **{f"err_{k}": v for k, v in scores._geometry_errors(res.geometry, sm.geometry).items()},
    )


def _dic_kwargs(args) -> dict:
    return {} if args.window is None else dict(window=args.window)


def run_start(name, args, mp, side, out_dir, suffix):
    kw = dict(STARTS[name])
    if args.dose is not None:
        kw["dose"] = args.dose or None
    if args.camera is not None:
        # Realistic patterns: recorded by a camera, processed by the user
        kw.pop("dose", None)
        kw["camera"] = Camera(dose=args.camera)
    t0 = time.perf_counter()
    sm = synthetic.synthetic_map(
        mp,
        (side, side),
        orientations=args.orientations,
        shape=(args.size, args.size),
        seed=args.seed,
        **kw,
    )
    t_map = time.perf_counter() - t0
    nav = sm.geometry.navigation_shape
    pts = calibration_points(nav, side * side)
    flat = flat_index(pts, nav)
    truth_all = sm.xmap.rotations.flatten()
    m0 = misorientations(sm.start_xmap.rotations.flatten()[flat], truth_all[flat])
    d0 = scores.mean_displacement(sm.start_geometry, sm.geometry)
    print(
        f"\n## Start {name!r}: {kw}, {side} x {side} map of {args.size} x {args.size} px, "
        f"orientations {args.orientations!r}, seed {args.seed} (map built in {t_map:.0f} s)\n"
        f"Start: displacement {100 * d0:.2f} % of the width; misorientation {m0['mean']:.3f} "
        f"deg; without the common rotation of {m0['common']:.3f} deg: mean "
        f"{m0['nocommon']:.3f}, median {m0['nocommon_median']:.3f} deg, {m0['n_off']} "
        f"point(s) > {OFF:g} deg off",
        flush=True,
    )
    configs = dict(
        methods=args.methods,
        refine_kwargs=dict(dic_kwargs=_dic_kwargs(args)),
        dic_configs={
            "dic-paper": dict(solver="paper", dic_kwargs=_dic_kwargs(args)),
            "dic-only": dict(full_field=False, dic_kwargs=_dic_kwargs(args)),
        },
        scheduler="synchronous",
    )
    # Every method once on a few points first, untimed: the first call in
    # a process loads numba's caches, OpenCV and the master pattern's
    # arrays (0.3-0.6 s for the defaults), which no later call pays
    comparison.compare_methods(
        sm,
        points=4,
        method_points={"differential-evolution": 2},
        de_kwargs=dict(seed=0, maxiter=2),
        **configs,
    )
    with _Recorder() as rec:
        rows = comparison.compare_methods(
            sm,
            points=side * side,
            method_points={"differential-evolution": args.de_points},
            de_kwargs=dict(seed=0, maxiter=args.de_maxiter),
            verbose=True,
            **configs,
        )
    if len(rec.records) != len(rows):
        raise RuntimeError(f"{len(rec.records)} rotation records for {len(rows)} methods")
    t_dic = next(r for r in rows if r["method"] == "dic")["time_at_n"]
    for r, rc in zip(rows, rec.records, strict=True):
        f = flat_index(rc["points"], nav)
        own = misorientations(rc["own"], truth_all[f])
        if not np.isclose(own["mean"], r["misorientation"], rtol=1e-6, atol=1e-9):
            raise RuntimeError(f"{r['method']}: recorded rotations do not match the row")
        rr = misorientations(rc["rerefined"], truth_all[f])
        r.update(
            misorientation_nocommon=own["nocommon"],
            misorientation_nocommon_median=own["nocommon_median"],
            n_off=own["n_off"],
            common_rotation=own["common"],
            misorientation_rerefined_nocommon=rr["nocommon"],
            misorientation_rerefined_nocommon_median=rr["nocommon_median"],
            speedup=r["time_at_n"] / t_dic,
            undetermined=rc["undetermined"],
        )
    print(tables.format_table(rows, SHOW), flush=True)
    by = {r["method"]: r for r in rows}
    print(
        "\nDIC joint speed-up (time_at_n ratio"
        + (
            f"; DE extrapolated from {by['differential-evolution']['n_points']} points"
            if "differential-evolution" in by
            else ""
        )
        + "): "
        + ", ".join(f"{m} {by[m]['speedup']:.2f}x" for m in args.methods[1:]),
        flush=True,
    )
    if args.oracle:
        o = run_oracle(sm, side * side, _dic_kwargs(args))
        print(
            f"Oracle (true orientations held fixed): max PC error {o['max_pc_error']:.2e} in "
            f"{o['time']:.1f} s; DIC joint / oracle PC error "
            f"{by['dic']['max_pc_error'] / o['max_pc_error']:.2f}",
            flush=True,
        )
        rows.append(o)
    with open(out_dir / f"joint_{name}{suffix}.csv", "w") as fh:
        fh.write(",".join(COLUMNS) + "\n")
        for r in rows:
            fh.write(",".join(str(r.get(c, "")) for c in COLUMNS) + "\n")
    return rows


def _code_version() -> str:
    """HEAD commit and whether the package has uncommitted changes (read-only git)."""
    import subprocess

    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "kikuchipy_geomdic"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + (" + uncommitted changes to kikuchipy_geomdic" if dirty else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="4 x 4 map, 60 px, DE on 2 points")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder")
    ap.add_argument("--points", type=int, default=100, help="calibration points (a square)")
    ap.add_argument("--size", type=int, default=120, help="pattern side in px")
    ap.add_argument("--de-points", type=int, default=10)
    ap.add_argument(
        "--de-maxiter",
        type=int,
        default=50,
        help="SciPy differential_evolution maxiter (its default 1000 took ~290 s "
        "per 60 x 60 pattern here)",
    )
    ap.add_argument("--orientations", default="random", choices=("random", "single", "variants"))
    ap.add_argument("--starts", nargs="+", default=list(STARTS), choices=list(STARTS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--methods", nargs="+", default=list(METHODS), choices=METHODS, help="dic first"
    )
    ap.add_argument(
        "--dose",
        type=float,
        default=None,
        help="shot noise (counts/px) of every start instead of its own; 0: none",
    )
    ap.add_argument(
        "--camera",
        type=float,
        default=None,
        help="counts/px of a Camera (realistic patterns: background lobe, "
        "blur, shot noise, static and dynamic background removal) instead of --dose",
    )
    ap.add_argument(
        "--oracle",
        action="store_true",
        help="also calibrate with the true orientations held fixed",
    )
    ap.add_argument("--suffix", default="", help="added to the output file names")
    ap.add_argument(
        "--window", type=int, default=None, help="Lucas-Kanade window (px) of every DIC run"
    )
    args = ap.parse_args(argv)
    if args.methods[0] != "dic":
        ap.error("--methods must start with dic (speed-ups are relative to it)")
    if args.quick:
        args.points, args.size, args.de_points = 16, 60, 2
    suffix = ("_quick" if args.quick else "") + args.suffix
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass
    args.out.mkdir(parents=True, exist_ok=True)
    log = open(args.out / f"joint_bench{suffix}.log", "w")
    stdout = sys.stdout
    sys.stdout = Tee(stdout, log)
    try:
        side = int(round(np.sqrt(args.points)))
        print(
            f"bench_joint.py {' '.join(argv if argv is not None else sys.argv[1:])}\n"
            f"{datetime.datetime.now().isoformat(timespec='seconds')}; machine "
            f"{platform.node()}, {os.cpu_count()} CPUs (shared), Python "
            f"{platform.python_version()}; single-CPU timing (dask synchronous, 1 thread)\n"
            f"DE: maxiter {args.de_maxiter}, {args.de_points} points, time extrapolated to "
            f"{side * side}; time excludes the NM/DE re-refinement (time_rerefine)\n"
            f"Code: {_code_version()}"
        )
        t_all = time.perf_counter()
        mp = master_patterns.master_pattern("Si")
        for name in args.starts:
            run_start(name, args, mp, side, args.out, suffix)
        print(f"\nTotal {(time.perf_counter() - t_all) / 60:.1f} min")
    finally:
        sys.stdout = stdout
        log.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
