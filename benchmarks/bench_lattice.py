"""Benchmark: a crystal whose lattice is not its CIF's. BaTiO3 domain maps
of the envelope (``bench_envelope.py``'s ``domains`` kind: ebsdsim data,
de-ebsd's master pattern calibrated with, users' starts) whose data come
from a crystal with the c axis ``--stretches`` times the CIF's
(:func:`~kikuchipy_geomdic.validation.master_patterns.stretched`; 0.989 is
about a cubic CIF's c/a against BaTiO3's 1.011), each calibrated with the
lattice held at the CIF's (``lattice_tolerance=0``) and fitted (the
default tolerance). ``--kind single``: one BaTiO3 crystal of one variant
(the envelope's ``bto-single`` kind, the domain maps' simulators and
processing), its c axis in one direction only. ``--kind poly``: a BaTiO3
polycrystal instead, 11 x 11
points of random orientations, 96 px, 150 counts/px, static and dynamic
background removed, the free orientation model (as ``bench_realistic.py``'s
maps, the same simulator pair as the domain maps): how far a lattice
error moves a polycrystal's PC (the calibration holds the lattice there;
`results/lattice/poly_67df582.log` shows it fitted, before it was held).

Printed per map and tolerance: the PC errors, their standard errors, the
largest |error| / standard error, the fitted c/a stretch with its standard
error against the data's, how many of the calibration points have the
right c axis (a 90 deg variant wrong is a point wrongly indexed), whether
the calibration says it converged (a fitted c/a near cubic is marked not
converged: the variants alike), time.

Usage::

    python benchmarks/bench_lattice.py --stretches 0.994 1.0 1.006 --seeds 0 1 2
    python benchmarks/bench_lattice.py --cells base fov-2000 --stretches 0.996 --seeds 0
    python benchmarks/bench_lattice.py --kind poly --stretches 0.994 1.0 1.006 --seeds 0 1
    python benchmarks/bench_lattice.py --kind single --stretches 0.994 1.004 --seeds 0 1 2
    python benchmarks/bench_lattice.py --stretches 0.994 --seeds 0 1 --reindex
"""

from __future__ import annotations

import argparse
import contextlib
import io
import time
import warnings

import numpy as np
from _tee import start_log
from bench_envelope import CELLS, PARAMETERS, _reindex_row, envelope_map  # run from benchmarks/

from kikuchipy_geomdic import refine_geometry_dic
from kikuchipy_geomdic.calibration.refinement import LATTICE_TOLERANCE
from kikuchipy_geomdic.indexing.variants import domain_labels, variant_operators
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.camera import MODERATE

PC = ("pcx", "pcy", "pcz")


def poly_map(seed: int, stretch: float) -> synthetic.SyntheticMap:
    """A BaTiO3 polycrystal (see the module docstring)."""
    data = master_patterns.master_pattern("BaTiO3", kind="ebsdsim")
    return synthetic.synthetic_map(
        master_patterns.master_pattern("BaTiO3", kind="dynamical"), (11, 11), shape=(96, 96),
        seed=seed, orientation_error=1.0, start="indexed", camera=MODERATE,
        simulator=master_patterns.stretched(data, stretch) if stretch != 1 else data,
    )  # fmt: skip


def run(
    cell: str, seed: int, stretch: float, tolerance: float, kind: str = "domains", again=False
) -> str:
    poly = kind == "poly"
    crystal = "bto-single" if kind == "single" else "domains"
    sm = poly_map(seed, stretch) if poly else envelope_map(crystal, cell, seed, stretch=stretch)
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = refine_geometry_dic(
            sm.signal, sm.start_xmap, sm.start_detector, sm.master_pattern, sm.energy,
            parameters=PARAMETERS, pseudo_symmetry_ops=None if poly else variant_operators()[1:],
            lattice_tolerance=tolerance, show_progressbar=False,
            points=sm.xmap.size if poly else 100,  # as bench_realistic.py, bench_envelope.py
        )  # fmt: skip
    seconds = time.perf_counter() - t0
    truth = sm.geometry.as_dict()
    err = {k: res.parameters[k] - truth[k] for k in PC}
    se = res.standard_errors
    z = max(abs(err[k]) / se[k] for k in PC)
    c_right = np.nan
    if not poly:
        labels = domain_labels(sm.xmap)
        pts = np.asarray(res.points)
        true_label = labels.label.reshape(sm.xmap.shape)[pts[:, 0], pts[:, 1]]
        got = domain_labels(res.xmap, parent=labels.parent).label
        c_right = float(np.mean(got // 2 == true_label // 2))
    lat = res.lattice
    fit = (
        f"{lat['stretch']:+.2%} +- {lat['stretch_se']:.2%} "
        f"(z {(lat['stretch'] - (stretch - 1)) / lat['stretch_se']:+5.1f}"
        f"{'' if lat['determined'] else ', not determined'})"
        if lat
        else "held"
    )
    label = "poly" if poly else cell if kind == "domains" else f"single-{cell}"
    after = ""
    if again and not poly:
        # The map reindexed from users' starts at the calibrated detector
        # (with the CIF's master pattern, as a user has it)
        after = "\n  " + _reindex_row(
            label, sm, sm.start_xmap, res.detector, variant_operators()[1:]
        )
    return (
        f"{label:<9} {seed:2d} data {stretch - 1:+.1%} tol {tolerance:<5g} | PC err "
        + " ".join(f"{err[k]:+.1e}" for k in PC)
        + " | se "
        + " ".join(f"{se[k]:.1e}" for k in PC)
        + f" | max z {z:4.1f} | c/a stretch {fit:<34s} | c axis right {c_right:4.0%} "
        f"| conv {res.converged!s:5} | {seconds:3.0f} s" + after
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kind", default="domains", choices=["domains", "single", "poly"])
    ap.add_argument("--cells", nargs="+", default=["base"], choices=list(CELLS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--stretches", type=float, nargs="+", default=[0.994, 1.0, 1.006])
    ap.add_argument("--tolerances", type=float, nargs="+", default=[0.0, LATTICE_TOLERANCE])
    ap.add_argument("--reindex", action="store_true", help="reindex each domain map after")
    args = ap.parse_args(argv)
    start_log()
    for cell in args.cells:
        for stretch in args.stretches:
            for seed in args.seeds:
                for tol in args.tolerances:
                    print(run(cell, seed, stretch, tol, args.kind, args.reindex), flush=True)


if __name__ == "__main__":
    main()
