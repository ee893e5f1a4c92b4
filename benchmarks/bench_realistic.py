"""Benchmark: the calibration on maps made as a microscope and a user make them.

Polycrystalline Ni maps of 11 x 11 points (121 calibration points, all of
them) of 96 px patterns recorded by ``Camera`` (background lobe
at the PC, per-grain brightness, 0.6 px phosphor blur, Poisson counts in
uint16, kikuchipy's static and dynamic background removal), the start
geometry ``synthetic.DEFAULT_PERTURBATION`` (2 % of the width) off with
orientations indexed by kikuchipy at it (``start="indexed"``). Each map is
calibrated with the defaults, with the DIC stage alone
(``full_field=False``) and, with ``--kikuchipy``, by kikuchipy's
pattern-wise Nelder-Mead with the PCs averaged
(``comparison.pattern_wise_geometry``). The bound is that of the same
processed patterns at the true geometry and orientations, with the
master pattern the data were simulated from (``bound.cramer_rao_bound``).
Cases:

- ``moderate``: 150 counts/px, data and calibration EMsoft Ni;
- ``real-noise``: 30 counts/px (kikuchipy's real Ni patterns);
- ``emsoft-data``: 150 counts/px, data from EMsoft, calibrated with the
  ebsdsim Ni master pattern (another simulator);
- ``ebsdsim-data``: the other way round;
- ``far``: as ``moderate`` with the start twice as far off (4 %);
- ``model-family``: ``a * blur(S) + b`` plus Poisson noise at 150
  counts/px (``degrade_patterns``), the full field's own model:
  a labelled best case, not evidence.

Printed per case and method: time, the largest error of the PC (pcx,
pcy, pcz at the map centre, the parameters with standard errors) and the
largest over the map's PC field (which adds the angles' errors), each
PC parameter's error over its standard error, each standard error over
the bound, the angles' errors with their standard errors (``held`` when
reported undetermined) and the calibration's adequacy verdict.

Usage::

    python benchmarks/bench_realistic.py                 # all cases, seed 0
    python benchmarks/bench_realistic.py --cases moderate far --seeds 0 1 2
    python benchmarks/bench_realistic.py --cases emsoft-data --seeds 2 3 4 --dose 10000
"""

from __future__ import annotations

import argparse
import time
import warnings
from dataclasses import replace

import numpy as np
from _tee import start_log  # run from benchmarks/

from kikuchipy_geomdic.calibration.bound import cramer_rao_bound
from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.camera import MODERATE, REAL_NI

CASES = {
    "moderate": dict(camera=MODERATE),
    "real-noise": dict(camera=REAL_NI),
    "emsoft-data": dict(camera=MODERATE, calibrate="ebsdsim"),
    "ebsdsim-data": dict(camera=MODERATE, data="ebsdsim"),
    "far": dict(camera=MODERATE, far=True),
    "model-family": dict(camera=None),
}
PC = ("pcx", "pcy", "pcz")
ANGLES = ("azimuthal", "tilt-sample_tilt")


def realistic_map(case: str, seed: int, side: int = 11, size: int = 96, dose=None):
    """The synthetic map of *case* (see the module docstring), its camera's
    counts per pixel replaced by *dose* if given."""
    cfg = dict(CASES[case])
    if dose is not None and cfg["camera"] is not None:
        cfg["camera"] = replace(cfg["camera"], dose=dose)
    data = master_patterns.master_pattern("Ni", kind=cfg.get("data", "emsoft"))
    calibrate = master_patterns.master_pattern(
        "Ni", kind=cfg.get("calibrate", cfg.get("data", "emsoft"))
    )
    perturbation = synthetic.DEFAULT_PERTURBATION
    if cfg.get("far"):
        perturbation = {k: 2 * v for k, v in perturbation.items()}
    noise = dict(camera=cfg["camera"]) if cfg["camera"] else dict(dose=150, blur=0.6)
    return synthetic.synthetic_map(
        calibrate, (side, side), shape=(size, size), seed=seed, orientation_error=1.0,
        start="indexed", simulator=data, perturbation=perturbation, **noise,
    )  # fmt: skip


