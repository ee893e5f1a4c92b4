"""Benchmark: the calibration against the Cramer-Rao bound of its data.

Polycrystalline Ni maps of 11 x 11 points (121 calibration points, all
of them) of 96 px patterns simulated from kikuchipy's EMsoft Ni master
pattern with a detector blur of 0.6 px and Poisson noise, the start
geometry ``synthetic.DEFAULT_PERTURBATION`` (2 % of the width) off with
orientations indexed by kikuchipy at it (``start="indexed"``). Each map is
calibrated twice, with the defaults (DIC stage, then the full field) and
with ``full_field=False`` (DIC alone); the bound is that of the same
patterns at the true geometry and orientations
(``bound.cramer_rao_bound``, each rotation free). Cases:

- ``moderate``: dose 150 counts/px, calibrated with the EMsoft master
  pattern (the data's own simulator);
- ``real-noise``: dose 30 (as noisy as the real Ni patterns of
  ``kikuchipy.data.nickel_ebsd_small``, see ``bench_noise.py``);
- ``mismatch``: dose 150, calibrated with the ebsdsim Ni master pattern
  (another simulator: its intensities differ, its band positions agree).

Printed per case and method: time, the largest PC error on the map, each
PC parameter's error over its standard error, each standard error over
the bound, and the angles' errors with their standard errors.

Usage::

    python benchmarks/bench_fullfield.py                 # all three cases
    python benchmarks/bench_fullfield.py --cases moderate --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np

from kikuchipy_geomdic import synthetic
from kikuchipy_geomdic.bound import cramer_rao_bound
from kikuchipy_geomdic.refinement import refine_geometry_dic

CASES = {
    "moderate": dict(dose=150, calibrate_with="emsoft"),
    "real-noise": dict(dose=30, calibrate_with="emsoft"),
    "mismatch": dict(dose=150, calibrate_with="ebsdsim"),
}
PC = ("pcx", "pcy", "pcz")


def run(case: str, seed: int, side: int, size: int) -> list[dict]:
    cfg = CASES[case]
    emsoft = synthetic.master_pattern("Ni", kind="emsoft")
    sm = synthetic.synthetic_map(
        emsoft, (side, side), shape=(size, size), seed=seed, dose=cfg["dose"], blur=0.6,
        orientation_error=1.0, start="indexed",
    )  # fmt: skip
    mp = emsoft if cfg["calibrate_with"] == "emsoft" else synthetic.master_pattern("Ni")
    rows = []
    crb = None
    for method, kw in (("DIC + full field", {}), ("DIC alone", dict(full_field=False))):
        t0 = time.perf_counter()
        res = refine_geometry_dic(
            *sm.start_inputs[:3], mp, sm.energy, points=side * side, show_progressbar=False, **kw
        )
        sec = time.perf_counter() - t0
        if crb is None:
            crb = cramer_rao_bound(
                sm.signal, sm.xmap, sm.geometry, emsoft, sm.energy, points=res.points
            )
        truth, got, se = sm.geometry.as_dict(), res.parameters, res.standard_errors
        err = {k: got[k] - truth[k] for k in (*PC, "azimuthal")}
        err["tilt-sample_tilt"] = (got["tilt"] - got["sample_tilt"]) - (
            truth["tilt"] - truth["sample_tilt"]
        )
        rows.append(
            dict(
                case=case, seed=seed, method=method, time=sec,
                max_pc=float(np.abs(res.detector.pc - sm.detector.pc).max()),
                z={k: err[k] / se[k] for k in err},
                ratio={k: se[k] / crb.sigma[k] for k in PC},
                err=err, se=se,
            )
        )  # fmt: skip
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--side", type=int, default=11)
    p.add_argument("--size", type=int, default=96)
    args = p.parse_args(argv)
    print(f"command: {' '.join(sys.argv)}")
    print(
        f"{'case':<11s} {'seed':>4s} {'method':<17s} {'time s':>6s} {'max PC err':>10s} "
        f"{'err/se pcx,pcy,pcz':>19s} {'se/bound':>16s} {'azim. err (se)':>15s} "
        f"{'tilt diff. err (se)':>19s}"
    )
    for case in args.cases:
        for seed in args.seeds:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rows = run(case, seed, args.side, args.size)
            for r in rows:
                z = ",".join(f"{r['z'][k]:+.1f}" for k in PC)
                ratio = ",".join(f"{r['ratio'][k]:.2f}" for k in PC)
                az, td = "azimuthal", "tilt-sample_tilt"
                print(
                    f"{case:<11s} {seed:4d} {r['method']:<17s} {r['time']:6.1f} "
                    f"{r['max_pc']:10.2e} {z:>19s} {ratio:>16s} "
                    f"{r['err'][az]:+6.3f} ({r['se'][az]:.3f}) "
                    f"{r['err'][td]:+9.3f} ({r['se'][td]:.3f})",
                    flush=True,
                )


if __name__ == "__main__":
    main()
