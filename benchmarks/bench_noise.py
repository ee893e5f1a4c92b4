"""Noise robustness: success against dose (Poisson shot noise), down to
patterns as noisy as the real Ni patterns shipped with kikuchipy.

Usage::

    python benchmarks/bench_noise.py            # 5 doses x 8 runs
    python benchmarks/bench_noise.py --binning 2 --rois 6 --dic-blur 0.5 --suffix _bin2
    python benchmarks/bench_noise.py --quick    # 2 doses x 2 runs

1. The noise of the real data: the nine 60 x 60 Ni patterns of
   ``kikuchipy.data.nickel_ebsd_small()`` (static and dynamic background
   removed) are compared by NCC with patterns simulated from the shipped
   Ni master pattern at their stored orientations and PC. That NCC
   (simulation mismatch included, so a pessimistic measure of noise) is
   matched against the NCC between a noisy synthetic pattern and its
   noise-free version at each dose.
2. For each dose, a small perturbation study (Si polycrystal, 5 x 5 map of
   60 x 60 px, pairs (pcx, pcz) and (tilt, azimuthal) at +-d/2, start at
   the true orientations, blur 0.5 px) counts strict successes
   (misorientation < 0.1 deg and PC error < 1e-3; the paper's NCC > 0.9
   cannot hold for noisy patterns and is not used).
Writes ``benchmarks/results/noise.csv``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np

from kikuchipy_geomdic.validation import study as st
from kikuchipy_geomdic.validation import synthetic, tables

RESULTS = Path(__file__).resolve().parent / "results"


def _ncc(a, b):
    a = a.reshape(len(a), -1).astype(float)
    b = b.reshape(len(b), -1).astype(float)
    a = a - a.mean(1, keepdims=True)
    b = b - b.mean(1, keepdims=True)
    return (a * b).sum(1) / np.sqrt((a**2).sum(1) * (b**2).sum(1))


def real_ni_ncc() -> np.ndarray:
    import kikuchipy as kp

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = kp.data.nickel_ebsd_small()
        s.remove_static_background(show_progressbar=False)
        s.remove_dynamic_background(show_progressbar=False)
        mp = kp.data.nickel_ebsd_master_pattern_small(projection="lambert", hemisphere="both")
        rot = s.xmap.rotations.reshape(*s.detector.navigation_shape)
        sim = mp.get_patterns(rot, s.detector, energy=20, compute=True, show_progressbar=False)
    return _ncc(s.data.reshape(-1, 60, 60), sim.data.reshape(-1, 60, 60))


def synthetic_ncc(dose, blur=0.5, n=9) -> np.ndarray:
    clean = synthetic.synthetic_map("Si", (3, 3), shape=(60, 60), seed=1)
    noisy = synthetic.synthetic_map("Si", (3, 3), shape=(60, 60), seed=1, dose=dose, blur=blur)
    return _ncc(noisy.signal.data.reshape(-1, 60, 60), clean.signal.data.reshape(-1, 60, 60))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--doses", type=float, nargs="+", default=[1000, 100, 30, 10, 3])
    ap.add_argument("--binning", type=int, default=1, help="DIC binning of refine_geometry_dic")
    ap.add_argument(
        "--dic-blur",
        type=float,
        default=0.0,
        help="blur (px) of the simulated patterns before DIC (dic_kwargs['blur'])",
    )
    ap.add_argument("--rois", type=int, default=8, help="ROI grid side")
    ap.add_argument("--map", type=int, default=5, help="map side (points = side^2)")
    ap.add_argument("--suffix", default="")
    args = ap.parse_args(argv)
    doses = [100.0, 3.0] if args.quick else args.doses
    print(
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs (shared), Python "
        f"{platform.python_version()}; map {args.map} x {args.map}, ROIs {args.rois}, DIC binning "
        f"{args.binning}, DIC blur {args.dic_blur}"
    )
    t_all = time.perf_counter()
    ni = real_ni_ncc()
    print(
        f"Real Ni (kikuchipy nickel_ebsd_small, 9 patterns): NCC to simulation "
        f"{ni.mean():.3f} (min {ni.min():.3f}, max {ni.max():.3f})"
    )
    levels = (-0.5, 0.5)
    pairs = [("pcx", "pcz"), ("tilt", "azimuthal")]
    if args.quick:
        pairs, levels = [("pcx", "pcz")], (0.5,)
    rows = []
    for dose in doses:
        ncc = synthetic_ncc(dose)
        nav = (args.map, args.map)
        rkw = dict(
            max_iterations=4,
            refine_kwargs=dict(trust_region=[1, 1, 1]),
            binning=args.binning,
            rois=(args.rois, args.rois),
        )
        if args.dic_blur:
            rkw["dic_kwargs"] = dict(blur=args.dic_blur)
        study = st.perturbation_study(
            "Si",
            pairs=pairs,
            levels=levels,
            navigation_shape=nav,
            shape=(60, 60),
            orientations="random",
            base_geometry=st.paper_geometry(nav, (60, 60)),
            refine_kwargs=rkw,
            dose=dose,
            blur=0.5,
            n_workers=args.workers,
        )
        t = study.table
        if study.settings["errors"]:
            print("Runs that raised:", set(study.settings["errors"]))
        row = dict(
            dose=dose,
            ncc_noisy_vs_clean=float(ncc.mean()),
            as_noisy_as_real_ni=bool(ncc.mean() <= ni.mean()),
            runs=t.size,
            success=int(t["success"].sum()),
            success_ncc=int(t["success_ncc"].sum()),
            median_misorientation=float(np.median(t["misorientation"])),
            max_pc_error=float(t["max_pc_error"].max()),
            median_pc_error=float(np.median(t["max_pc_error"])),
            max_abs_tilt_difference_error=float(np.abs(t["err_tilt_difference"]).max()),
            final_ncc=float(t["final_ncc"].mean()),
            max_initial_displacement=float(t["initial_displacement"].max()),
            minutes=study.wall_time / 60,
        )
        rows.append(row)
        print(tables.format_table([row]), flush=True)
    print("\n" + tables.format_table(rows))
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / f"noise{'_quick' if args.quick else ''}{args.suffix}.csv", "w") as f:
        f.write(",".join(rows[0]) + "\n")
        for r in rows:
            f.write(",".join(str(v) for v in r.values()) + "\n")
    print(f"Total {(time.perf_counter() - t_all) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
