"""A map of several phases refined phase by phase (:func:`_reindex_phases`):
each phase's points by the one-phase route of
:func:`~kikuchipy_geomdic.indexing.reindex.reindex`, put together in one
crystal map with every phase; with ``decide_phase``, every point refined
against every phase and the phase its pattern shows kept
(:func:`_decide`), with its margin over the best other phase in units of
the pattern's noise.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import dask
import numpy as np
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.indexing._kikuchipy import _reindex_kikuchipy
from kikuchipy_geomdic.indexing._map_output import _flag_isolated, _with_domain
from kikuchipy_geomdic.indexing._map_refinement import _reindex_geomdic
from kikuchipy_geomdic.indexing._parts import _parts
from kikuchipy_geomdic.indexing._projection import PhaseArrays, detector_matrix, detector_pcs
from kikuchipy_geomdic.indexing._variant_comparison import compare_variants

#: Points whose patterns the phase decision reads at a time
_DECISION_BATCH = 1024


def _reindex_phases(signal, xmap, detector, phases, energy, todo, options) -> CrystalMap:
    """Each phase's points (*todo* and of its phase) refined by the one-phase
    route, the results put together in one map with every phase."""
    pid = xmap.phase_id.reshape(todo.shape)
    maps = [
        _reindex_phase(signal, xmap, detector, p, energy, todo & (pid == p.phase_id), options)
        for p in phases
    ]
    ids = np.where(todo.ravel(), xmap.phase_id, -2)
    return _combined(maps, phases, ids)


def _reindex_phase(signal, xmap, detector, phase, energy, todo, options) -> CrystalMap:
    """One phase's points refined: :func:`reindex`'s one-phase route."""
    o = dict(options)
    ops, pid, mp = phase.pseudo_symmetry_ops, phase.phase_id, phase.master_pattern
    kwargs = dict(o["refine_kwargs"])
    if o["method"] == "kikuchipy":
        if ops is not None:
            kwargs["pseudo_symmetry_ops"] = ops
        out = _reindex_kikuchipy(
            signal, xmap, detector, mp, energy, todo, pid, phase.phase.deepcopy(),
            o["show_progressbar"], kwargs,
        )  # fmt: skip
        return _with_domain(out, ops, pid)
    out = _reindex_geomdic(
        signal, xmap, detector, mp, energy, todo, pid, phase.phase.deepcopy(),
        pseudo_symmetry_ops=ops, reseed=o["reseed"], dic_rms=o["dic_rms"],
        show_progressbar=o["show_progressbar"], min_significance=o["min_significance"],
        refine_kwargs=kwargs,
    )  # fmt: skip
    out = _with_domain(out, ops, pid)
    if ops is not None and "domain" in out.prop:
        _flag_isolated(out)
    return out


def _combined(maps, phases, ids) -> CrystalMap:
    """One map of the per-phase *maps* (each of the whole map): at each
    point the map of the phase *ids* (N,) names (the map's phase id of
    ``phases[k]``; other values: the first map's point), with every
    phase's master pattern phase."""
    if len(maps) == 1:
        return maps[0]
    first = maps[0]
    q = first.rotations.data.reshape(-1, 4).copy()
    pid = first.phase_id.copy()
    prop = {k: np.asarray(v).copy() for k, v in first.prop.items()}
    phase_list = {int(i): p.deepcopy() for i, p in first.phases if i >= 0}
    for m, p in zip(maps, phases):
        sel = ids == p.phase_id
        phase_list[p.phase_id] = m.phases[p.phase_id].deepcopy()
        q[sel] = m.rotations.data.reshape(-1, 4)[sel]
        pid[sel] = m.phase_id[sel]
        for key, value in m.prop.items():
            value = np.asarray(value)
            if key not in prop:
                prop[key] = np.full(value.shape, -1 if key == "domain" else 0, value.dtype)
            prop[key][sel] = value[sel]
    return CrystalMap(
        rotations=Rotation(q),
        phase_id=pid,
        x=None if first.x is None else first.x.copy(),
        y=None if first.y is None else first.y.copy(),
        phase_list=PhaseList(phase_list),
        prop=prop,
        scan_unit=first.scan_unit,
    )


def _decide(signal, xmap, detector, phases, energy, todo, options) -> CrystalMap:
    """Every point of *todo* refined against every phase (from its own
    orientation, and, where it scores poorly, from its neighbours'
    refined in that phase: the route's reseeding), the phase its pattern
    shows kept (:func:`_phase_calls`), ``phase_margin`` its significance
    and ``converged`` 0 below *min_significance*."""
    flat = todo.ravel()
    relabelled = [_as_phase(xmap, p.phase_id, flat) for p in phases]
    maps = [
        _reindex_phase(signal, x, detector, p, energy, todo, options)
        for x, p in zip(relabelled, phases)
    ]
    rows = np.flatnonzero(flat & np.all([m.phase_id >= 0 for m in maps], axis=0))
    candidates = np.stack([m.rotations.data.reshape(-1, 4)[rows] for m in maps], axis=1)
    arrays = tuple(p.arrays(energy) for p in phases)
    kept, margin, ncc = _phase_calls(signal, detector, rows, candidates, arrays)
    ids = np.full(flat.size, -2)
    ids[rows] = np.array([p.phase_id for p in phases])[kept]
    # Points refined in no phase (a NaN pattern): the first phase's result
    lost = flat & (ids == -2)
    ids[lost] = phases[0].phase_id
    out = _combined(maps, phases, ids)
    phase_margin = np.zeros(flat.size)
    phase_margin[rows] = margin
    out.prop["phase_margin"] = phase_margin
    for k in range(len(phases)):
        score = np.zeros(flat.size)
        score[rows] = ncc[:, k]
        out.prop[f"phase_score_{k}"] = score
    undecided = flat & ~(phase_margin >= options["min_phase_significance"])
    out.prop["converged"] = np.where(undecided, 0, out.prop["converged"]).astype(np.int8)
    out.prop["phase_changed"] = (flat & (out.phase_id != xmap.phase_id)).astype(np.int8)
    return out


def _as_phase(xmap, phase_id, flat) -> CrystalMap:
    """*xmap* with the points *flat* labelled *phase_id* (a fresh map)."""
    pid = np.where(flat, phase_id, xmap.phase_id)
    return CrystalMap(
        rotations=Rotation(xmap.rotations.data.reshape(-1, 4).copy()),
        phase_id=pid,
        x=xmap.x,
        y=xmap.y,
        phase_list=xmap.phases.deepcopy(),
        prop={k: np.asarray(v).copy() for k, v in xmap.prop.items()},
        scan_unit=xmap.scan_unit,
    )


def _phase_calls(signal, detector, rows, candidates, arrays):
    """The phase (N,) each point of *rows* shows among its *candidates*
    (N, K, 4), one refined in each phase of *arrays*, by
    :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants` across
    phases (each candidate projected from its own phase), its significance
    (N,) and every candidate's NCC (N, K).

    Each point is compared on its own, so the points are split into parts
    run on dask's scheduler (:func:`_compare_parts`): in one call the
    comparison ran on one core while the refinements it follows ran on
    all, a quarter of the decision's wall time on two cores (measured:
    0.11 s beside 0.38 s per phase on the hard pair's 15 x 15 map of
    80 px)."""
    n, k = candidates.shape[:2]
    data = signal.data.reshape((-1,) + signal.data.shape[-2:])
    pcs = detector_pcs(detector, data.shape[0])
    om = detector_matrix(detector)
    kept, sig, ncc = np.zeros(n, np.int64), np.zeros(n), np.zeros((n, k))
    for start in range(0, n, _DECISION_BATCH):
        i = slice(start, start + _DECISION_BATCH)
        r = rows[i]
        patterns = np.asarray(data[r].compute() if hasattr(data, "compute") else data[r])
        kept[i], sig[i], ncc[i] = _compare_parts(patterns, candidates[i], pcs[r], om, arrays)
    return kept, sig, ncc


def _compare_parts(patterns, candidates, pcs, om, arrays):
    """:func:`_compare` of *patterns* (N, rows, cols) in parts, two per
    thread of dask's pool, on dask's scheduler."""
    tasks = [
        dask.delayed(_compare)(patterns[p], candidates[p], pcs[p], om, arrays)
        for p in _parts(len(patterns))
    ]
    results = dask.compute(*tasks)
    return tuple(np.concatenate([res[j] for res in results]) for j in range(3))


def _compare(patterns, candidates, pcs, om, arrays):
    """The kept candidate (N,), its significance (N,) and every candidate's
    NCC (N, K) of *patterns*, each candidate projected from its phase."""
    k = candidates.shape[1]
    labels = np.tile(np.arange(k), len(patterns))
    cmp = compare_variants(
        patterns.astype(np.float64), candidates, pcs, om, PhaseArrays(arrays, labels)
    )
    return cmp.variant, cmp.significance, cmp.ncc
