"""Benchmark: telling BaTiO3's pseudo-symmetric variants apart.

A BaTiO3 stripe-domain map (``synthetic_map(orientations="stripes")``:
the parent, a 90 deg (+x) and a 180 deg (-z) domain), the start the
parent's variant everywhere, as an indexer that cannot tell the variants
apart returns it. Reindexed with ``reindex(..., pseudo_symmetry_ops=...)``
(this package's solver: every variant of every point refined, the kept one
chosen by ``orientation.compare_variants``).

``picks``
    At the true detector, against dose: the share of points given their
    true variant, per true variant (base, 180 deg, 90 deg), by the
    confidence index and by plain NCC (the argmax of ``variant_score_k``),
    and kikuchipy's ``refine_orientation`` with ``pseudo_symmetry_ops``
    (best plain NCC over its refined variants); the smallest
    cross-variant margin above which >= 95 % of the points are right, and
    the share of points it keeps. ``--mismatch`` reindexes with the coarse
    ebsdsim master pattern patterns simulated from the de-ebsd one.

``detectors``
    The paper's Fig. 7C-D comparison: a map whose starting geometry is
    ``--offset`` off, reindexed at the nominal (start) detector and at the
    DIC-calibrated one (``refine_geometry_dic`` with the operators):
    largest PC error, variant accuracy, mean margin and confidence.

Usage::

    python benchmarks/bench_variants.py picks
    python benchmarks/bench_variants.py picks --mismatch
    python benchmarks/bench_variants.py detectors
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
import warnings

import numpy as np

from kikuchipy_geomdic import synthetic
from kikuchipy_geomdic.reindex import reindex

KINDS = {0: "base", 1: "180 deg", 2: "90 deg"}


def _map(args, dose, perturbation, seed):
    return synthetic.synthetic_map(
        "BaTiO3", (args.rows, args.rows), orientations="stripes", shape=(args.size, args.size),
        dose=dose, seed=seed, perturbation=perturbation,
    )  # fmt: skip


def _quiet():
    stack = contextlib.ExitStack()
    stack.enter_context(contextlib.redirect_stdout(io.StringIO()))
    stack.enter_context(warnings.catch_warnings())
    warnings.simplefilter("ignore")
    return stack


def margin_threshold(margin: np.ndarray, right: np.ndarray, share: float = 0.95):
    """The smallest margin above which at least *share* of the points are
    right, and the fraction of points it keeps (NaN, 0 if none)."""
    for t in np.sort(margin):
        keep = margin >= t
        if right[keep].mean() >= share:
            return float(t), float(keep.mean())
    return float("nan"), 0.0


def picks(args) -> None:
    ops = synthetic.variant_operators()[1:]
    mp = synthetic.master_pattern("BaTiO3", kind="ebsdsim") if args.mismatch else None
    print(
        f"{'dose':>6s} {'rule':<22s} {'base':>6s} {'180deg':>7s} {'90deg':>6s} "
        f"{'margin t95':>10s} {'kept':>5s} {'time s':>7s}"
    )
    for dose in args.doses:
        sm = _map(args, dose, {}, args.seed)
        truth = sm.xmap.prop["variant"]
        cal = mp or sm.master_pattern
        t0 = time.perf_counter()
        with _quiet():
            out = reindex(
                sm.signal, sm.start_xmap, sm.detector, cal, 20, pseudo_symmetry_ops=ops,
                show_progressbar=False,
            )  # fmt: skip
        sec = time.perf_counter() - t0
        scores = np.stack([out.prop[f"variant_score_{k}"] for k in range(6)], axis=1)
        rules = {"confidence index": out.variant, "plain NCC": scores.argmax(axis=1)}
        if "kikuchipy" in args.methods:
            t1 = time.perf_counter()
            with _quiet():
                nm = reindex(
                    sm.signal, sm.start_xmap, sm.detector, cal, 20, pseudo_symmetry_ops=ops,
                    method="kikuchipy", show_progressbar=False,
                )  # fmt: skip
            rules["kikuchipy NM (NCC)"] = nm.pseudo_symmetry_index
            nm_sec = time.perf_counter() - t1
        for name, v in rules.items():
            right = v == truth
            acc = [right[truth == k].mean() for k in KINDS]
            t, kept = (
                margin_threshold(out.cross_variant_margin, right)
                if name == "confidence index"
                else (np.nan, np.nan)
            )
            sec_r = nm_sec if name.startswith("kikuchipy") else sec
            print(
                f"{dose:6g} {name:<22s} {acc[0]:6.1%} {acc[1]:7.1%} {acc[2]:6.1%} "
                f"{t:10.3f} {kept:5.0%} {sec_r:7.1f}"
            )


def detectors(args) -> None:
    from kikuchipy_geomdic.refinement import refine_geometry_dic

    ops = synthetic.variant_operators()[1:]
    off = args.offset
    perturbation = {"pcx": off, "pcy": -off, "pcz": off, "tilt": 0.5, "azimuthal": 0.3}
    sm = _map(args, args.doses[0], perturbation, args.seed)
    truth = sm.xmap.prop["variant"]
    t0 = time.perf_counter()
    with _quiet():
        res = refine_geometry_dic(
            *sm.start_inputs, pseudo_symmetry_ops=ops, show_progressbar=False
        )
    t_cal = time.perf_counter() - t0
    print(
        f"{'detector':<16s} {'max PC err':>10s} {'base':>6s} {'180deg':>7s} {'90deg':>6s} "
        f"{'margin':>7s} {'confidence':>10s}"
    )
    for name, det in (("nominal", sm.start_detector), ("DIC-calibrated", res.detector)):
        with _quiet():
            out = reindex(
                sm.signal, sm.start_xmap, det, sm.master_pattern, 20, pseudo_symmetry_ops=ops,
                show_progressbar=False,
            )  # fmt: skip
        err = np.abs(det.pc.reshape(-1, 3) - sm.detector.pc.reshape(-1, 3)).max()
        right = out.variant == truth
        acc = [right[truth == k].mean() for k in KINDS]
        print(
            f"{name:<16s} {err:10.2e} {acc[0]:6.1%} {acc[1]:7.1%} {acc[2]:6.1%} "
            f"{out.cross_variant_margin.mean():7.3f} {out.confidence.mean():10.3f}"
        )
    print(f"(calibration {t_cal:.0f} s; standard errors {res.standard_errors})")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment", choices=["picks", "detectors"])
    p.add_argument("--rows", type=int, default=9)
    p.add_argument("--size", type=int, default=120)
    p.add_argument("--doses", type=float, nargs="+", default=[10, 30, 100, 300, 1000])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mismatch", action="store_true", help="reindex with the ebsdsim pattern")
    p.add_argument("--methods", nargs="+", default=["geomdic", "kikuchipy"])
    p.add_argument("--offset", type=float, default=0.02, help="detectors: PC offset")
    args = p.parse_args(argv)
    if args.experiment == "detectors" and len(args.doses) > 1:
        args.doses = [100.0]
    print(f"command: {' '.join(sys.argv)}")
    {"picks": picks, "detectors": detectors}[args.experiment](args)


if __name__ == "__main__":
    main()
