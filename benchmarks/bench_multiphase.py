"""Benchmark: phase decisions and orientations on realistic two-phase maps (issue 55).

Maps from ``validation.multiphase.two_phase_map``: Voronoi grains of two
iron phases, patterns simulated with de-ebsd's master patterns and recorded
by ``Camera`` (150 counts/px, background lobe, blur, static and dynamic
background removal), calibrated and reindexed with ebsdsim's; a vendor's
start: the geometry ``synthetic.DEFAULT_PERTURBATION`` off (about 2 % of
the width), 5 % of the points labelled with the other phase, every point's
orientation indexed in its label's phase by kikuchipy at that geometry.
Pairs: ferrite + austenite (bcc/fcc, easy) and ferrite + martensite (bcc
against bct with c/a = 1.025, hard).

Methods, each scored against the truth:

- ``vendor start``: the start itself (labels and orientations);
- ``kikuchipy merge @start`` / ``@truth``: kikuchipy's route for a
  multi-phase map, ``EBSD.refine_orientation`` (Nelder-Mead) per phase over
  every point from the start orientations, then
  ``kikuchipy.indexing.merge_crystal_maps`` (best NCC wins), at the start
  detector (no calibration) and at the true one (a perfect calibration);
- ``geomdic today``: the package as it is: ``refine_geometry_dic`` from the
  points of the majority label (``phase=``), then ``reindex`` one phase a
  call at the calibrated detector, each point keeping its label;
- ``geomdic multi-phase``: issue 55's core, plugged in through a HOOK
  (:func:`package_multiphase`, :func:`default_hooks`): ``refine_geometry_dic``
  from every phase's points in one solve, then ``reindex(...,
  decide_phase=True)``; ``n/a`` where ``reindex`` has no ``decide_phase``;
- ``from-truth limit``: every point refined from its TRUE orientation
  against each phase at the true detector (kikuchipy NM): the fraction
  where the true phase scores best bounds any decision by NCC on these
  patterns.

Printed per seed, pair and method: the fraction of points whose phase is
right (``phase%``), the orientation error (disorientation to the truth in
the true phase's symmetry, deg) of the points with the right phase (mean,
median, count over 5 deg, and ``rel mean``: the mean with the map's common
rotation removed, what an error of the detector angles leaves, over the
points within 5 deg), the largest PC error over the map of the detector
used, the wall time (s), and where the method flags points not to trust
(``converged`` 0) the flagged percentage and the number of points with a
wrong phase left trusted (``wrong``).

Usage::

    python benchmarks/bench_multiphase.py --seeds 0 1 --side 15 --size 80
    python benchmarks/bench_multiphase.py --pairs ferrite+martensite --size 60 --dose 30
"""

from __future__ import annotations

import argparse
import inspect
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from kikuchipy.indexing import merge_crystal_maps
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
from kikuchipy_geomdic.geometry import rotation_vectors
from kikuchipy_geomdic.indexing.reindex import quiet, reindex
from kikuchipy_geomdic.validation.camera import MODERATE
from kikuchipy_geomdic.validation.multiphase import PAIRS, two_phase_map

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _tee import start_log  # noqa: E402

#: A calibration of a two-phase map: ``calibrate(signal, start_xmap,
#: start_detector, master_patterns, energy) -> detector``, master_patterns
#: a list in the map's phase-id order.
Calibrate = Callable
#: A reindexing that decides each point's phase: ``decide(signal, xmap,
#: detector, master_patterns, energy) -> CrystalMap`` with both phases.
Decide = Callable


def _deviations(truth: Rotation, got: Rotation, symmetry) -> np.ndarray:
    """Rotation vectors (deg, n x 3) of ``~truth * (op * got)`` with the
    crystal operator *op* that brings each point closest to its truth."""
    best = np.full(truth.size, -1.0)
    q = np.zeros((truth.size, 4))
    for op in Rotation(symmetry.proper_subgroup).flatten():
        cand = ~truth * (op * got)
        better = np.abs(cand.a) > best
        best = np.where(better, np.abs(cand.a), best)
        q[better] = cand.data[better]
    return np.rad2deg(rotation_vectors(Rotation(q)))


