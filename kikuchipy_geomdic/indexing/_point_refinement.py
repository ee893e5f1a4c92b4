"""The orientation refinement of a batch of map points, as rows of
:func:`~kikuchipy_geomdic.indexing.reindex.refine_map`'s output: each
point refined from its start and, with pseudo-symmetry operators, from
each variant of it, the variant its pattern shows kept; optionally the
DIC displacement at the result.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import warnings

import numpy as np

from kikuchipy_geomdic.indexing._projection import project_arrays
from kikuchipy_geomdic.indexing._quaternions import _qmul
from kikuchipy_geomdic.indexing._variant_comparison import compare_variants
from kikuchipy_geomdic.indexing.orientation import (
    MAX_EVALUATIONS,
    _coarse_stages,
    _fine_stage,
    refine_arrays,
)

# Columns of the per-point output of a chunk; then one NCC per candidate
_Q, _SCORE, _EVALS, _CONV, _RMS, _VARIANT, _CONF, _MARGIN = slice(0, 4), 4, 5, 6, 7, 8, 9, 10
_SIG, _NCC = 11, 12


#: Full-resolution evaluations (accelerated steps) of each variant started
#: at the refined best's variant. The significance of a call is a margin
#: between refined candidates: one left short of its optimum moves it, and
#: a point's flag then depends on where the point started. Measured on a 9 x 9
#: stripe map of 96 px (dose 150) reindexed from users' starts and from the
#: truth at one detector: 4 of 81 flags differed at 8 evaluations (the
#: significances' 90th percentile difference 0.50), 3 at 12, none at 16
#: (0.15) and 24 (0.06); 16 costs 29 % more projections per point than 8.
#: On the users maps (13 x 13, doses 30 and 150, seeds 0-2, the true
#: detector) users' starts then flag within 2 points of the truth's starts
#: on every map (at 8: 25 against 16 on one), with as many right calls or
#: more (an earlier screen of 3 evaluations lost right 90 deg variants)
VARIANT_EVALUATIONS = 16

#: A reseeding trial whose refined best scores below this fraction of the
#: point's own score does not refine its other variants (a seed's result
#: replaces the point's only where it scores better; at a neighbour's
#: orientation the right variant scores best). Measured on the users maps
#: (doses 30 and 150, seeds 0 and 1): 1.0 kept every point of 0.9 and
#: saved 4 % of the projections
HOPELESS = 1.0


def _width(ops) -> int:
    return _NCC + 1 + (0 if ops is None else len(ops))


def _refine_points(
    patterns, q, pcs, arrays, om, levels, max_step, dic_rms, ops, floor=None, retry=True
) -> np.ndarray:
    """The output rows (k, width) of k patterns refined from starts *q*:
    with pseudo-symmetry *ops*, from each variant of the start too, the
    variant kept by :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`.

    With *ops*, in three steps. First every variant of the start runs
    the coarse stages from its own start. A start a few degrees off (a
    user's, refined in the wrong variant at a wrong geometry) leaves some
    of them in a local optimum, and comparing those with one that
    converged would choose by convergence, not by the pattern. So the best
    of them by full-resolution NCC (variants differ in it only in the
    third decimal where they are alike; a missed basin is far below) runs
    the full-resolution stage alone, and gives every other variant a start
    at the same place, ``op_j * op_b^-1 * q_b``, next to its own optimum
    (the coarse result is ~0.9 deg from the full-resolution optimum, its
    variants then 0.1-0.5 deg from theirs). Those run
    :data:`VARIANT_EVALUATIONS` accelerated full-resolution steps, and the
    six are compared. Candidate j stays the start's variant j
    (``op_j * q``). *floor* (reseeding: the point's own score) skips the
    other variants of a trial whose best is below :data:`HOPELESS` of it:
    it cannot replace the point's result. Without *retry*, a kept result
    that did not converge is not refined again here (:func:`_retry`: the
    map's driver does it for the points that do not score poorly, after
    reseeding)."""
    k = patterns.shape[0]
    rows = np.arange(k)
    hopeless = np.zeros(k, dtype=bool)
    if ops is None:
        res = refine_arrays(patterns, q, pcs, om, arrays, levels, max_step)
        rq = res.rotations.data.copy()[:, None, :]
        scores, conv = res.scores.copy()[:, None], res.converged.copy()[:, None]
        evals = res.evaluations.copy()
        kept = np.zeros(k, dtype=np.int64)
        out = np.full((k, _width(ops)), np.nan)
        out[:, _CONF], out[:, _MARGIN], out[:, _NCC] = res.scores, 0.0, res.scores
        out[:, _SIG] = np.inf
    else:
        # Crystal-frame operators act on the left (op * rotation)
        ops_all = np.concatenate([[[1.0, 0.0, 0.0, 0.0]], ops])
        m = ops_all.shape[0]
        candidates = _qmul(ops_all[None, :, :], q[:, None, :])
        first = _coarse_stages(
            np.repeat(patterns, m, axis=0), candidates.reshape(-1, 4), np.repeat(pcs, m, axis=0),
            om, arrays, levels, max_step,
        )  # fmt: skip
        cq = first.rotations.data.reshape(k, m, 4)
        c_ncc = first.scores.reshape(k, m)
        best = np.argmax(np.where(np.isfinite(c_ncc), c_ncc, -np.inf), axis=1)
        # The best alone runs the full-resolution stage from the coarse
        # result: ~0.9 deg from its optimum there (median), it takes ~23
        # evaluations; the others then start at its variants, next to theirs
        fine = _fine_stage(
            patterns, cq[rows, best], pcs, om, arrays, max_step, MAX_EVALUATIONS[1]
        )  # fmt: skip
        base = _qmul(ops_all[best] * [1, -1, -1, -1], fine.rotations.data)
        target = _qmul(ops_all[None, :, :], base[:, None, :])
        rq, scores, conv = target.copy(), np.full((k, m), -np.inf), np.zeros((k, m), dtype=bool)
        rq[rows, best], scores[rows, best], conv[rows, best] = (
            fine.rotations.data,
            fine.scores,
            fine.converged,
        )
        spent = np.zeros((k, m))
        spent[rows, best] = fine.evaluations
        p, c = np.nonzero(np.arange(m) != best[:, None])
        if floor is not None:
            # A reseeding trial whose best is well below the point's own
            # score cannot replace it: its other variants are not refined
            hopeless = ~(fine.scores >= HOPELESS * floor)
            p, c = p[~hopeless[p]], c[~hopeless[p]]
        if p.size:
            res = _fine_stage(
                patterns[p], target[p, c], pcs[p], om, arrays, max_step, VARIANT_EVALUATIONS
            )  # fmt: skip
            rq[p, c], scores[p, c] = res.rotations.data, res.scores
            conv[p, c], spent[p, c] = res.converged, res.evaluations
        evals = first.evaluations.reshape(k, m).sum(axis=1) + spent.sum(axis=1)
        cmp = compare_variants(patterns, rq, pcs, om, arrays)
        kept = cmp.variant
        out = np.full((k, _width(ops)), np.nan)
        out[:, _CONF], out[:, _MARGIN], out[:, _NCC:] = cmp.confidence, cmp.margin, cmp.ncc
        out[:, _SIG] = cmp.significance
    q_kept, s_kept, c_kept = rq[rows, kept], scores[rows, kept], conv[rows, kept]
    if retry:
        again = np.flatnonzero(~c_kept & np.isfinite(s_kept) & ~hopeless)
        evals[again] += _retry(
            patterns[again], q_kept, s_kept, c_kept, again, pcs[again], om, arrays, max_step, ops
        )  # fmt: skip
    out[:, _Q] = q_kept
    out[:, _SCORE] = s_kept
    out[:, _EVALS] = evals
    out[:, _CONV] = c_kept
    out[:, _VARIANT] = kept
    if dic_rms:
        out[:, _RMS] = _dic_rms(patterns, out[:, _Q], pcs, om, arrays)
    return out


def _retry(patterns, q, scores, conv, rows, pcs, om, arrays, max_step, ops) -> np.ndarray:
    """Refine the kept results *rows* that did not converge once more at
    full resolution from where they are, in place in *q*, *scores* and
    *conv* where the NCC does not drop; return the evaluations spent
    (*patterns* and *pcs*: those of *rows*).

    A fine stage entered from a coarse result can run out of evaluations
    dithering between the master pattern's cells (measured: 16 % of
    candidates refined from the truth at dose 150, 4 % at full
    resolution alone): a stage from where it is converges."""
    if not rows.size:
        return np.zeros(0)
    if ops is None:
        res = refine_arrays(patterns, q[rows], pcs, om, arrays, (1,), max_step)
    else:
        res = _fine_stage(patterns, q[rows], pcs, om, arrays, max_step, MAX_EVALUATIONS[1])
    better = res.scores >= scores[rows]
    i = rows[better]
    q[i], scores[i] = res.rotations.data[better], res.scores[better]
    conv[i] = res.converged[better]
    return res.evaluations


def _dic_rms(patterns, q, pcs, om, arrays) -> np.ndarray:
    """RMS DIC displacement (px) of each pattern from its simulation."""
    from kikuchipy_geomdic.patterns.displacement import measure_displacements

    sim = project_arrays(q, pcs, om, arrays, patterns.shape[1:])
    with warnings.catch_warnings():
        # Empty ROIs and patterns are expected; their RMS is NaN below
        warnings.simplefilter("ignore", UserWarning)
        field = measure_displacements(sim, np.asarray(patterns, dtype=np.float64))
    with np.errstate(invalid="ignore"):
        return np.sqrt(
            (field.counts * (field.u**2).sum(axis=-1)).sum(axis=1) / field.counts.sum(axis=1)
        )