def _errors(sm, parameters, detector):
    """Errors of the parameters, and the largest PC error over the map."""
    truth = sm.geometry.as_dict()
    err = {k: parameters[k] - truth[k] for k in (*PC, "azimuthal")}
    err["tilt-sample_tilt"] = (parameters["tilt"] - parameters["sample_tilt"]) - (
        truth["tilt"] - truth["sample_tilt"]
    )
    return err, float(np.abs(detector.pc - sm.detector.pc).max())


def run(case: str, seed: int, side: int, size: int, kikuchipy: bool, dose=None) -> list[dict]:
    sm = realistic_map(case, seed, side, size, dose)
    methods = [("default", {}), ("DIC alone", dict(full_field=False))]
    rows, crb = [], None
    for method, kw in methods:
        t0 = time.perf_counter()
        res = refine_geometry_dic(
            *sm.start_inputs, points=side * side, show_progressbar=False, **kw
        )
        sec = time.perf_counter() - t0
        if crb is None:
            crb = cramer_rao_bound(
                sm.signal, sm.xmap, sm.geometry, sm.simulator, sm.energy, points=res.points
            )
        err, max_pc = _errors(sm, res.parameters, res.detector)
        se = res.standard_errors
        rows.append(
            dict(
                method=method, time=sec, max_pc=max_pc, err=err, se=se,
                z={k: err[k] / se[k] for k in err},
                ratio={k: se[k] / crb.sigma[k] for k in PC},
                held=[a for a in ANGLES if a in res.undetermined
                      or (a == "tilt-sample_tilt" and "tilt" in res.undetermined)],
                verdict="" if res.adequacy.get("consistent", True) else "inflated",
            )
        )  # fmt: skip
    if kikuchipy:
        from kikuchipy_geomdic.validation.comparison import pattern_wise_geometry

        t0 = time.perf_counter()
        pw = pattern_wise_geometry(sm, res.points)
        sec = time.perf_counter() - t0
        err, max_pc = _errors(sm, pw.geometry.as_dict(), pw.geometry.detector())
        rows.append(dict(method="kikuchipy NM", time=sec, max_pc=max_pc, err=err, se=None))
    return rows


def _fmt(r) -> str:
    if r["se"] is None:
        return ""
    z = ",".join(f"{r['z'][k]:+.1f}" for k in PC)
    ratio = ",".join(f"{r['ratio'][k]:.2f}" for k in PC)
    angles = []
    for a in ANGLES:
        held = " held" if a in r["held"] else ""
        angles.append(f"{r['err'][a]:+6.3f} ({r['se'][a]:.3f}{held})")
    return f"{z:>19s} {ratio:>16s} " + " ".join(angles) + f" {r['verdict']}"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--side", type=int, default=11)
    p.add_argument("--size", type=int, default=96)
    p.add_argument("--kikuchipy", action="store_true", help="also kikuchipy's NM, averaged")
    p.add_argument(
        "--dose", type=float, help="the camera's counts per pixel instead of the case's"
    )
    args = p.parse_args(argv)
    start_log()
    print(
        f"{'case':<13s} {'seed':>4s} {'method':<12s} {'time s':>6s} {'PC err':>10s} "
        f"{'field max':>10s} "
        f"{'err/se pcx,pcy,pcz':>19s} {'se/bound':>16s} {'azimuthal err (se)':>18s} "
        f"{'tilt diff. err (se)':>19s}"
    )
    for case in args.cases:
        for seed in args.seeds:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rows = run(case, seed, args.side, args.size, args.kikuchipy, args.dose)
            for r in rows:
                print(
                    f"{case:<13s} {seed:4d} {r['method']:<12s} {r['time']:6.1f} "
                    f"{max(abs(r['err'][k]) for k in PC):10.2e} {r['max_pc']:10.2e} {_fmt(r)}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