def score(tp, xmap: CrystalMap) -> dict:
    """Phase right fraction and orientation errors of *xmap* against the
    truth of the two-phase map *tp*: of the points with the right phase,
    the disorientation to the truth (mean, median, count over 5 deg) and
    its mean with the map's common rotation removed (``rel``: what the
    detector angles leave, mean over the points within 5 deg)."""
    names = dict(xmap.phases)
    got = np.array([names[i].name if i in names else "" for i in xmap.phase_id])
    truth_names = np.array(tp.phase_names)[tp.xmap.phase_id]
    right = got == truth_names
    dev = np.full((right.size, 3), np.nan)
    for pid in range(2):
        m = right & (tp.xmap.phase_id == pid)
        if m.any():
            sym = tp.xmap.phases[pid].point_group
            dev[m] = _deviations(tp.xmap.rotations[m], xmap.rotations[m], sym)
    e = np.linalg.norm(dev[right], axis=1)
    near = dev[right][e < 5]
    rel = np.linalg.norm(near - near.mean(axis=0), axis=1).mean() if near.size else np.nan
    flagged = wrong_trusted = None
    if "converged" in xmap.prop:
        trusted = xmap.prop["converged"] == 1
        flagged, wrong_trusted = 1 - trusted.mean(), int((~right & trusted).sum())
    return dict(
        flagged=flagged,
        wrong_trusted=wrong_trusted,
        right=right.mean(),
        mean=e.mean() if e.size else np.nan,
        median=np.median(e) if e.size else np.nan,
        over5=int((e > 5).sum()),
        rel=rel,
    )


def _one_phase_xmap(tp, rotations, name) -> CrystalMap:
    """Every point of the map in phase *name*, at *rotations*."""
    x = tp.start_xmap
    return CrystalMap(
        rotations=rotations, x=x.x, y=x.y, scan_unit="um",
        phase_list=PhaseList(tp.master_patterns[name].phase.deepcopy()),
    )  # fmt: skip


def refine_each_phase(tp, rotations, detector) -> list[CrystalMap]:
    """kikuchipy's ``refine_orientation`` (Nelder-Mead) of every point
    against each phase from *rotations*."""
    out = []
    for name in tp.phase_names:
        with quiet():
            out.append(
                tp.signal.refine_orientation(
                    _one_phase_xmap(tp, rotations, name),
                    detector,
                    tp.master_patterns[name],
                    tp.energy,
                )  # fmt: skip
            )
    return out


def kikuchipy_merge(tp, detector) -> CrystalMap:
    """kikuchipy's multi-phase route: refine per phase, merge by NCC."""
    refined = refine_each_phase(tp, tp.start_xmap.rotations, detector)
    return merge_crystal_maps(refined, mean_n_best=1, greater_is_better=True)


def from_truth_limit(tp) -> float:
    """Fraction of points whose true phase scores best when each point is
    refined from its true orientation at the true detector."""
    a, b = refine_each_phase(tp, tp.xmap.rotations, tp.detector)
    best = (b.prop["scores"] > a.prop["scores"]).astype(int)
    return float((best == tp.xmap.phase_id).mean())


def geomdic_today(tp) -> tuple[CrystalMap, object]:
    """The package today: calibrate from the majority label's points,
    then reindex one phase a call, each point keeping its label."""
    label = tp.start_xmap.phase_id
    major = int(np.bincount(label, minlength=2).argmax())
    name = tp.phase_names[major]
    res = refine_geometry_dic(
        tp.signal, tp.start_xmap, tp.start_detector, tp.master_patterns[name], tp.energy,
        phase=name, points=min(100, int((label == major).sum())), show_progressbar=False,
    )  # fmt: skip
    return reindex_per_label(tp, res.detector), res.detector


