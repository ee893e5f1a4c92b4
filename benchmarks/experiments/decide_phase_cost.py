"""Experiment (issue 55, item 2): the cost of ``reindex(...,
decide_phase=True)`` over K phases against K one-phase reindexes.

On a map of ``bench_multiphase.py`` (15 x 15 points of 80 px, the true
detector as its ``decide @truth`` row), in one process, repeated and
interleaved: ``reindex`` of every point labelled phase k with phase k's
master pattern alone (``one k``), and the decision over both phases, as
the package runs it (its phase calls in parts on dask's threads) and with
the phase calls in one call (``serial calls``, the code before). Printed:
CPU (``time.process_time``, every thread) and wall time of each, medians
over the repeats, and the ratio of each decision to the sum of the
one-phase reindexes (the issue's "K times one phase's reindex").

Usage::

    python benchmarks/experiments/decide_phase_cost.py --pairs ferrite+martensite --repeats 5
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from kikuchipy_geomdic.indexing import _phase_maps
from kikuchipy_geomdic.indexing.reindex import reindex
from kikuchipy_geomdic.validation.multiphase import PAIRS, two_phase_map

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _tee import start_log  # noqa: E402

PARTS = _phase_maps._compare_parts


def _serial(patterns, candidates, pcs, om, arrays):
    """The phase calls in one call, as before the parts."""
    return _phase_maps._compare(patterns, candidates, pcs, om, arrays)


def _timed(fn):
    c, w = time.process_time(), time.perf_counter()
    out = fn()
    return time.process_time() - c, time.perf_counter() - w, out


def run(pair, seed, args):
    tp = two_phase_map(PAIRS[pair], (args.side, args.side), (args.size, args.size), seed=seed)
    mps = [tp.master_patterns[n] for n in tp.phase_names]
    n = tp.start_xmap.size

    def one(k):
        x = _phase_maps._as_phase(tp.start_xmap, k, np.ones(n, bool))
        return reindex(tp.signal, x, tp.detector, mps[k], tp.energy, phase=k,
                       show_progressbar=False)  # fmt: skip

    def decide(serial):
        _phase_maps._compare_parts = _serial if serial else PARTS
        try:
            return reindex(tp.signal, tp.start_xmap, tp.detector, mps, tp.energy,
                           decide_phase=True, show_progressbar=False)  # fmt: skip
        finally:
            _phase_maps._compare_parts = PARTS

    jobs = {
        "one 0": lambda: one(0),
        "one 1": lambda: one(1),
        "decide": lambda: decide(False),
        "decide, serial calls": lambda: decide(True),
    }
    for f in jobs.values():
        f()  # compiled and cached
    times = {k: [] for k in jobs}
    outs = {}
    for _ in range(args.repeats):
        for k, f in jobs.items():
            c, w, outs[k] = _timed(f)
            times[k].append((c, w))
    med = {k: np.median(np.array(v), axis=0) for k, v in times.items()}
    base = med["one 0"] + med["one 1"]
    for k in jobs:
        ratio = med[k] / base
        print(f"{pair:<19s} {seed:4d} {k:<22s} CPU {med[k][0]:6.3f} s  wall {med[k][1]:6.3f} s"
              + (f"   ratio CPU {ratio[0]:.2f}  wall {ratio[1]:.2f}" if "decide" in k else ""),
              flush=True)  # fmt: skip
    same = np.array_equal(outs["decide"].phase_id, outs["decide, serial calls"].phase_id) and (
        np.array_equal(
            outs["decide"].prop["phase_margin"], outs["decide, serial calls"].prop["phase_margin"]
        )  # fmt: skip
    )
    print(f"{pair:<19s} {seed:4d} parts and serial calls give the same phases and margins: {same}")


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--pairs", nargs="+", choices=list(PAIRS), default=list(PAIRS))
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--side", type=int, default=15)
    p.add_argument("--size", type=int, default=80)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--log", type=Path)
    args = p.parse_args(argv)
    start_log(args.log)
    warnings.simplefilter("ignore")
    for pair in args.pairs:
        for seed in args.seeds:
            run(pair, seed, args)


if __name__ == "__main__":
    main()
