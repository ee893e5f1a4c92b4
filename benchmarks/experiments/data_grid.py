"""Instrument check (not the package's behaviour): how much of the BaTiO3
domain maps' PC error is the *data's* master pattern grid.

``bench_crystal.py --case bto`` simulates its data from ebsdsim's 201 x 201
master pattern and calibrates with de-ebsd's 801 x 801 one. Here the data
come from de-ebsd's own pattern, every *step*-th grid point kept (step 4:
201 x 201, step 2: 401 x 401), optionally interpolated back to 801 x 801
by a cubic spline (``--spline``): the same physics as the calibration's
master pattern, only the grid differs.

Usage::

    python benchmarks/experiments/data_grid.py --step 4 --seeds 0 1
    python benchmarks/experiments/data_grid.py --step 2 --seeds 0
    python benchmarks/experiments/data_grid.py --step 4 --spline --seeds 0
    python benchmarks/experiments/data_grid.py --step 2 --envelope --kinds domains --seeds 0

With ``--envelope``, the rest of the command line goes to
``bench_envelope.py``, whose domain maps then take their data from the
coarsened de-ebsd pattern.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from kikuchipy.signals import EBSDMasterPattern
from scipy.ndimage import map_coordinates

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import bench_crystal as bc  # noqa: E402

from kikuchipy_geomdic import refine_geometry_dic  # noqa: E402


def _coarse(full: EBSDMasterPattern, step: int, spline: bool) -> EBSDMasterPattern:
    d = full.data[:, ::step, ::step].astype(np.float32)
    if spline:
        m = full.data.shape[-1]
        c = np.linspace(0, d.shape[-1] - 1, m)
        yy, xx = np.meshgrid(c, c, indexing="ij")
        d = np.stack([map_coordinates(h, [yy, xx], order=3, mode="nearest") for h in d])
    n = d.shape[-1]
    axes = [
        {"size": 2, "name": "hemisphere", "scale": 1, "offset": 0, "units": ""},
        {"size": n, "name": "height", "scale": 1, "offset": -(n // 2), "units": "px"},
        {"size": n, "name": "width", "scale": 1, "offset": -(n // 2), "units": "px"},
    ]
    return EBSDMasterPattern(
        d.astype(np.float32), axes=axes, projection="lambert", hemisphere="both",
        phase=full.phase.deepcopy(),
    )  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--step", type=int, default=4)
    ap.add_argument("--spline", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--model", default="crystal")
    ap.add_argument("--envelope", nargs=argparse.REMAINDER, help="bench_envelope.py's arguments")
    args = ap.parse_args(argv)
    own = bc.master_patterns.master_pattern

    def data_pattern(phase, kind=None, **kw):
        if phase == "BaTiO3" and kind == "ebsdsim":
            return _coarse(own("BaTiO3", kind="dynamical"), args.step, args.spline)
        return own(phase, kind=kind, **kw)

    bc.master_patterns.master_pattern = data_pattern
    if args.envelope is not None:
        import bench_envelope

        bench_envelope.main(args.envelope)
        return
    grid = f"step {args.step}{' + spline' if args.spline else ''}"
    for seed in args.seeds:
        with bc._quiet():
            sm = bc._map("bto", seed, 200.0, "users")
        t0 = time.perf_counter()
        with bc._quiet() as caught:
            res = refine_geometry_dic(
                sm.signal, sm.start_xmap, sm.start_detector, sm.master_pattern, sm.energy,
                parameters=["pcx", "pcy", "pcz", "tilt", "azimuthal"],
                pseudo_symmetry_ops=bc.variant_operators()[1:], orientation_model=args.model,
                show_progressbar=False,
            )  # fmt: skip
        row = bc._row("bto", seed, args.model, sm, res, time.perf_counter() - t0, caught)
        print(f"grid {grid}: {row.splitlines()[0][:170]}", flush=True)


if __name__ == "__main__":
    main()
