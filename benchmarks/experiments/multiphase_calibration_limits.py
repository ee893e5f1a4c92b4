"""Experiment (issue 55, item 1): what limits the joint calibration's PC on
the two-phase maps of ``bench_multiphase.py``.

Each map (``two_phase_map``, the benchmark's defaults) is calibrated with
``refine_geometry_dic`` in several ways, everything else the benchmark's:

- ``joint N``: every phase's points in one solve, *N* points (the
  benchmark's 100, or every point of the map);
- ``major N``: the majority label's points only (``phase=`` that label),
  *N* of them (100 as the benchmark's joint call, or all of that label).

Printed per map and way: the PC errors at the map's reference point,
their standard errors, the largest z, the standard errors' systematic
part (``adequacy["systematic"]``), the points per phase and the time.

Usage::

    python benchmarks/experiments/multiphase_calibration_limits.py --seeds 0 1 2 3 4
    python benchmarks/experiments/multiphase_calibration_limits.py --size 96 --side 15
    python benchmarks/experiments/multiphase_calibration_limits.py --calibrate de-ebsd
    python benchmarks/experiments/multiphase_calibration_limits.py --ways joint:100 --psf 0.6

``--psf`` forces the full field's point spread (px) to the camera's
instead of the one it estimates (printed beside each row). Each row ends
with the PC's standard errors over the Cramer-Rao bound of the points
used (the data's own master patterns at the truth).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from kikuchipy_geomdic.calibration import _full_field
from kikuchipy_geomdic.calibration.bound import cramer_rao_bound
from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
from kikuchipy_geomdic.validation.camera import MODERATE
from kikuchipy_geomdic.validation.multiphase import PAIRS, two_phase_map

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _tee import start_log  # noqa: E402

PC = ("pcx", "pcy", "pcz")
_ESTIMATED = {}


def _forced_psf(psf):
    """The full field's processing estimate, its point spread replaced by
    *psf* (None: as estimated); the estimate is kept in _ESTIMATED."""
    estimate = _full_field._estimate_processing

    def forced(*args, **kwargs):
        proc = estimate(*args, **kwargs)
        _ESTIMATED["psf"] = proc.psf
        return proc if psf is None else replace(proc, psf=psf)

    _full_field._estimate_processing = forced


def calibrations(tp, ways):
    label = tp.start_xmap.phase_id
    major = int(np.bincount(label[label >= 0], minlength=2).argmax())
    mps = [tp.master_patterns[n] for n in tp.phase_names]
    truth = tp.geometry.as_dict()
    for way in ways:
        kind, n = way.split(":")
        n_all = label.size if kind == "joint" else int((label == major).sum())
        points = n_all if n == "all" else int(n)
        if kind == "joint":
            args = dict(master_pattern=mps)
        else:
            name = tp.phase_names[major]
            args = dict(master_pattern=tp.master_patterns[name], phase=name)
        t = time.process_time()
        res = refine_geometry_dic(
            tp.signal, tp.start_xmap, tp.start_detector, args.pop("master_pattern"),
            tp.energy, points=points, show_progressbar=False, **args,
        )  # fmt: skip
        t = time.process_time() - t
        err = np.array([res.parameters[k] - truth[k] for k in PC])
        se = np.array([res.standard_errors[k] for k in PC])
        sys_ = res.adequacy.get("systematic", {}) or {}
        syst = np.array([sys_.get(k, np.nan) for k in PC])
        crb = cramer_rao_bound(
            tp.signal, tp.xmap, tp.geometry, [tp.simulators[n] for n in tp.phase_names],
            tp.energy, points=res.points,
        )  # fmt: skip
        bound = np.array([crb.sigma[k] for k in PC])
        yield dict(way=f"{kind} {n}", err=err, se=se, sys=syst, t=t, bound=bound,
                   ppp=res.points_per_phase, conv=res.converged)  # fmt: skip


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--pair", default="ferrite+austenite", choices=list(PAIRS))
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--side", type=int, default=15)
    p.add_argument("--size", type=int, default=80)
    p.add_argument("--dose", type=float, default=150.0)
    p.add_argument("--calibrate", default="dynamical", help="master patterns to calibrate with")
    p.add_argument(
        "--ways", nargs="+", default=["joint:100", "major:100", "joint:all", "major:all"]
    )
    p.add_argument("--psf", type=float, help="the full field's point spread forced (px)")
    p.add_argument("--log", type=Path)
    args = p.parse_args(argv)
    start_log(args.log)
    _forced_psf(args.psf)
    print(f"{'seed':>4s} {'way':<10s} {'PC err (pcx pcy pcz)':<26s} {'se':<24s} {'max z':>5s} "
          f"{'systematic part of se':<24s} {'CPU s':>6s}  points per phase")  # fmt: skip
    for seed in args.seeds:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tp = two_phase_map(PAIRS[args.pair], (args.side, args.side), (args.size, args.size),
                               camera=replace(MODERATE, dose=args.dose), seed=seed,
                               calibrate=args.calibrate)  # fmt: skip
            for r in calibrations(tp, args.ways):
                z = np.max(np.abs(r["err"]) / r["se"])
                print(
                    f"{seed:4d} {r['way']:<10s} " + " ".join(f"{e:+.1e}" for e in r["err"])
                    + "   " + " ".join(f"{s:.1e}" for s in r["se"]) + f" {z:5.1f}  "
                    + " ".join(f"{s:.1e}" for s in r["sys"])
                    + f" {r['t']:6.1f}  {r['ppp']}" + ("" if r["conv"] else " NOT CONVERGED")
                    + f"  point spread estimated {_ESTIMATED.get('psf', np.nan):.2f}"
                    + "  se/bound " + " ".join(f"{s:.1f}" for s in r["se"] / r["bound"]),
                    flush=True,
                )  # fmt: skip


if __name__ == "__main__":
    main()
