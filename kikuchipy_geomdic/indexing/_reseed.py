"""The reseeding stage of
:func:`~kikuchipy_geomdic.indexing.reindex.refine_map`: the points of a
map that score poorly for where they are
(:func:`~kikuchipy_geomdic.indexing.orientation.poor_points`), that sit a
fraction of a degree from neighbours that agree with one another
(:func:`~kikuchipy_geomdic.indexing.orientation.neighbour_disagreement`),
or that are alone in their variant among neighbours of their parent,
refined again from their neighbours' distinct orientations, a result kept
only where it scores better.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import dask
import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.indexing._parts import _parts
from kikuchipy_geomdic.indexing._point_refinement import (
    _EVALS,
    _NCC,
    _Q,
    _SCORE,
    _VARIANT,
    _refine_points,
)
from kikuchipy_geomdic.indexing._quaternions import _qmul
from kikuchipy_geomdic.indexing._seeds import (
    DISAGREEMENT,
    DISAGREEMENT_MAX,
    neighbour_disagreement,
    neighbour_seeds,
    poor_points,
)
from kikuchipy_geomdic.patterns.phases import _proper_subgroup


def _proper_symmetry(master_pattern) -> np.ndarray:
    """Quaternions (S, 4) of the proper point group of the master pattern's
    phase (the identity alone for bare arrays)."""
    phase = getattr(master_pattern, "phase", None)
    if phase is None:
        return np.array([[1.0, 0.0, 0.0, 0.0]])
    ops = Rotation(_proper_subgroup(phase.point_group)).flatten()
    return np.asarray(ops.data, dtype=np.float64)


def _equivalents(ops, sym) -> np.ndarray:
    """Quaternions (E, 4) of every ``s * op`` (s a symmetry, op the identity
    or a pseudo-symmetry operator): what makes two orientations the same
    candidate set."""
    ident = np.array([[1.0, 0.0, 0.0, 0.0]])
    ops_all = ident if ops is None else np.concatenate([ident, ops])
    return _qmul(sym[:, None, :], ops_all[None, :, :]).reshape(-1, 4)


def _distinct(
    seeds: np.ndarray, equivalents: np.ndarray, min_angle: float = DISAGREEMENT
) -> np.ndarray:
    """The seeds (k, 4) whose candidate sets differ: a seed that is an
    equivalent (symmetry times variant) of an earlier one within
    *min_angle* degrees adds nothing, as its variants are refined anyway
    (the disagreement a point is tried for: at 1 deg, a good seed next to
    one tried earlier was never tried)."""
    cos_half = np.cos(np.deg2rad(min_angle) / 2)
    kept: list[np.ndarray] = []
    for q in seeds:
        if kept:
            eq = _qmul(equivalents, q[None, :])
            if (np.abs(eq @ np.array(kept).T) >= cos_half).any():
                continue
        kept.append(q)
    return np.array(kept).reshape(-1, 4)


def _relabel(q, start, ops, sym) -> np.ndarray:
    """Variant index (0: the start's, k: ``ops[k - 1]`` applied) of each
    orientation *q* (n, 4) relative to its *start* (n, 4): the variant of
    the start nearest to it, the crystal's symmetry allowed."""
    ident = np.array([[1.0, 0.0, 0.0, 0.0]])
    ops_all = np.concatenate([ident, ops])
    targets = _qmul(ops_all[None, :, :], start[:, None, :])  # (n, K, 4)
    eq = _qmul(sym[None, :, :], q[:, None, :])  # (n, S, 4)
    cos = np.abs(np.einsum("nkq,nsq->nks", targets, eq)).max(axis=2)
    return cos.argmax(axis=1)


#: Most passes of reseeding: a point fixed in one pass seeds its poor
#: neighbours in the next (runs of misindexed points); passes stop as soon
#: as one changes nothing. At 4, a region of 25 points whose first pass
#: failed stayed wrong (users map of dose 30, seed 1, azimuthal 2 deg
#: off: 84 % of the 90 deg domain right; at 16, all but one)
RESEED_PASSES = 16


def _reseed(d, out, todo, pcs, nav, options, start, sym) -> np.ndarray:
    """Refine poor and disagreeing points again from their neighbours'
    orientations, in place in *out*; return which points a neighbour's
    seed improved.

    A seed's result replaces the point's own only where it scores better
    on the point's own pattern, so reseeding never lowers a score. Seeds
    are the neighbours' refined orientations as they are (each refined
    with all its variants when there are operators), never averages;
    seeds that are symmetry or variant equivalents of one another are
    refined once. A replaced point's ``variant`` is relabelled relative to
    its own *start*."""
    rows, cols = nav
    ops = options["ops"]
    if ops is not None:
        # A seed is a neighbour's refined orientation, next to the point's
        # own in its variant: the coarse stages that widen the basin for
        # users' starts are not needed; the seed's variants are compared
        # at full resolution alone (measured on the users map of dose 150,
        # seed 0: 14 fewer projections per point of the map, same calls)
        options = dict(options, levels=(1,))
    equivalents = _equivalents(ops, sym)
    reseeded = np.zeros(rows * cols, dtype=bool)
    valid = todo.reshape(nav) & np.isfinite(out[:, _SCORE]).reshape(nav)
    tried: dict[int, list[np.ndarray]] = {}
    for _ in range(RESEED_PASSES):
        q_map = out[:, _Q].reshape(rows, cols, 4)
        poor, disagree, agree = _to_try(
            q_map, out[:, _SCORE].reshape(nav), valid, equivalents, sym, ops is not None
        )
        if not (poor | disagree).any():
            break
        points, seeds = [], []
        for p in np.argwhere(poor | disagree):
            f = int(p[0] * cols + p[1])
            usable = valid & ~poor & (agree if disagree[tuple(p)] else True)
            s = _distinct(neighbour_seeds(q_map, tuple(p), usable), equivalents)
            # A seed refined in an earlier pass gives the same result again
            done = tried.setdefault(f, [])
            if done and len(s):
                old = np.concatenate(done)
                s = np.array([q for q in s if not _seen(q, old, equivalents)]).reshape(-1, 4)
            if len(s):
                points.append(p)
                seeds.append(s)
                done.append(s)
        if not points:
            break
        points = np.array(points)
        patterns = np.asarray(d.vindex[points[:, 0], points[:, 1]].compute())
        counts = [len(s) for s in seeds]
        idx = np.repeat(np.arange(len(points)), counts)
        flat = points[:, 0] * cols + points[:, 1]
        floor = out[flat[idx], _SCORE] if ops is not None else None
        trial = _trials(patterns[idx], np.concatenate(seeds), pcs[flat[idx]], options, floor)
        changed = False
        for i, f in enumerate(flat):
            mine = trial[idx == i]
            b = int(np.nanargmax(mine[:, _SCORE]))
            best = mine[b]
            spent = out[f, _EVALS] + mine[:, _EVALS].sum()
            if best[_SCORE] > out[f, _SCORE]:
                out[f] = best
                if ops is not None:
                    out[f, _VARIANT] = _relabel(best[None, _Q], start[None, f], ops, sym)[0]
                    out[f, _NCC:] = _scores_from_start(
                        best[_NCC:], seeds[i][b], start[f], ops, sym
                    )
                reseeded[f] = changed = True
            out[f, _EVALS] = spent
        if not changed:
            break
    return reseeded


def _scores_from_start(ncc, seed, start, ops, sym) -> np.ndarray:
    """The NCCs (K,) of a trial's candidates, ``op_j * seed``, reordered
    as the variants of the point's own *start* (the order the output's
    columns count in); a variant no candidate maps to gets NaN."""
    ident = np.array([[1.0, 0.0, 0.0, 0.0]])
    candidates = _qmul(np.concatenate([ident, ops]), seed[None, :])
    label = _relabel(candidates, np.repeat(start[None, :], len(candidates), axis=0), ops, sym)
    out = np.full(len(ncc), np.nan)
    out[label] = ncc
    return out


def _to_try(q_map, scores, valid, equivalents, sym, variants):
    """Boolean maps of the points to refine again: those scoring poorly
    for where they are; those that disagree with neighbours that agree
    with theirs (tried only from those); and the neighbours that agree.

    A point disagrees when it is :data:`DISAGREEMENT` to
    :data:`DISAGREEMENT_MAX` from its neighbours (candidate sets:
    symmetry and variants allowed), a local optimum next to theirs that
    its score need not show (*equivalents*: :func:`_equivalents`); or,
    with *variants* (operators), when it is in their
    parent but most of them are in another variant (its own variants
    were refined from its start, not from theirs; measured: a base point
    called 90 deg among base neighbours, right from the true orientations)."""
    poor = poor_points(scores, valid)
    with np.errstate(invalid="ignore"):
        angle = neighbour_disagreement(q_map, valid, equivalents)
        agree = angle <= DISAGREEMENT
        disagree = valid & ~poor & (angle > DISAGREEMENT) & (angle <= DISAGREEMENT_MAX)
        if variants:
            lone = neighbour_disagreement(q_map, valid, sym) > DISAGREEMENT_MAX
            disagree |= valid & ~poor & agree & lone
    return poor, disagree, agree


def _trials(patterns, seeds, pcs, options, floor) -> np.ndarray:
    """:func:`_refine_points` of the seeds, in parts on dask's scheduler.

    Every row is refined on its own, so the parts give the rows one call
    gives; run as one call, reseeding took one core (measured: a quarter
    of the work of the users map of dose 150 on one of two threads)."""
    tasks = [
        dask.delayed(_refine_points)(
            patterns[r], seeds[r], pcs[r], **options, floor=None if floor is None else floor[r]
        )
        for r in _parts(len(seeds))
    ]
    return np.concatenate(dask.compute(*tasks))


def _seen(q, old, equivalents, min_angle: float = DISAGREEMENT) -> bool:
    cos_half = np.cos(np.deg2rad(min_angle) / 2)
    return bool((np.abs(_qmul(equivalents, q[None, :]) @ old.T) >= cos_half).any())
