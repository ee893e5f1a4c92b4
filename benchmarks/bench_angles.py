"""When can a map calibrate the detector angles?

Standard errors (and actual errors) of the determined tilt difference
``tilt - sample_tilt`` and of ``azimuthal`` from *indexed* starts with no
orientation prior, against the field of view, the detector distance, the
pattern size and the number of calibration points.

Usage::

    python benchmarks/bench_angles.py            # the study, 48 runs (12 min CPU)
    python benchmarks/bench_angles.py --quick    # smoke test, 5 x 5 maps of 60 px (< 1 min)
    python benchmarks/bench_angles.py --plot     # redo the figure from the CSV

Why: with every orientation free (one rotation per pattern solved jointly
with the geometry), a rotation common to all orientations is exactly a
change of the detector angles; only the variation of the projection centre
(PC) across the map, which grows with the field of view, tells them apart.
So the angles' standard errors should fall about as 1 / field of view.

Every run: one synthetic Si map (``synthetic.synthetic_map``, random
orientations, Poisson shot noise of ``--dose`` counts per pixel, default
300, a moderate noise: noise-free the base map gives standard errors of
4e-4 deg), true geometry ``synthetic.default_geometry`` (480 px detector of
70 um pixels binned to the pattern size, PC (0.51, 0.27, pcz), tilt 2 deg,
azimuthal 0.3 deg, sample tilt 70 deg) with the map's field of view and
pcz, start geometry = truth + ``synthetic.DEFAULT_PERTURBATION`` (PC off by
1.5 % of the width, tilt +0.9 deg, azimuthal -0.75 deg), starting
orientations indexed by kikuchipy at that wrong geometry (start="indexed",
1 deg RMS error before), then ``refine_geometry_dic`` with its defaults
(joint solver, six parameters, no orientation prior) on ``points``
calibration points. Single process; OpenCV, BLAS and numba on one thread,
Dask synchronous.

Base: 10 x 10 map over 500 um, pcz 0.62, 120 x 120 px, 100 points. Sweeps,
one at a time from the base: field of view {100, 250, 500, 1000, 2000} um;
pcz {0.5, 0.62, 0.8}; pattern size {60, 120, 240} px; points {25, 49, 100}
on the 10 x 10 map (same map, fewer points) and 196 on a 14 x 14 map over
the same 500 um. Each configuration with every seed of ``--seeds``.

Columns of ``results/angles.csv``: the configuration; ``sigma_az``,
``sigma_td`` the reported standard errors (deg) of azimuthal and
tilt-sample_tilt; ``err_az``, ``err_td`` refined minus true (deg);
``start_err_*`` the start's error; ``moved_*`` whether the refinement
moved the angle from its start (an angle whose standard error is above
``DETERMINACY_LIMITS`` is moved only by a significant step);
``undetermined``; ``max_pc_err`` the largest PC error over the whole map
(PC units, i.e. fractions of the detector width / height);
``sigma_pc`` the largest standard error of pcx, pcy, pcz (at the map
centre); ``converged``, ``steps``; ``t_map`` (synthetic map and
indexing) and ``t_refine`` (s).

Writes ``results/angles.csv``, ``results/angles.log`` (everything printed)
and ``results/angles.png`` (``_quick`` suffix with --quick).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _tee import Tee  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
LIMIT = 0.1  # uncertainty.DETERMINACY_LIMITS of the angles (deg)

BASE = dict(fov=500.0, pcz=0.62, size=120, nav=10, points=100)
SWEEPS = {
    "fov": dict(fov=[100.0, 250.0, 500.0, 1000.0, 2000.0]),
    "pcz": dict(pcz=[0.5, 0.62, 0.8]),
    "size": dict(size=[60, 120, 240]),
    # 196 points need a 14 x 14 map over the same field of view
    "points": dict(points=[25, 49, 100, 196]),
}
QUICK_BASE = dict(fov=500.0, pcz=0.62, size=60, nav=5, points=25)
QUICK_SWEEPS = {
    "fov": dict(fov=[500.0, 2000.0]),
    "pcz": dict(pcz=[0.62, 0.8]),
    "size": dict(size=[60]),
    "points": dict(points=[9, 25]),
}

COLUMNS = [
    "sweep",
    "seed",
    "fov",
    "pcz",
    "size",
    "nav",
    "points",
    "n_points",
    "sigma_az",
    "err_az",
    "start_err_az",
    "moved_az",
    "sigma_td",
    "err_td",
    "start_err_td",
    "moved_td",
    "undetermined",
    "max_pc_err",
    "start_max_pc_err",
    "sigma_pc",
    "converged",
    "steps",
    "t_map",
    "t_refine",
]
SHOW = [
    "sweep",
    "seed",
    "fov",
    "pcz",
    "size",
    "nav",
    "n_points",
    "sigma_az",
    "err_az",
    "sigma_td",
    "err_td",
    "undetermined",
    "max_pc_err",
    "sigma_pc",
    "t_map",
    "t_refine",
]


def configurations(base: dict, sweeps: dict) -> list[dict]:
    """One-at-a-time configurations; the base is run once (sweep "base")
    and belongs to every sweep. Sorted so that runs sharing a map (the
    points sweep) follow each other."""
    out = [dict(base, sweep="base")]
    for name, values in sweeps.items():
        ((key, vals),) = values.items()
        for v in vals:
            c = dict(base, sweep=name, **{key: v})
            if key == "points" and v > base["nav"] ** 2:
                c["nav"] = int(np.ceil(np.sqrt(v)))
            if all(c[k] == base[k] for k in base):
                continue  # the base itself
            out.append(c)
    order = []
    for c in out:
        if _map_key(c) not in order:
            order.append(_map_key(c))
    return sorted(out, key=lambda c: order.index(_map_key(c)))


def _map_key(c: dict) -> tuple:
    return (c["fov"], c["pcz"], c["size"], c["nav"])


def make_map(c: dict, seed: int, dose: float):
    from kikuchipy_geomdic.validation import synthetic

    nav = (c["nav"], c["nav"])
    shape = (c["size"], c["size"])
    geo = synthetic.default_geometry(nav, shape, c["fov"])
    pc = geo.pc
    geo = replace(geo, pc=(pc[0], pc[1], c["pcz"]))
    return synthetic.synthetic_map(
        "Si",
        nav,
        orientations="random",
        geometry=geo,
        shape=shape,
        dose=dose,
        orientation_error=1.0,
        start="indexed",
        seed=seed,
    )


def run_one(sm, c: dict, seed: int, t_map: float) -> dict:
    from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
    from kikuchipy_geomdic.calibration.uncertainty import TILT_DIFFERENCE

    t0 = time.perf_counter()
    res = refine_geometry_dic(
        sm.signal,
        sm.start_xmap,
        sm.start_detector,
        sm.master_pattern,
        sm.energy,
        points=c["points"],
        show_progressbar=False,
        seed=0,
    )
    t_ref = time.perf_counter() - t0
    true, start, new = sm.geometry, sm.start_geometry, res.geometry

    def td(g):
        return g.tilt - g.sample_tilt

    se = res.standard_errors
    return dict(
        sweep=c["sweep"],
        seed=seed,
        fov=c["fov"],
        pcz=c["pcz"],
        size=c["size"],
        nav=c["nav"],
        points=c["points"],
        n_points=len(res.points),
        sigma_az=se["azimuthal"],
        err_az=new.azimuthal - true.azimuthal,
        start_err_az=start.azimuthal - true.azimuthal,
        moved_az=bool(abs(new.azimuthal - start.azimuthal) > 1e-9),
        sigma_td=se[TILT_DIFFERENCE],
        err_td=td(new) - td(true),
        start_err_td=td(start) - td(true),
        moved_td=bool(abs(td(new) - td(start)) > 1e-9),
        undetermined=" ".join(res.undetermined) or "-",
        max_pc_err=float(np.abs(res.detector.pc - sm.detector.pc).max()),
        start_max_pc_err=float(np.abs(sm.start_detector.pc - sm.detector.pc).max()),
        sigma_pc=max(se[k] for k in ("pcx", "pcy", "pcz")),
        converged=bool(res.converged),
        steps=len(res.history),
        t_map=round(t_map, 1),
        t_refine=round(t_ref, 1),
    )


def _fmt(v) -> str:
    if isinstance(v, float):
        if v == 0 or 1e-3 <= abs(v) < 1e4:
            return f"{v:.4g}"
        return f"{v:.2e}"
    return str(v)


def format_table(rows: list[dict], cols=SHOW) -> str:
    cells = [[_fmt(r[c]) for c in cols] for r in rows]
    widths = [
        max(len(c), *(len(x[i]) for x in cells)) if cells else len(c) for i, c in enumerate(cols)
    ]
    line = "  ".join(c.rjust(w) for c, w in zip(cols, widths, strict=True))
    out = [line, "-" * len(line)]
    out += ["  ".join(x.rjust(w) for x, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join(out)


def read_csv(path: Path) -> list[dict]:
    num = {"seed", "size", "nav", "points", "n_points", "steps"}
    boolean = {"moved_az", "moved_td", "converged"}
    rows = []
    with open(path) as f:
        for r in csv.DictReader(f):
            for k, v in r.items():
                if k in num:
                    r[k] = int(v)
                elif k in boolean:
                    r[k] = v == "True"
                elif k not in ("sweep", "undetermined"):
                    r[k] = float(v)
            rows.append(r)
    return rows


def in_sweep(rows: list[dict], sweep: str) -> list[dict]:
    return [r for r in rows if r["sweep"] in (sweep, "base")]


def summary(rows: list[dict]) -> str:
    """Per configuration: median sigma over the seeds; the error/sigma
    check; log-log slopes of sigma."""
    lines = []
    keys = []
    for r in rows:
        k = (r["fov"], r["pcz"], r["size"], r["nav"], r["points"])
        if k not in keys:
            keys.append(k)
    lines.append("Per configuration (over the seeds): median sigma, RMS |error| (deg)")
    hdr = (
        f"{'fov_um':>7} {'pcz':>5} {'px':>4} {'map':>6} {'N':>4} {'seeds':>5} "
        f"{'sigma_az':>9} {'rms_err_az':>10} {'sigma_td':>9} {'rms_err_td':>10} "
        f"{'max_pc_err':>10} {'t_refine':>8}"
    )
    lines += [hdr, "-" * len(hdr)]
    for k in sorted(keys):
        g = [r for r in rows if (r["fov"], r["pcz"], r["size"], r["nav"], r["points"]) == k]

        def med(c, g=g):
            return float(np.median([r[c] for r in g]))

        def rms(c, g=g):
            return float(np.sqrt(np.mean([r[c] ** 2 for r in g])))

        lines.append(
            f"{k[0]:7.0f} {k[1]:5.2f} {k[2]:4d} {k[3]:>3d}x{k[3]:<2d} {k[4]:4d} {len(g):5d} "
            f"{med('sigma_az'):9.4f} {rms('err_az'):10.4f} {med('sigma_td'):9.4f} "
            f"{rms('err_td'):10.4f} {med('max_pc_err'):10.2e} {med('t_refine'):8.1f}"
        )
    # Standard errors against actual errors, over runs that moved the angle
    lines.append("\nerror / sigma, over the runs where the refinement moved the angle:")
    for a, name in (("az", "azimuthal"), ("td", "tilt-sample_tilt")):
        z = np.array([r[f"err_{a}"] / r[f"sigma_{a}"] for r in rows if r[f"moved_{a}"]])
        zdet = np.array(
            [
                r[f"err_{a}"] / r[f"sigma_{a}"]
                for r in rows
                if r[f"moved_{a}"] and r[f"sigma_{a}"] <= LIMIT
            ]
        )
        if len(z):
            lines.append(
                f"  {name:>16}: {len(z)} runs, RMS {np.sqrt(np.mean(z**2)):.2f}, "
                f"mean {z.mean():+.2f}, max |z| {np.abs(z).max():.2f}, "
                f"|z| > 2 in {(np.abs(z) > 2).sum()}; sigma <= {LIMIT} deg: {len(zdet)} runs"
                + (f", RMS {np.sqrt(np.mean(zdet**2)):.2f}" if len(zdet) else "")
            )
        kept = [r for r in rows if not r[f"moved_{a}"]]
        if kept:
            lines.append(
                f"  {'':>16}  {len(kept)} runs kept {name} at its start "
                f"(error {np.median([r[f'start_err_{a}'] for r in kept]):+.2f} deg)"
            )
    # Slopes of log sigma
    lines.append("\nLog-log slope of the median sigma (least squares over the sweep):")
    for sweep, key in (("fov", "fov"), ("pcz", "pcz"), ("size", "size"), ("points", "n_points")):
        g = in_sweep(rows, sweep)
        xs = sorted({r[key] for r in g})
        if len(xs) < 2:
            continue
        for a in ("az", "td"):
            y = [np.median([r[f"sigma_{a}"] for r in g if r[key] == x]) for x in xs]
            s = np.polyfit(np.log(xs), np.log(y), 1)[0]
            lines.append(f"  sigma_{a} vs {key}: slope {s:+.2f}")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, dose: float, base: dict = BASE) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(2, 3, figsize=(13, 8.8))
    panels = [
        ("fov", "fov", "field of view (um)", True),
        ("points", "n_points", "calibration points N", True),
        ("pcz", "pcz", "detector distance pcz (fraction of width)", False),
        ("size", "size", "pattern size (px)", True),
    ]
    colors = {"az": "C0", "td": "C3"}
    names = {"az": "azimuthal", "td": "tilt - sample_tilt"}
    flat = axes.ravel()
    for ax, (sweep, key, label, logx) in zip(flat[:4], panels, strict=True):
        g = in_sweep(rows, sweep)
        xs = sorted({r[key] for r in g})
        for a in ("az", "td"):
            x = np.array([r[key] for r in g], float)
            jitter = 1.03 if a == "td" else 0.97
            xj = x * jitter if logx else x + (0.004 if a == "td" else -0.004)
            ax.plot(
                xj,
                [r[f"sigma_{a}"] for r in g],
                "o",
                color=colors[a],
                ms=5,
                label=f"sigma {names[a]}",
            )
            moved = np.array([r[f"moved_{a}"] for r in g], bool)
            err = np.array([abs(r[f"err_{a}"]) for r in g])
            ax.plot(
                xj[moved],
                err[moved],
                "x",
                color=colors[a],
                ms=5,
                alpha=0.7,
                label=f"|error| {names[a]}",
            )
            ax.plot(
                xj[~moved],
                err[~moved],
                "+",
                color=colors[a],
                ms=7,
                alpha=0.4,
                label=f"|error| {names[a]}, kept at start",
            )
            med = [np.median([r[f"sigma_{a}"] for r in g if r[key] == v]) for v in xs]
            ax.plot(xs, med, "-", color=colors[a], lw=1)
        if sweep == "fov" and len(xs) > 1:
            ref = np.median([r["sigma_td"] for r in g if r["fov"] == base["fov"]] or [1])
            xx = np.array([xs[0], xs[-1]])
            ax.plot(xx, ref * base["fov"] / xx, "k:", lw=1, label="1 / FOV")
        if sweep == "points" and len(xs) > 1:
            ref = np.median([r["sigma_td"] for r in g if r["n_points"] == base["points"]] or [1])
            xx = np.array([xs[0], xs[-1]])
            ax.plot(xx, ref * np.sqrt(base["points"] / xx), "k:", lw=1, label="1 / sqrt(N)")
        ax.axhline(LIMIT, color="k", ls="--", lw=1, label="DETERMINACY_LIMIT 0.1 deg")
        ax.set_yscale("log")
        if logx:
            ax.set_xscale("log")
            ax.set_xticks(xs)
            ax.set_xticklabels([f"{v:g}" for v in xs])
            ax.minorticks_off()
        ax.set_xlabel(label)
        ax.set_ylabel("deg")
        ax.set_title(f"{sweep} sweep")
        ax.grid(alpha=0.3, which="both")
    handles, labels = flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8)
    # error / sigma of every run that moved the angle
    ax = flat[4]
    for a in ("az", "td"):
        g = [r for r in rows if r[f"moved_{a}"]]
        ax.plot(
            [r[f"sigma_{a}"] for r in g],
            [r[f"err_{a}"] / r[f"sigma_{a}"] for r in g],
            "o",
            color=colors[a],
            ms=5,
            label=names[a],
        )
    for y in (-2, 2):
        ax.axhline(y, color="k", ls=":", lw=1)
    ax.axhline(0, color="k", lw=0.5)
    ax.axvline(LIMIT, color="k", ls="--", lw=1)
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xticks([0.05, 0.1, 0.2, 0.5])
    ax.set_xlabel("reported sigma (deg)")
    ax.set_ylabel("error / sigma")
    ax.set_title("error / sigma (runs that moved the angle)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    # max PC error vs field of view
    ax = flat[5]
    g = in_sweep(rows, "fov")
    ax.plot(
        [r["fov"] for r in g],
        [r["max_pc_err"] for r in g],
        "s",
        color="C2",
        label="max PC error on the map",
    )
    ax.plot(
        [r["fov"] for r in g],
        [r["sigma_pc"] for r in g],
        "^",
        color="C1",
        label="max sigma of pcx, pcy, pcz",
    )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("field of view (um)")
    ax.set_ylabel("PC (fraction of detector)")
    ax.set_title("PC error, fov sweep")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    fig.suptitle(
        f"Detector angles from indexed starts, no orientation prior (Si, dose {dose:g} "
        f"counts/px; base {base['nav']} x {base['nav']} map, {base['fov']:g} um, "
        f"{base['size']} px, pcz {base['pcz']:g}, {base['points']} points)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny grid (< 1 min)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    p.add_argument("--dose", type=float, default=300.0)
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--plot", action="store_true", help="only redo the figure and summary")
    p.add_argument(
        "--sweeps",
        nargs="+",
        choices=list(SWEEPS),
        default=list(SWEEPS),
        help="sweeps to run (the base is always run)",
    )
    p.add_argument(
        "--unrestricted",
        action="store_true",
        help="diagnostic: DETERMINACY_LIMITS set to infinity in this process, so "
        "that every parameter moves freely at every iteration (no 'significant "
        "step' rule); writes angles_unrestricted.*",
    )
    args = p.parse_args(argv)
    suffix = ("_quick" if args.quick else "") + ("_unrestricted" if args.unrestricted else "")
    if args.unrestricted:
        from kikuchipy_geomdic.calibration import uncertainty

        for k in uncertainty.DETERMINACY_LIMITS:
            uncertainty.DETERMINACY_LIMITS[k] = float("inf")
    if args.quick and args.seeds == [0, 1, 2, 3]:
        args.seeds = [0]
    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = args.out / f"angles{suffix}.csv"
    png_path = args.out / f"angles{suffix}.png"
    if args.plot:
        rows = read_csv(csv_path)
        print(summary(rows))
        plot(rows, png_path, args.dose, QUICK_BASE if args.quick else BASE)
        return 0

    import cv2
    import dask

    cv2.setNumThreads(1)
    dask.config.set(scheduler="synchronous")
    log = open(args.out / f"angles{suffix}.log", "w")
    sys.stdout = Tee(sys.__stdout__, log)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).parent,
    ).stdout.strip()
    import kikuchipy

    print(f"# bench_angles.py, {datetime.datetime.now():%Y-%m-%d %H:%M}, commit {commit}")
    print(
        "Command: python benchmarks/bench_angles.py "
        + " ".join(sys.argv[1:] if argv is None else argv)
    )
    print(
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs (shared), Python "
        f"{platform.python_version()}, kikuchipy {kikuchipy.__version__}, OpenCV "
        f"{cv2.__version__}; one thread, single process"
    )
    base, sweeps = (QUICK_BASE, QUICK_SWEEPS) if args.quick else (BASE, SWEEPS)
    sweeps = {k: v for k, v in sweeps.items() if k in args.sweeps}
    confs = configurations(base, sweeps)
    if args.unrestricted:
        print(
            "DIAGNOSTIC: DETERMINACY_LIMITS set to inf (no parameter held, no "
            "'significant step' rule; 'undetermined' is then always empty)"
        )
    print(
        f"Base {base}, dose {args.dose:g}, seeds {args.seeds}, {len(confs)} "
        f"configurations, {len(confs) * len(args.seeds)} runs\n"
    )
    t_all = time.perf_counter()
    rows = []
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for seed in args.seeds:
            cache = {}
            for c in confs:
                key = _map_key(c)
                if key not in cache:
                    cache.clear()
                    t0 = time.perf_counter()
                    cache[key] = make_map(c, seed, args.dose)
                    t_map = time.perf_counter() - t0
                else:
                    t_map = 0.0  # same map as the run before
                row = run_one(cache[key], c, seed, t_map)
                rows.append(row)
                w.writerow(row)
                f.flush()
                print(
                    f"seed {seed} {c['sweep']:>6}: fov {c['fov']:g} um, pcz {c['pcz']:g}, "
                    f"{c['size']} px, {c['nav']}x{c['nav']}, N {row['n_points']}: sigma az "
                    f"{row['sigma_az']:.4f} err {row['err_az']:+.4f}, sigma td "
                    f"{row['sigma_td']:.4f} err {row['err_td']:+.4f}, undetermined "
                    f"{row['undetermined']}, max PC err {row['max_pc_err']:.1e}, "
                    f"{t_map:.1f} + {row['t_refine']:.1f} s",
                    flush=True,
                )
    total = time.perf_counter() - t_all
    print("\n" + format_table(rows))
    print("\n" + summary(rows))
    print(f"\nTotal {total / 60:.1f} min ({total:.0f} s) for {len(rows)} runs")
    plot(rows, png_path, args.dose, base)
    print(f"Wrote {csv_path}, {png_path}")
    sys.stdout = sys.__stdout__
    log.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
