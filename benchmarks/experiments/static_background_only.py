"""Experiment (not the package's behaviour): calibrate the default stripe
maps of ``bench_variants.py users`` (one crystal, the map's mean divided
out) on their stored static background alone, then reindex the map there.

Usage::

    python benchmarks/experiments/static_background_only.py --seeds 0 1 2 3 4 5 --dose 30

The stored background (the map's mean, 169 patterns' counts) with its
dynamic background removed becomes a 1 x 1 signal; its orientation is the
users' start orientation whose simulation correlates best with it, its
PC the map's mean start PC. ``refine_geometry_dic`` refines the PC there
(the angles cannot be told from a rotation of one pattern), the map's
detector is moved by the change, and the map reindexed with the
operators. Printed: the PC error and its standard errors, the largest PC
error over the map, and the reindex's scores as ``bench_variants.py
users`` prints them.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import kikuchipy as kp
import numpy as np
from orix.crystal_map import CrystalMap

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import bench_variants as bv  # noqa: E402

from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic  # noqa: E402
from kikuchipy_geomdic.geometry import copy_detector  # noqa: E402
from kikuchipy_geomdic.indexing import orientation as ori  # noqa: E402
from kikuchipy_geomdic.indexing.variants import variant_operators  # noqa: E402
from kikuchipy_geomdic.patterns.simulation import simulate_patterns  # noqa: E402
from kikuchipy_geomdic.validation import synthetic  # noqa: E402
from kikuchipy_geomdic.validation.camera import Camera  # noqa: E402


def run(seed: int, dose: float) -> None:
    ops = variant_operators()[1:]
    with bv._quiet():
        sm = synthetic.synthetic_map(
            "BaTiO3", (13, 13), orientations="stripes", shape=(120, 120), seed=seed,
            camera=Camera(dose=dose), start="indexed", orientation_error=1.0,
        )  # fmt: skip
    bg = np.asarray(sm.signal.static_background, dtype=np.float32)
    one = kp.signals.EBSD(bg[None, None].copy())
    one.remove_dynamic_background("divide", show_progressbar=False)
    one.static_background = np.asarray(sm.signal.static_background)
    start_pc = sm.start_detector.pc.reshape(-1, 3).mean(axis=0)
    det = copy_detector(sm.start_detector, pc=start_pc)
    rots = sm.start_xmap.rotations
    sim = simulate_patterns(sm.master_pattern, rots, det, sm.energy).reshape(rots.size, -1)
    e = ori.standardise(np.asarray(one.data, np.float64).reshape(1, -1))
    best = int(np.argmax((ori.standardise(sim.astype(np.float64)) * e).mean(axis=1)))
    xmap = CrystalMap(rots[best : best + 1], phase_list=sm.start_xmap.phases)
    t0 = time.perf_counter()
    with bv._quiet():
        res = refine_geometry_dic(
            one, xmap, det, sm.master_pattern, sm.energy, parameters=["pcx", "pcy", "pcz"],
            show_progressbar=False,
        )  # fmt: skip
    sec = time.perf_counter() - t0
    pc = np.array([res.parameters[k] for k in ("pcx", "pcy", "pcz")])
    se = np.array([res.standard_errors[k] for k in ("pcx", "pcy", "pcz")])
    err = pc - sm.detector.pc.reshape(-1, 3).mean(axis=0)
    moved = copy_detector(sm.start_detector, pc=sm.start_detector.pc + (pc - start_pc))
    print(
        f"dose {dose:g} seed {seed}: PC error {np.array2string(err, precision=6)}, in standard "
        f"errors {np.array2string(err / se, precision=2)} ({sec:.1f} s); largest over the map "
        f"{bv.max_pc_error(moved, sm):.1e}",
        flush=True,
    )
    out, t = bv._reindex(sm, moved, sm.master_pattern, ops)
    scores = bv._users_scores(out, sm, "geomdic")
    print("  " + bv._users_line((dose, seed, "background", *scores, t)))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--dose", type=float, default=30.0)
    args = p.parse_args(argv)
    print("command: benchmarks/experiments/static_background_only.py " + " ".join(sys.argv[1:]))
    for seed in args.seeds:
        run(seed, args.dose)


if __name__ == "__main__":
    main()