def reindex_per_label(tp, detector) -> CrystalMap:
    """``reindex`` of each labelled phase's points, the other phase's left
    out (``navigation_mask``), merged point by point into one map."""
    nav = tp.geometry.navigation_shape
    label = tp.start_xmap.phase_id
    rot = tp.start_xmap.rotations.data.copy()
    converged = np.zeros(label.size, dtype=int)
    for pid, name in enumerate(tp.phase_names):
        if not (label == pid).any():
            continue
        out = reindex(
            tp.signal, tp.start_xmap, detector, tp.master_patterns[name], tp.energy,
            phase=name, navigation_mask=(label != pid).reshape(nav), show_progressbar=False,
        )  # fmt: skip
        rot[label == pid] = out.rotations.data[label == pid]
        converged[label == pid] = out.prop["converged"][label == pid]
    x = tp.start_xmap
    return CrystalMap(
        rotations=Rotation(rot), phase_id=label, x=x.x, y=x.y,
        phase_list=x.phases.deepcopy(), prop={"converged": converged}, scan_unit="um",
    )  # fmt: skip


# --------------------------------------------------------------------- #
# HOOK: issue 55's core. Pass the package's functions here when they exist
# --------------------------------------------------------------------- #


def package_multiphase(tp, calibrate: Calibrate, decide: Decide) -> tuple[CrystalMap, object]:
    """Run a multi-phase calibration and a phase-deciding reindex on *tp*.

    Parameters
    ----------
    tp
        :class:`~kikuchipy_geomdic.validation.multiphase.TwoPhaseMap`.
    calibrate
        ``calibrate(signal, start_xmap, start_detector, master_patterns,
        energy) -> detector``: e.g. ``refine_geometry_dic`` over several
        phases (its ``.detector``).
    decide
        ``decide(signal, xmap, detector, master_patterns, energy) ->
        CrystalMap``: e.g. ``reindex(..., decide_phase=True)``.

    Returns
    -------
    xmap, detector
        The decided map and the calibrated detector.
    """
    mps = [tp.master_patterns[n] for n in tp.phase_names]
    detector = calibrate(tp.signal, tp.start_xmap, tp.start_detector, mps, tp.energy)
    return decide(tp.signal, tp.start_xmap, detector, mps, tp.energy), detector


#: The package's multi-phase calibrations run by :func:`default_hooks`'
#: ``calibrate``, in order (their standard errors for the honesty row)
CALIBRATIONS: list = []


def default_hooks() -> tuple[Calibrate, Decide] | None:
    """The package's own multi-phase functions, once ``reindex`` takes
    ``decide_phase`` (the core of issue 55); None before. Adapt the calls
    here to the core's final API."""
    if "decide_phase" not in inspect.signature(reindex).parameters:
        return None

    def calibrate(signal, xmap, detector, mps, energy):
        res = refine_geometry_dic(
            signal, xmap, detector, mps, energy, points=100, show_progressbar=False
        )
        CALIBRATIONS.append(res)
        return res.detector

    def decide(signal, xmap, detector, mps, energy):
        return reindex(signal, xmap, detector, mps, energy, decide_phase=True,
                       show_progressbar=False)  # fmt: skip

    return calibrate, decide


# --------------------------------------------------------------------- #


def _pc_error(tp, detector) -> float:
    return float(np.abs(np.asarray(detector.pc) - tp.detector.pc).max())


