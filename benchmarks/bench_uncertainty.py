"""Benchmark: are the standard errors the errors' size? Coverage and width
of the calibration's PC standard errors over many realistic maps.

For each map: the PC errors over their standard errors (z), and each
standard error over the Cramer-Rao bound of the same processed patterns
(``bound.cramer_rao_bound``, the data's own master pattern at the true
geometry). Per kind of map: the RMS of z (about 1 when the standard errors
are the errors' size), the fraction within 1 and 2 standard errors (68 and
95 % if so), the largest |z| (3 at most), sigma over the bound (median and
range) and the grains per map. Maps:

- ``realistic-<case>``: ``bench_realistic.py``'s 11 x 11 Ni maps of 96 px
  (cases ``moderate``, ``real-noise``, ``emsoft-data``, ``ebsdsim-data``,
  ``far``; ``model-family`` is the best case);
- ``poly-<cell>``: ``bench_envelope.py``'s polycrystal cells (10 x 10
  points, 120 px, EMsoft data calibrated with ebsdsim's);
- ``single-<cell>``, ``domains-<cell>``: its single Ni crystals and BaTiO3
  domain maps, the crystal model (the bound is the free orientations':
  for the PC one crystal's shared rotation is no tie, its bound within
  0.1 % of theirs on a Si crystal at the default scatter prior);
- ``--grain-points P`` makes every map's grains P points on average
  (default 16: 6-7 grains a map; 5 gives 20-24).

Usage::

    python benchmarks/bench_uncertainty.py --maps realistic-moderate realistic-emsoft-data \
        --seeds 0 1 2 3 4
    python benchmarks/bench_uncertainty.py --maps poly-base poly-px-60 --seeds 0 1 2 3 4
    python benchmarks/bench_uncertainty.py --maps single-base domains-base --seeds 0 1 2 3 4
    python benchmarks/bench_uncertainty.py --maps realistic-moderate --grain-points 5 --seeds 0 1
    python benchmarks/bench_uncertainty.py --from-json results/uncertainty/FILE.jsonl
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
import warnings

import numpy as np
from _tee import start_log
from bench_envelope import CELLS, PARAMETERS, envelope_map  # run from benchmarks/
from bench_realistic import CASES, realistic_map

from kikuchipy_geomdic import refine_geometry_dic
from kikuchipy_geomdic.calibration.bound import cramer_rao_bound
from kikuchipy_geomdic.indexing.variants import variant_operators
from kikuchipy_geomdic.validation import orientations

PC = ("pcx", "pcy", "pcz")
#: The maps run without --maps: polycrystals
DEFAULT = ("realistic", "poly")
MAPS = [f"realistic-{c}" for c in CASES] + [
    f"{kind}-{c}" for kind in ("poly", "single", "domains") for c in CELLS
]


def make_map(name: str, seed: int):
    family, _, which = name.partition("-")
    if family == "realistic":
        return realistic_map(which, seed)
    return envelope_map(family, which, seed)


def _options(name: str) -> dict:
    """Each family's own options: bench_realistic's defaults, the
    envelope's five parameters (one crystal: the crystal model)."""
    family = name.partition("-")[0]
    if family == "realistic":
        return {}
    if family == "poly":
        return dict(parameters=PARAMETERS)
    ops = variant_operators()[1:] if family == "domains" else None
    # As bench_envelope.py: the default 100 points
    return dict(
        parameters=PARAMETERS, orientation_model="crystal", pseudo_symmetry_ops=ops, points=100
    )


def run(name: str, seed: int) -> dict:
    sm = make_map(name, seed)
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kw = {"points": sm.xmap.size, **_options(name)}
        res = refine_geometry_dic(*sm.start_inputs, show_progressbar=False, **kw)
    seconds = time.perf_counter() - t0
    crb = cramer_rao_bound(
        sm.signal, sm.xmap, sm.geometry, sm.simulator, sm.energy, points=res.points
    )
    truth = sm.geometry.as_dict()
    # Without a grain property every point has its own random orientation
    grains = len(np.unique(sm.xmap.prop.get("grain", np.arange(sm.xmap.size))))
    if "orientation_model" in kw:
        grains = 1
    sys_part = res.adequacy.get("systematic", {}) or {}
    return dict(
        map=name,
        seed=seed,
        grains=int(grains),
        seconds=seconds,
        err={k: float(res.parameters[k] - truth[k]) for k in PC},
        se={k: float(res.standard_errors[k]) for k in PC},
        systematic={k: float(sys_part.get(k, 0.0)) for k in PC},
        bound={k: float(crb.sigma[k]) for k in PC},
        consistent=bool(res.adequacy.get("consistent", True)),
        # The DIC stage's step from the full field's solution (a shared
        # misfit moves the two apart)
        dic_step={k: float(v) for k, v in res.adequacy.get("dic_step", {}).items() if k in PC},
        dic_z={k: float(v) for k, v in res.adequacy.get("z", {}).items() if k in PC},
        converged=bool(res.converged),
    )


def row(r: dict) -> str:
    z = " ".join(f"{r['err'][k] / r['se'][k]:+5.1f}" for k in PC)
    ratio = " ".join(f"{r['se'][k] / r['bound'][k]:4.1f}" for k in PC)
    err = " ".join(f"{r['err'][k]:+.1e}" for k in PC)
    return (
        f"{r['map']:<26s} {r['seed']:2d} grains {r['grains']:3d} | err {err} | z {z} | "
        f"se/bound {ratio} | {'' if r['consistent'] else 'inflated '}{r['seconds']:4.1f} s"
    )


def summary(rows: list[dict], label: str) -> str:
    z = np.array([[r["err"][k] / r["se"][k] for k in PC] for r in rows]).ravel()
    ratio = np.array([[r["se"][k] / r["bound"][k] for k in PC] for r in rows]).ravel()
    grains = sorted({r["grains"] for r in rows})
    return (
        f"{label:<28s} {len(rows):3d} maps  grains {grains[0]}-{grains[-1]}  "
        f"RMS z {np.sqrt(np.mean(z**2)):.2f}  within 1 {np.mean(np.abs(z) <= 1):4.0%}  "
        f"within 2 {np.mean(np.abs(z) <= 2):4.0%}  largest {np.abs(z).max():.2f}  "
        f"se/bound median {np.median(ratio):.2f} ({ratio.min():.2f}-{ratio.max():.2f})"
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--maps", nargs="+", choices=MAPS, default=[m for m in MAPS if m.startswith(DEFAULT)]
    )
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--grain-points", type=int, default=orientations.GRAIN_POINTS)
    ap.add_argument("--json", help="append each map's figures to this file (JSON lines)")
    ap.add_argument("--from-json", help="print the rows and summary of such a file instead")
    args = ap.parse_args(argv)
    if args.from_json:
        with open(args.from_json) as f:
            rows = [json.loads(line) for line in f]
        print(f"command: {' '.join(sys.argv)}")
        print("\n".join(map(row, rows)) + "\n")
        for name in dict.fromkeys(r["map"] for r in rows):
            print(summary([r for r in rows if r["map"] == name], name))
        print(summary(rows, "all"))
        return
    orientations.GRAIN_POINTS = args.grain_points
    start_log()
    rows = []
    for name in args.maps:
        for seed in args.seeds:
            r = run(name, seed)
            rows.append(r)
            print(row(r), flush=True)
            if args.json:
                with open(args.json, "a") as f:
                    f.write(json.dumps(r) + "\n")
    print()
    for name in args.maps:
        print(summary([r for r in rows if r["map"] == name], name))
    print(summary(rows, "all"))


if __name__ == "__main__":
    main()
