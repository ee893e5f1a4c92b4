"""The whole map refined by this package's solver, chunk by chunk
(``method="geomdic"`` of :func:`~kikuchipy_geomdic.indexing.reindex.reindex`):
:func:`refine_map` expresses the work as a dask graph over the patterns'
chunks, reseeds poor points and says which results to trust;
``_reindex_geomdic`` turns its arrays into the refined crystal map.
The public names are presented by
:mod:`~kikuchipy_geomdic.indexing.reindex`.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import contextlib

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation

from kikuchipy_geomdic.indexing._map_output import _merge
from kikuchipy_geomdic.indexing._parts import _threads
from kikuchipy_geomdic.indexing._point_refinement import (
    _CONF,
    _CONV,
    _EVALS,
    _MARGIN,
    _NCC,
    _Q,
    _RMS,
    _SCORE,
    _SIG,
    _VARIANT,
    _dic_rms,
    _refine_points,
    _retry,
    _width,
)
from kikuchipy_geomdic.indexing._reseed import _proper_symmetry, _reseed
from kikuchipy_geomdic.indexing.orientation import (
    MAX_STEP,
    MasterPatternArrays,
    detector_matrix,
    detector_pcs,
    master_pattern_arrays,
    poor_points,
    pyramid_levels,
)

#: Pattern bytes (as float32) per dask chunk when the signal is in memory,
#: and per batch the solver takes from a chunk: large enough that the
#: Python overhead is small (290 patterns of 120 px), small enough that
#: the solver's working copies stay near 100 MB per thread (measured: 384
#: MB above the map for chunks of 256 patterns of 240 px on two threads).
CHUNK_BYTES = 16 * 2**20

#: Smallest significance (z-score of the cross-variant margin against its
#: standard error from the pattern's own noise,
#: :attr:`~kikuchipy_geomdic.indexing.orientation.VariantComparison.significance`)
#: of a variant call that :func:`reindex` trusts: below it the point gets
#: ``converged`` = 0. 2.5 is a false-call rate of 0.6 % per point
#: (one-sided normal tail) where a pattern carries no information about
#: the call: at most one such point per 13 x 13 map. At 2, calls biased by
#: a detector angle 1 deg off passed (measured: 2 of 81 points on a 9 x 9
#: map of 96 px; 0 at 2.5). Measured on 13 x 13 BaTiO3 stripe maps of
#: 120 px: ``bench_variants.py users`` and ``benchmarks/README.md``.
VARIANT_SIGNIFICANCE = 2.5


def refine_map(
    data,
    rotations: np.ndarray,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern | MasterPatternArrays,
    energy: float,
    *,
    todo: np.ndarray | None = None,
    reseed: bool = True,
    dic_rms: bool = False,
    show_progressbar: bool = False,
    pseudo_symmetry_ops: Rotation | None = None,
    min_significance: float = VARIANT_SIGNIFICANCE,
    levels=None,
    max_step: float = MAX_STEP,
) -> dict[str, np.ndarray]:
    """Refine the orientations of a map's patterns, chunk by chunk.

    The functional core of :func:`reindex` (``method="geomdic"``): plain
    arrays in and out, the work expressed as a dask graph over the
    patterns' chunks.

    Parameters
    ----------
    data
        Patterns, NumPy or dask array of shape nav + (rows, columns), nav
        1D or 2D.
    rotations
        Starting quaternions (n, 4), n the map's points in flat order.
    detector
        Detector of the patterns' shape with one PC or n.
    master_pattern, energy
        Lambert master pattern (or its arrays) and beam energy in kV.
    todo
        Boolean (n,): points to refine (default all).
    reseed
        Refine poor points again from their neighbours' orientations.
    dic_rms
        Measure the RMS DIC displacement at the refined orientations.
    show_progressbar
        Show dask's progress bar over the chunks.
    pseudo_symmetry_ops
        Operators (crystal frame, ``op * rotation``) of the variants to
        try at every point besides its start.
    min_significance
        With *pseudo_symmetry_ops*: variant calls of a smaller
        significance are not ``converged``.
    levels, max_step
        Of :func:`~kikuchipy_geomdic.indexing.orientation.refine_patterns`.

    Returns
    -------
    result
        Dict of flat arrays (n,): ``rotations`` (n, 4), ``scores``,
        ``iterations``, ``converged`` (bool), ``reseeded`` (bool) and
        ``dic_rms`` (NaN without *dic_rms*), ``variant`` (0: the start's,
        k: ``pseudo_symmetry_ops[k - 1]`` applied), ``confidence``,
        ``cross_variant_margin`` and ``variant_scores`` (n, K + 1) (NCC
        per candidate) and ``variant_significance`` of
        :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`; points
        not to do keep their rotation with NaN scores.

    Examples
    --------
    Every point of a 2 x 3 map but the last, from the map's starts:

    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.indexing.reindex import refine_map
    >>> sm = synthetic.synthetic_map("Si", (2, 3), shape=(40, 40), seed=0)
    >>> q = sm.start_xmap.rotations.data.reshape(-1, 4)
    >>> todo = [True] * 5 + [False]
    >>> out = refine_map(sm.signal.data, q, sm.detector, sm.master_pattern, 20, todo=todo)
    >>> out["rotations"].shape, out["converged"].tolist()
    ((6, 4), [True, True, True, True, True, False])
    """
    import dask
    import dask.array as da

    nav = tuple(data.shape[:-2])
    shape = tuple(data.shape[-2:])
    if len(nav) not in (1, 2):
        raise ValueError(f"The patterns must have a 1D or 2D navigation shape, not {nav}")
    rows, cols = (1,) + nav if len(nav) == 1 else nav
    n = rows * cols
    q = np.ascontiguousarray(np.asarray(rotations, dtype=np.float64).reshape(-1, 4))
    if q.shape[0] != n:
        raise ValueError(f"{q.shape[0]} starting orientations for a map of {n} points")
    todo = np.ones(n, dtype=bool) if todo is None else np.asarray(todo, dtype=bool).ravel()
    if todo.size != n:
        raise ValueError(f"todo has {todo.size} points, the map {n}")
    if tuple(detector.shape) != shape:
        raise ValueError(
            f"The detector's shape {detector.shape} differs from the patterns' {shape}"
        )
    pcs = detector_pcs(detector, n)
    arrays = master_pattern_arrays(master_pattern, energy)
    levels = pyramid_levels(shape, levels)
    om = detector_matrix(detector)

    if isinstance(data, da.Array):
        d = data.reshape((rows, cols) + shape) if len(nav) == 1 else data
        d = d.rechunk({2: -1, 3: -1})
    else:
        # name=False: not named by a hash of the patterns (12 ms per 16 MB)
        d = da.from_array(
            np.asarray(data).reshape((rows, cols) + shape),
            chunks=_chunks(rows, cols, 4 * shape[0] * shape[1]) + (-1, -1),
            name=False,
        )
    chunks = d.chunks[:2]
    qd = da.from_array(q.reshape(rows, cols, 4), chunks=chunks + ((4,),), name=False)
    pd = da.from_array(pcs.reshape(rows, cols, 3), chunks=chunks + ((3,),), name=False)
    td = da.from_array(todo.reshape(rows, cols), chunks=chunks, name=False)
    ops = None if pseudo_symmetry_ops is None else _operators(pseudo_symmetry_ops)
    width = _width(ops)
    options = dict(
        arrays=arrays, om=om, levels=levels, max_step=max_step, dic_rms=dic_rms, ops=ops
    )
    # With reseeding, results that did not converge are refined again on
    # the whole map (_finish), not in their chunk
    graph = da.blockwise(
        _refine_block, "ijk",
        d, "ijrc", qd, "ijq", pd, "ijp", td, "ij",
        new_axes={"k": width}, concatenate=True, dtype=np.float64, retry=not reseed, **options,
    )  # fmt: skip
    with _progress(show_progressbar):
        out = np.asarray(dask.compute(graph)[0]).reshape(n, width)

    reseeded = np.zeros(n, dtype=bool)
    if reseed:
        reseeded = _finish(d, out, todo, pcs, (rows, cols), options, q, master_pattern)
    scores = out[:, _SCORE].reshape(rows, cols)
    poor = poor_points(scores, todo.reshape(rows, cols)).ravel()
    converged = (out[:, _CONV] > 0) & ~poor & todo
    if ops is not None:
        # A variant call within the pattern's noise is not trusted
        converged &= out[:, _SIG] >= min_significance
    return {
        "rotations": out[:, _Q],
        "scores": out[:, _SCORE],
        "iterations": out[:, _EVALS],
        "converged": converged,
        "reseeded": reseeded,
        "dic_rms": out[:, _RMS],
        "variant": out[:, _VARIANT].astype(np.int64),
        "confidence": out[:, _CONF],
        "cross_variant_margin": out[:, _MARGIN],
        "variant_significance": out[:, _SIG],
        "variant_scores": out[:, _NCC:],
    }


def _chunks(rows: int, cols: int, pattern_bytes: int) -> tuple[int, int]:
    """Rows and columns per chunk of a map in memory: at most
    :data:`CHUNK_BYTES` of patterns, and at least :data:`CHUNKS_PER_THREAD`
    chunks per thread of dask's pool where the map has the points (a map
    that fit one chunk ran on one core: measured, 21 x 21 points of 96 px
    took 1.6 s in one chunk and 1.3 s in four on two busy cores)."""
    want = CHUNKS_PER_THREAD * _threads()
    per_row = max(1, CHUNK_BYTES // (pattern_bytes * cols))
    per_row = min(per_row, max(1, -(-rows // want)))
    per_col = cols
    if per_row == 1:
        # A row is too large for one chunk, or too few rows for the threads
        per_col = min(cols, max(1, CHUNK_BYTES // pattern_bytes))
        if rows < want:
            per_col = min(per_col, max(1, -(-cols // -(-want // rows))))
    return per_row, per_col


#: Chunks per thread of dask's pool that :func:`refine_map` makes at least
#: of a map in memory (more than one: chunks differ in cost)
CHUNKS_PER_THREAD = 2


def _operators(ops) -> np.ndarray:
    """Pseudo-symmetry operators as quaternions (K, 4)."""
    q = np.asarray(Rotation(ops).flatten().data, dtype=np.float64)
    if q.shape[0] == 0:
        raise ValueError("pseudo_symmetry_ops is empty")
    return q


def _progress(show: bool):
    if not show:
        return contextlib.nullcontext()
    from dask.diagnostics import ProgressBar

    return ProgressBar()


def _finish(d, out, todo, pcs, nav, options, start, master_pattern) -> np.ndarray:
    """Reseeding (:func:`~._reseed._reseed`) with the retries of results
    that did not converge (:func:`~._point_refinement._retry`) that the
    chunks left out, in place in *out*; return which points a seed gave.

    A point that scores poorly for where it is is retried only if no
    neighbour's seed replaced it: a misindexed start runs out of
    evaluations far from any optimum, and a retry there is as far
    (measured on ``bench_orientations.py far``, 96 px: 9 of 100 points
    spent 46 % of the map's projections, their retries half of it). The
    others are retried before reseeding, so that a seed's result replaces
    a point's own only where it beats the retried one, as it does when
    the chunks retry."""
    scores = out[:, _SCORE]
    valid = todo & np.isfinite(scores)
    poor = poor_points(scores.reshape(nav), valid.reshape(nav)).ravel()
    first = valid & ~poor & ~(out[:, _CONV] > 0)
    _retry_map(d, out, np.flatnonzero(first), pcs, nav[1], options)
    sym = _proper_symmetry(master_pattern)
    reseeded = _reseed(d, out, todo, pcs, nav, options, start, sym)
    later = valid & ~first & ~reseeded & ~(out[:, _CONV] > 0)
    _retry_map(d, out, np.flatnonzero(later), pcs, nav[1], options)
    return reseeded


def _retry_map(d, out, rows, pcs, cols, options) -> None:
    """:func:`~._point_refinement._retry` of the map's points *rows* (flat
    indices), in place in *out* (evaluations added; the DIC RMS measured
    again where a result moved)."""
    if not rows.size:
        return
    patterns = np.asarray(d.vindex[rows // cols, rows % cols].compute())
    q, s, c = out[:, _Q].copy(), out[:, _SCORE].copy(), out[:, _CONV] > 0
    o = options
    out[rows, _EVALS] += _retry(
        patterns, q, s, c, rows, pcs[rows], o["om"], o["arrays"], o["max_step"], o["ops"]
    )  # fmt: skip
    moved = s[rows] != out[rows, _SCORE]
    out[:, _Q], out[:, _SCORE], out[:, _CONV] = q, s, c
    if o["dic_rms"] and moved.any():
        i = rows[moved]
        out[i, _RMS] = _dic_rms(patterns[moved], q[i], pcs[i], o["om"], o["arrays"])


def _refine_block(
    patterns, q, pcs, todo, *, arrays, om, levels, max_step, dic_rms, ops, retry
):  # fmt: skip
    """One dask chunk: patterns (r, c, rows, cols) -> (r, c, width)."""
    r, c = q.shape[:2]
    out = np.full((r * c, _width(ops)), np.nan)
    out[:, _Q] = q.reshape(-1, 4)
    out[:, _EVALS] = 0
    out[:, _CONV] = 0
    out[:, _VARIANT] = 0
    idx = np.flatnonzero(todo.ravel())
    p = patterns.reshape((r * c,) + patterns.shape[2:])
    q, pcs = q.reshape(-1, 4), pcs.reshape(-1, 3)
    # A file's chunks can be large (2200 patterns of 60 px in kikuchipy's
    # h5ebsd): the solver's float64 working copies are bounded by batches
    batch = max(1, CHUNK_BYTES // (4 * p.shape[1] * p.shape[2]))
    for start in range(0, idx.size, batch):
        i = idx[start : start + batch]
        out[i] = _refine_points(
            p[i], q[i], pcs[i], arrays, om, levels, max_step, dic_rms, ops, retry=retry
        )  # fmt: skip
    return out.reshape(r, c, -1)


def _reindex_geomdic(
    signal, xmap, detector, master_pattern, energy, todo, phase_id, mp_phase, *,
    pseudo_symmetry_ops, reseed, dic_rms, show_progressbar, min_significance, refine_kwargs,
):  # fmt: skip
    """:func:`~kikuchipy_geomdic.indexing.reindex.reindex` by :func:`refine_map`."""
    flat = todo.ravel()
    q0 = xmap.rotations.data.reshape(-1, 4)
    out = refine_map(
        signal.data,
        np.where(flat[:, None], q0, [1.0, 0.0, 0.0, 0.0]),
        detector,
        master_pattern,
        energy,
        todo=flat,
        pseudo_symmetry_ops=pseudo_symmetry_ops,
        reseed=reseed,
        dic_rms=dic_rms,
        show_progressbar=show_progressbar,
        min_significance=min_significance,
        **refine_kwargs,
    )
    scores = out["scores"]
    bad = flat & ~np.isfinite(scores)  # NaN patterns give NaN scores
    done = flat & ~bad
    prop = {
        "scores": np.where(done, scores, 0.0),
        "converged": (done & out["converged"]).astype(np.int8),
        "iterations": np.where(done, out["iterations"], 0.0),
        "reseeded": (done & out["reseeded"]).astype(np.int8),
    }
    if dic_rms:
        prop["dic_rms"] = np.where(done, out["dic_rms"], np.nan)
    if pseudo_symmetry_ops is not None:
        prop["variant"] = np.where(done, out["variant"], 0)
        prop["confidence"] = np.where(done, out["confidence"], 0.0)
        prop["cross_variant_margin"] = np.where(done, out["cross_variant_margin"], 0.0)
        prop["variant_significance"] = np.where(done, out["variant_significance"], 0.0)
        for k, v in enumerate(out["variant_scores"].T):
            prop[f"variant_score_{k}"] = np.where(done, v, 0.0)
    return _merge(xmap, out["rotations"], done, bad, prop, phase_id, mp_phase)