def run(pair: str, seed: int, args, hooks) -> list[dict]:
    t0 = time.perf_counter()
    tp = two_phase_map(
        PAIRS[pair], (args.side, args.side), (args.size, args.size), mislabel=args.mislabel,
        data=args.data, calibrate=args.calibrate, seed=seed,
        camera=replace(MODERATE, dose=args.dose),
    )  # fmt: skip
    rows = [dict(method="vendor start", t=time.perf_counter() - t0,
                 pc=_pc_error(tp, tp.start_detector), **score(tp, tp.start_xmap))]  # fmt: skip

    def timed(method, fn, detector=None):
        t = time.perf_counter()
        out = fn()
        xmap, det = out if isinstance(out, tuple) else (out, detector)
        rows.append(dict(method=method, t=time.perf_counter() - t, pc=_pc_error(tp, det),
                         **score(tp, xmap)))  # fmt: skip

    timed("kikuchipy merge @start", lambda: kikuchipy_merge(tp, tp.start_detector),
          tp.start_detector)  # fmt: skip
    timed("kikuchipy merge @truth", lambda: kikuchipy_merge(tp, tp.detector), tp.detector)
    timed("geomdic today", lambda: geomdic_today(tp))
    if hooks is None:
        rows.append(dict(method="geomdic multi-phase", na=True))
    else:
        timed("geomdic multi-phase", lambda: package_multiphase(tp, *hooks))
        if CALIBRATIONS:
            # The calibration's PC at the map's reference point against its
            # standard errors: honest where every |error| <= 3 of them
            res, truth = CALIBRATIONS[-1], tp.geometry.as_dict()
            err = [res.parameters[k] - truth[k] for k in ("pcx", "pcy", "pcz")]
            se = [res.standard_errors[k] for k in ("pcx", "pcy", "pcz")]
            rows.append(dict(method="joint calibration", calib=(err, se)))
        # decide_phase alone at kikuchipy's @truth detector: its time beside
        # kikuchipy's refinement per phase and merge
        mps = [tp.master_patterns[n] for n in tp.phase_names]
        timed("geomdic decide @truth",
              lambda: hooks[1](tp.signal, tp.start_xmap, tp.detector, mps, tp.energy),
              tp.detector)  # fmt: skip
    t = time.perf_counter()
    limit = from_truth_limit(tp)
    rows.append(dict(method="from-truth limit", t=time.perf_counter() - t, right=limit,
                     limit=True, pc=0.0))  # fmt: skip
    return rows


def _line(pair, seed, r) -> str:
    head = f"{pair:<19s} {seed:4d} {r['method']:<23s}"
    if r.get("calib"):
        err, se = r["calib"]
        z = max(abs(e) / s for e, s in zip(err, se))
        return head + (
            "   PC err " + " ".join(f"{e:+.1e}" for e in err) + " | se "
            + " ".join(f"{s:.1e}" for s in se) + f" | max z {z:.1f}"
        )  # fmt: skip
    if r.get("na"):
        return head + "   n/a (hook: package_multiphase, default_hooks)"
    if r.get("limit"):
        return head + f" {100 * r['right']:6.1f} {'':>39s} {r['pc']:9.2e} {r['t']:7.1f}"
    flags = "        -     -"
    if r["flagged"] is not None:
        flags = f" {100 * r['flagged']:8.1f} {r['wrong_trusted']:5d}"
    return head + (
        f" {100 * r['right']:6.1f} {r['mean']:9.3f} {r['median']:9.3f} {r['over5']:9d}"
        f" {r['rel']:9.3f} {r['pc']:9.2e} {r['t']:7.1f}{flags}"
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", nargs="+", choices=list(PAIRS), default=list(PAIRS))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--side", type=int, default=15)
    p.add_argument("--size", type=int, default=80)
    p.add_argument("--mislabel", type=float, default=0.05)
    p.add_argument("--dose", type=float, default=150.0, help="the camera's counts per pixel")
    p.add_argument("--data", default="de-ebsd", help="master patterns of the data (kind)")
    p.add_argument("--calibrate", default="dynamical", help="master patterns to calibrate with")
    p.add_argument("--log", type=Path, help="also write the output to this file")
    args = p.parse_args(argv)
    start_log(args.log)
    hooks = default_hooks()
    print(
        f"{'pair':<19s} {'seed':>4s} {'method':<23s} {'phase%':>6s} {'err mean':>9s} "
        f"{'median':>9s} {'n > 5deg':>9s} {'rel mean':>9s} {'PC err':>9s} {'time s':>7s} "
        f"{'flagged%':>8s} {'wrong':>5s}"
    )
    for pair in args.pairs:
        for seed in args.seeds:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rows = run(pair, seed, args, hooks)
            for r in rows:
                print(_line(pair, seed, r), flush=True)


if __name__ == "__main__":
    main()
