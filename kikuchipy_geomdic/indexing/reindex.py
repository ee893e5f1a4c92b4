"""Whole-map orientation refinement with a calibrated detector.

After the geometry is calibrated on a few hundred points, every
orientation of the map is refined with the calibrated detector: the
expensive part, one optimisation per pattern. :func:`reindex` is a thin
wrapper over kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation`
that adds what a whole real map needs:

- the map's phase is matched to the master pattern's by the package's
  one rule (:mod:`kikuchipy_geomdic.patterns.phases`: orix reads an ``.ang``
  file's phase with its proper point group only, e.g. 432 for silicon,
  which kikuchipy would refuse against an m-3m master pattern), and a
  master pattern of another phase is refused with a clear message;
- points that cannot be refined (not indexed, zero or NaN rotations,
  another phase, masked out) are excluded and kept as they were, points
  whose pattern holds NaN come back as not indexed;
- the result has the input map's shape, coordinates and phases, so it
  writes straight to ``.ang`` or orix h5.

Scale
-----
Nothing here touches the pattern data: kikuchipy builds a dask graph over
the (possibly lazy) signal, and dask computes it chunk by chunk, so memory
stays bounded by the chunk size. The graph runs on whatever dask scheduler
is active: the default thread pool, or a ``dask.distributed`` cluster when
a :class:`~distributed.Client` exists (see ``docs/cluster.md``). There is
no scheduler or process pool of our own.
"""

from __future__ import annotations

import contextlib
import io
import warnings
from typing import Any

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import copy_detector
from kikuchipy_geomdic.geometry.maps import (
    check_signal_and_detector,
    check_whole_map,
    navigation_shape,
)
from kikuchipy_geomdic.indexing.orientation import (
    MAX_STEP,
    MasterPatternArrays,
    coarse_arrays,
    compare_variants,
    detector_matrix,
    detector_pcs,
    master_pattern_arrays,
    neighbour_seeds,
    poor_points,
    project_arrays,
    pyramid_levels,
    refine_arrays,
)
from kikuchipy_geomdic.indexing.variants import _qmul

# Defined in kikuchipy_geomdic.patterns.phases; importable from here for existing code
from kikuchipy_geomdic.patterns.phases import (  # noqa: F401
    check_phase,
    map_with_phase,
    match_phase,
    phases_match,
    replace_phase,
)
from kikuchipy_geomdic.patterns.preprocessing import bin_pattern

__all__ = [
    "usable_points",
    "reindex",
    "refine_map",
    "refine_orientations",
    "quiet",
    "VARIANT_SIGNIFICANCE",
]


def usable_points(xmap: CrystalMap, phase_id: int | None = None) -> np.ndarray:
    """Return which map points have a usable orientation.

    Parameters
    ----------
    xmap
        Crystal map; all its points must be in the data.
    phase_id
        Only points of this phase are usable. Default: any indexed phase.

    Returns
    -------
    usable
        Boolean array of ``xmap.shape``: indexed (phase id >= 0, or the
        given phase) with a finite rotation of norm near 1 (zero
        quaternions, which some files use for non-indexed points, and
        NaN rotations are not usable).

    Examples
    --------
    >>> import numpy as np
    >>> from orix.crystal_map import CrystalMap
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.indexing.reindex import usable_points
    >>> q = np.array([[1, 0, 0, 0], [0, 0, 0, 0], [np.nan] * 4, [1, 0, 0, 0]])
    >>> xmap = CrystalMap(Rotation(q), phase_id=np.array([0, 0, 0, -1]))
    >>> usable_points(xmap).tolist()
    [True, False, False, False]
    """
    check_whole_map(xmap)
    q = xmap.rotations.data.reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(q).all(axis=1) & (np.abs(np.linalg.norm(q, axis=1) - 1) < 1e-3)
    pid = xmap.phase_id
    ok &= pid >= 0 if phase_id is None else pid == phase_id
    return ok.reshape(xmap.shape)


# --------------------------------------------------------------------- #
# Reindexing
# --------------------------------------------------------------------- #

#: Methods of :func:`reindex`.
METHODS = ("geomdic", "kikuchipy")

#: Options of ``method="geomdic"`` (those of
#: :func:`~kikuchipy_geomdic.indexing.orientation.refine_patterns`).
GEOMDIC_OPTIONS = ("levels", "max_step")

#: Pattern bytes (as float32) per dask chunk when the signal is in memory,
#: and per batch the solver takes from a chunk: large enough that the
#: Python overhead is small (290 patterns of 120 px), small enough that
#: the solver's working copies stay near 100 MB per thread (measured: 384
#: MB above the map for chunks of 256 patterns of 240 px on two threads).
CHUNK_BYTES = 16 * 2**20

# Columns of the per-point output of a chunk; then one NCC per candidate
_Q, _SCORE, _EVALS, _CONV, _RMS, _VARIANT, _CONF, _MARGIN = slice(0, 4), 4, 5, 6, 7, 8, 9, 10
_SIG, _NCC = 11, 12

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


def _width(ops) -> int:
    return _NCC + 1 + (0 if ops is None else len(ops))


def reindex(
    signal: EBSD,
    xmap: CrystalMap,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern,
    energy: float,
    *,
    phase: str | int | None = None,
    navigation_mask: np.ndarray | None = None,
    method: str = "geomdic",
    pseudo_symmetry_ops: Rotation | None = None,
    reseed: bool = True,
    dic_rms: bool = False,
    min_significance: float = VARIANT_SIGNIFICANCE,
    show_progressbar: bool | None = None,
    **refine_kwargs: Any,
) -> CrystalMap:
    """Refine every orientation of a map with a (calibrated) detector.

    Parameters
    ----------
    signal
        ``EBSD`` or ``LazyEBSD`` map. A lazy signal is not loaded: it is
        read and refined chunk by chunk.
    xmap
        Starting orientations of the map's shape (e.g. Hough indexing).
    detector
        Detector with one PC or one per map point, e.g. ``res.detector``
        from :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`.
    master_pattern
        Lambert master pattern of one of the map's phases.
    energy
        Beam energy in kV.
    phase
        Name or id of the map's phase to refine; default the map's only
        indexed phase. It must match the master pattern's phase
        (:func:`~kikuchipy_geomdic.patterns.phases.check_phase`).
    navigation_mask
        Boolean array of the map's shape, ``True`` for points *not* to
        refine (kikuchipy's convention).
    method
        "geomdic" (default): this package's Gauss-Newton solver on the
        pattern intensities, coarse to fine
        (:func:`~kikuchipy_geomdic.indexing.orientation.refine_patterns`); it
        reaches kikuchipy's optimum with far fewer projections.
        "kikuchipy": kikuchipy's
        :meth:`~kikuchipy.signals.EBSD.refine_orientation`.
    pseudo_symmetry_ops
        Operators of a material's pseudo-symmetric variants (crystal
        frame, acting as ``op * rotation``, e.g.
        ``variant_operators()[1:]`` for BaTiO3). Every point is
        refined from its start and from each variant of it, and the
        variant its pattern shows is kept (with ``method="geomdic"``:
        :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`, with a
        variant-sensitive confidence index and the cross-variant margin;
        with ``method="kikuchipy"``: kikuchipy's best NCC).
        A variant call within the pattern's noise (significance below
        *min_significance*) gets ``converged`` = 0.
    reseed
        ``method="geomdic"`` only: refine the points that score poorly
        for where they are (:func:`~kikuchipy_geomdic.indexing.orientation.poor_points`)
        again from each of their neighbours' orientations, keeping the
        best. Points that stay poor get ``converged`` = 0.
    dic_rms
        ``method="geomdic"`` only: measure the DIC displacement between
        each pattern and its simulation at the refined orientation (a
        second opinion beside the NCC for a user who inspects suspicious
        points; it doubles the time: measured, 12 ms per 120 px pattern
        against 6 ms for the refinement).
    min_significance
        ``method="geomdic"`` with *pseudo_symmetry_ops*: a point whose
        variant call has a smaller significance (its cross-variant margin
        over the margin's standard error from the pattern's own noise: a
        z-score, :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`)
        gets ``converged`` = 0: its pattern does not decide between the
        kept variant and a rival (at low dose mostly a polarity, +z
        against -z). Default :data:`VARIANT_SIGNIFICANCE` (2.5). 0 flags
        only calls whose margin is negative, never in practice.
    show_progressbar
        Show a progress bar (dask's, or kikuchipy's summary and bar with
        ``method="kikuchipy"``). Default: HyperSpy's preference.
    **refine_kwargs
        ``method="geomdic"``: ``levels`` and ``max_step`` of
        :func:`~kikuchipy_geomdic.indexing.orientation.refine_patterns`.
        ``method="kikuchipy"``: passed to
        :meth:`~kikuchipy.signals.EBSD.refine_orientation` (``method``
        there is given as ``kikuchipy_method``), e.g. ``method_kwargs``,
        ``trust_region``, ``signal_mask``, ``pseudo_symmetry_ops``,
        ``rechunk``, ``chunk_kwargs``.

    Returns
    -------
    xmap_refined
        :class:`~orix.crystal_map.CrystalMap` of the input's shape,
        coordinates and phases, with the master pattern's phase in place of
        the matched one. Refined points carry their refined orientation;
        points not refined keep theirs. Properties: the input's, plus
        ``scores`` (NCC; 0 where not refined), ``refined`` (1 or 0) and

        - "geomdic": ``converged`` (1, or 0 where the solver did not
          converge, the point still scores poorly for where it is, or,
          with *pseudo_symmetry_ops*, its variant call is within the
          noise: do not trust it), ``iterations`` (pattern projections, in
          full-resolution equivalents), ``reseeded`` (1 where a
          neighbour's orientation gave the kept result) and, with
          *dic_rms*, ``dic_rms`` (RMS DIC displacement in pixels); with
          *pseudo_symmetry_ops*, ``variant`` (0: as given, k: operator
          k - 1 applied), ``confidence`` (the kept variant's
          variant-sensitive confidence index), ``cross_variant_margin``,
          ``variant_significance`` (the call's z-score; ``converged`` is 0
          below *min_significance*), ``isolated_variant`` (1 where a
          trusted point's domain is shared by none of its trusted
          neighbours, two or more: ``converged`` set to 0; a detector
          angle error biases a few polarity calls beyond their noise, and
          such errors are scattered points),
          ``variant_score_k`` (NCC of each candidate) and ``domain``
          (the variant in the parent crystal's frame, -1 where not
          labelled: :func:`~kikuchipy_geomdic.indexing.variants.domain_labels`,
          the parent chosen from the refined, converged points);
        - "kikuchipy": ``num_evals`` and, with ``pseudo_symmetry_ops``,
          ``pseudo_symmetry_index`` and ``domain``.

        Points with unusable rotations or whose pattern holds NaN are not
        indexed (phase -1). The inputs are not modified.

    Raises
    ------
    ValueError
        Mismatched shapes, a master pattern of another phase, no point to
        refine, an unknown method or option, or ``compute=False`` (use
        kikuchipy directly for a lazy result).

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.indexing.reindex import reindex
    >>> sm = synthetic.synthetic_map("Si", (3, 4), shape=(40, 40), seed=0)
    >>> xmap = reindex(
    ...     sm.signal, sm.start_xmap, sm.detector, sm.master_pattern, 20,
    ...     show_progressbar=False,
    ... )
    >>> xmap.shape, bool(xmap.scores.min() > 0.99), int(xmap.converged.sum())
    ((3, 4), True, 12)
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, not {method!r}")
    show_progressbar = _show_progressbar(show_progressbar)
    if method == "geomdic":
        unknown = sorted(set(refine_kwargs) - set(GEOMDIC_OPTIONS))
        if unknown:
            raise ValueError(
                f"Options {unknown} are not options of method='geomdic' "
                f"({', '.join(GEOMDIC_OPTIONS)}); kikuchipy's options need method='kikuchipy'"
            )
    elif refine_kwargs.get("compute", True) is not True:
        raise ValueError("reindex() computes; call signal.refine_orientation() for a lazy result")
    refine_kwargs.pop("compute", None)
    check_signal_and_detector(signal, detector)
    check_whole_map(xmap)
    n_points = int(np.prod(navigation_shape(signal)))  # 1D or 2D maps only
    # kikuchipy compares the crystal map's shape with this one exactly
    nav = tuple(signal.axes_manager.navigation_shape[::-1])
    if tuple(xmap.shape) != nav:
        raise ValueError(
            f"The crystal map's shape {tuple(xmap.shape)} differs from the patterns' "
            f"navigation shape {nav}"
        )
    sig = tuple(signal.axes_manager.signal_shape[::-1])
    if tuple(detector.shape) != sig:
        raise ValueError(f"The detector's shape {detector.shape} differs from the patterns' {sig}")
    if detector.navigation_size not in (1, n_points):
        raise ValueError(
            f"The detector has {detector.navigation_size} PCs, neither one nor one per "
            f"map point of {nav}"
        )
    phase_id = check_phase(xmap, master_pattern, phase)

    todo = usable_points(xmap, phase_id)
    if navigation_mask is not None:
        navigation_mask = np.asarray(navigation_mask, dtype=bool)
        if navigation_mask.shape != nav:
            raise ValueError(f"navigation_mask has shape {navigation_mask.shape}, the map {nav}")
        todo &= ~navigation_mask
    if not todo.any():
        raise ValueError("No point of the map can be refined (none indexed with the phase)")
    mp_phase = master_pattern.phase.deepcopy()
    if method == "kikuchipy":
        if pseudo_symmetry_ops is not None:
            refine_kwargs["pseudo_symmetry_ops"] = pseudo_symmetry_ops
        out = _reindex_kikuchipy(
            signal, xmap, detector, master_pattern, energy, todo, phase_id, mp_phase,
            show_progressbar, refine_kwargs,
        )  # fmt: skip
        return _with_domain(out, pseudo_symmetry_ops, phase_id)

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
    merged = _merge(xmap, out["rotations"], done, bad, prop, phase_id, mp_phase)
    merged = _with_domain(merged, pseudo_symmetry_ops, phase_id)
    if pseudo_symmetry_ops is not None and "domain" in merged.prop:
        _flag_isolated(merged)
    return merged


def _flag_isolated(xmap: CrystalMap) -> None:
    """Give ``converged`` = 0 to every trusted point whose domain none of
    its trusted neighbours (8-connected, at least two of them) shares, in
    place, and add property ``isolated_variant`` (1 there).

    A detector angle error biases polarity calls beyond their noise
    (measured: two +z points of a 13 x 13 map at 30 counts per pixel
    called -z with significances 3.4 and 3.6, at an azimuthal angle 1 deg
    off); such errors are scattered points, while domains span several
    steps. A true domain one step wide is flagged too: it is not declared
    wrong, only not trusted."""
    shape = xmap.shape if len(xmap.shape) == 2 else (1, xmap.size)
    dom = np.asarray(xmap.prop["domain"]).reshape(shape)
    conv = np.asarray(xmap.prop["converged"]).reshape(shape).astype(bool)
    trusted = conv & (dom >= 0)
    n_trusted = np.zeros(shape, dtype=int)
    n_same = np.zeros(shape, dtype=int)
    rows, cols = shape
    pad_t = np.pad(trusted, 1)
    pad_d = np.pad(dom, 1, constant_values=-1)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == dc == 0:
                continue
            t = pad_t[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
            d = pad_d[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
            n_trusted += t
            n_same += t & (d == dom)
    isolated = (trusted & (n_trusted >= ISOLATED_NEIGHBOURS) & (n_same == 0)).ravel()
    xmap.prop["converged"] = np.where(isolated, 0, xmap.prop["converged"]).astype(np.int8)
    xmap.prop["isolated_variant"] = isolated.astype(np.int8)


#: Trusted neighbours a trusted point needs, none of them in its domain,
#: for :func:`reindex` to flag it as an isolated variant call
ISOLATED_NEIGHBOURS = 2


def _with_domain(xmap: CrystalMap, ops, phase_id: int) -> CrystalMap:
    """Add property ``domain`` (:func:`~kikuchipy_geomdic.indexing.variants.domain_labels`,
    the parent chosen from the refined, converged points) to a fresh map."""
    if ops is None:
        return xmap
    from kikuchipy_geomdic.indexing.variants import domain_labels

    trusted = xmap.prop["refined"].astype(bool) & (xmap.prop.get("converged", 1) != 0)
    try:
        lab = domain_labels(xmap, ops, phase=phase_id, points=trusted if trusted.any() else None)
    except ValueError as e:  # operators that do not make a group with the crystal's
        warnings.warn(f"No domain labels: {e}", UserWarning, stacklevel=3)
        return xmap
    xmap.prop["domain"] = lab.label.astype(np.int64)
    return xmap


def _show_progressbar(show_progressbar: bool | None) -> bool:
    """*show_progressbar*, or HyperSpy's preference if None."""
    if show_progressbar is None:
        import hyperspy.api as hs

        return bool(hs.preferences.General.show_progressbar)
    return bool(show_progressbar)


def _reindex_kikuchipy(
    signal, xmap, detector, master_pattern, energy, todo, phase_id, mp_phase, show, kwargs
):
    """:func:`reindex` by kikuchipy's ``refine_orientation``."""
    nav = tuple(signal.axes_manager.navigation_shape[::-1])
    kwargs = dict(kwargs)
    if "kikuchipy_method" in kwargs:
        kwargs["method"] = kwargs.pop("kikuchipy_method")
    # What kikuchipy sees: one phase (the master pattern's), the points to
    # refine indexed, every other point not indexed
    q_in = xmap.rotations.data.reshape(-1, 4)
    flat = todo.ravel()
    q = np.tile([1.0, 0.0, 0.0, 0.0], (flat.size, 1))
    q[flat] = q_in[flat]
    kx = CrystalMap(
        rotations=Rotation(q),
        phase_id=np.where(flat, 0, -1),
        x=xmap.x,
        y=xmap.y,
        phase_list=PhaseList({0: mp_phase}),
        scan_unit=xmap.scan_unit,
    )
    det = detector.deepcopy()
    if det.navigation_size > 1 and det.navigation_shape != nav:
        det.pc = det.pc.reshape(nav + (3,))
    with contextlib.nullcontext() if show else quiet():
        ref = signal.refine_orientation(kx, det, master_pattern, energy, **kwargs)

    n = flat.size
    done = np.zeros(n, dtype=bool)
    done[ref.id] = True
    done &= flat
    scores = np.zeros(n)
    scores[ref.id] = ref.prop["scores"]
    bad = done & ~np.isfinite(scores)
    done &= ~bad
    scores[~done] = 0.0
    num_evals = np.zeros(n, dtype=np.int64)
    num_evals[ref.id] = ref.prop["num_evals"]
    q_out = xmap.rotations.data.reshape(-1, 4).copy()
    q_out[done] = ref.rotations.data.reshape(-1, 4)[np.searchsorted(ref.id, np.flatnonzero(done))]
    prop = {"scores": scores, "num_evals": num_evals}
    if "pseudo_symmetry_index" in ref.prop:
        psi = np.zeros(n, dtype=np.int64)
        psi[ref.id] = ref.prop["pseudo_symmetry_index"]
        prop["pseudo_symmetry_index"] = psi
    return _merge(xmap, q_out, done, bad, prop, phase_id, mp_phase)


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
    >>> import numpy as np
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.indexing.reindex import refine_map
    >>> sm = synthetic.synthetic_map("Si", (2, 3), shape=(40, 40), seed=0)
    >>> q = sm.start_xmap.rotations.data.reshape(-1, 4)
    >>> out = refine_map(sm.signal.data, q, sm.detector, sm.master_pattern, 20)
    >>> out["rotations"].shape, bool(out["converged"].all())
    ((6, 4), True)
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
        d = da.from_array(
            np.asarray(data).reshape((rows, cols) + shape),
            chunks=_chunks(rows, cols, 4 * shape[0] * shape[1]) + (-1, -1),
        )
    chunks = d.chunks[:2]
    qd = da.from_array(q.reshape(rows, cols, 4), chunks=chunks + ((4,),))
    pd = da.from_array(pcs.reshape(rows, cols, 3), chunks=chunks + ((3,),))
    td = da.from_array(todo.reshape(rows, cols), chunks=chunks)
    ops = None if pseudo_symmetry_ops is None else _operators(pseudo_symmetry_ops)
    width = _width(ops)
    options = dict(
        arrays=arrays, om=om, levels=levels, max_step=max_step, dic_rms=dic_rms, ops=ops
    )
    graph = da.blockwise(
        _refine_block, "ijk",
        d, "ijrc", qd, "ijq", pd, "ijp", td, "ij",
        new_axes={"k": width}, concatenate=True, dtype=np.float64, **options,
    )  # fmt: skip
    with _progress(show_progressbar):
        out = np.asarray(dask.compute(graph)[0]).reshape(n, width)

    reseeded = np.zeros(n, dtype=bool)
    if reseed:
        sym = _proper_symmetry(master_pattern)
        reseeded = _reseed(d, out, todo, pcs, (rows, cols), options, q, sym)
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


def _threads() -> int:
    """Threads of dask's local pool (its ``num_workers`` setting, else the
    CPU count)."""
    import os

    import dask

    n = dask.config.get("num_workers", None)
    return int(n) if n else (os.cpu_count() or 1)


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


def _refine_points(patterns, q, pcs, arrays, om, levels, max_step, dic_rms, ops) -> np.ndarray:
    """The output rows (k, width) of k patterns refined from starts *q*:
    with pseudo-symmetry *ops*, from each variant of the start too, the
    variant kept by :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`.

    With *ops*, in two rounds. First every variant of the start runs the
    coarse stages from its own start. A start a few degrees off (a user's,
    refined in the wrong variant at a wrong geometry) leaves some of them
    in a local optimum, and comparing those with one that converged would
    choose by convergence, not by the pattern. So the best of them by
    full-resolution NCC (variants differ in it only in the third decimal
    where they are alike; a missed basin is far below) gives every
    variant a start of its own at the same place,
    ``op_j * op_b^-1 * q_b``, from which each runs the full-resolution
    stage, and the six are compared on equal terms. Candidate j stays the
    start's variant j (``op_j * q``)."""
    k = patterns.shape[0]
    rows = np.arange(k)
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
        first = coarse_arrays(
            np.repeat(patterns, m, axis=0), candidates.reshape(-1, 4), np.repeat(pcs, m, axis=0),
            om, arrays, levels, max_step,
        )  # fmt: skip
        cq = first.rotations.data.reshape(k, m, 4)
        c_ncc = first.scores.reshape(k, m)
        best = np.argmax(np.where(np.isfinite(c_ncc), c_ncc, -np.inf), axis=1)
        # The best, taken back to the start's variant, then each variant of it
        base = _qmul(ops_all[best] * [1, -1, -1, -1], cq[rows, best])
        target = _qmul(ops_all[None, :, :], base[:, None, :])
        res = refine_arrays(
            np.repeat(patterns, m, axis=0), target.reshape(-1, 4), np.repeat(pcs, m, axis=0),
            om, arrays, (1,), max_step,
        )  # fmt: skip
        rq = res.rotations.data.reshape(k, m, 4).copy()
        scores = res.scores.reshape(k, m).copy()
        conv = res.converged.reshape(k, m).copy()
        evals = (first.evaluations + res.evaluations).reshape(k, m).sum(axis=1)
        cmp = compare_variants(patterns, rq, pcs, om, arrays)
        kept = cmp.variant
        out = np.full((k, _width(ops)), np.nan)
        out[:, _CONF], out[:, _MARGIN], out[:, _NCC:] = cmp.confidence, cmp.margin, cmp.ncc
        out[:, _SIG] = cmp.significance
    q_kept, s_kept, c_kept = rq[rows, kept], scores[rows, kept], conv[rows, kept]
    # A fine stage entered from a coarse result can run out of evaluations
    # dithering between the master pattern's cells (measured: 16 % of
    # candidates refined from the truth at dose 150, 4 % at full
    # resolution alone): the kept one gets one more fine stage from where it is
    again = np.flatnonzero(~c_kept & np.isfinite(s_kept))
    if again.size:
        res3 = refine_arrays(
            patterns[again], q_kept[again], pcs[again], om, arrays, (1,), max_step
        )
        better = res3.scores >= s_kept[again]
        i = again[better]
        q_kept[i], s_kept[i] = res3.rotations.data[better], res3.scores[better]
        c_kept[i] = res3.converged[better]
        evals[again] += res3.evaluations
    out[:, _Q] = q_kept
    out[:, _SCORE] = s_kept
    out[:, _EVALS] = evals
    out[:, _CONV] = c_kept
    out[:, _VARIANT] = kept
    if dic_rms:
        out[:, _RMS] = _dic_rms(patterns, out[:, _Q], pcs, om, arrays)
    return out


def _refine_block(patterns, q, pcs, todo, *, arrays, om, levels, max_step, dic_rms, ops):
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
            p[i], q[i], pcs[i], arrays, om, levels, max_step, dic_rms, ops
        )  # fmt: skip
    return out.reshape(r, c, -1)


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


def _proper_symmetry(master_pattern) -> np.ndarray:
    """Quaternions (S, 4) of the proper point group of the master pattern's
    phase (the identity alone for bare arrays)."""
    phase = getattr(master_pattern, "phase", None)
    if phase is None:
        return np.array([[1.0, 0.0, 0.0, 0.0]])
    pg = phase.point_group
    return np.asarray(Rotation(pg.proper_subgroup).flatten().data, dtype=np.float64)


def _equivalents(ops, sym) -> np.ndarray:
    """Quaternions (E, 4) of every ``s * op`` (s a symmetry, op the identity
    or a pseudo-symmetry operator): what makes two orientations the same
    candidate set."""
    ident = np.array([[1.0, 0.0, 0.0, 0.0]])
    ops_all = ident if ops is None else np.concatenate([ident, ops])
    return _qmul(sym[:, None, :], ops_all[None, :, :]).reshape(-1, 4)


def _distinct(seeds: np.ndarray, equivalents: np.ndarray, min_angle: float = 1.0) -> np.ndarray:
    """The seeds (k, 4) whose candidate sets differ: a seed that is an
    equivalent (symmetry times variant) of an earlier one within
    *min_angle* degrees adds nothing, as its variants are refined anyway."""
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
#: neighbours in the next (runs of misindexed points).
RESEED_PASSES = 4


def _reseed(d, out, todo, pcs, nav, options, start, sym) -> np.ndarray:
    """Refine poor points again from their neighbours' orientations,
    in place in *out*; return which points a neighbour's seed improved.

    A seed's result replaces the point's own only where it scores better
    on the point's own pattern, so reseeding never lowers a score. Seeds
    are the neighbours' refined orientations as they are (each refined
    with all its variants when there are operators), never averages;
    seeds that are symmetry or variant equivalents of one another are
    refined once. A replaced point's ``variant`` is relabelled relative to
    its own *start*."""
    rows, cols = nav
    ops = options["ops"]
    equivalents = _equivalents(ops, sym)
    reseeded = np.zeros(rows * cols, dtype=bool)
    valid = todo.reshape(nav) & np.isfinite(out[:, _SCORE]).reshape(nav)
    tried: dict[int, list[np.ndarray]] = {}
    for _ in range(RESEED_PASSES):
        poor = poor_points(out[:, _SCORE].reshape(nav), valid)
        if not poor.any():
            break
        q_map = out[:, _Q].reshape(rows, cols, 4)
        points, seeds = [], []
        for p in np.argwhere(poor):
            f = int(p[0] * cols + p[1])
            s = _distinct(neighbour_seeds(q_map, tuple(p), valid & ~poor), equivalents)
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
        trial = _refine_points(patterns[idx], np.concatenate(seeds), pcs[flat[idx]], **options)
        changed = False
        for i, f in enumerate(flat):
            mine = trial[idx == i]
            best = mine[np.nanargmax(mine[:, _SCORE])]
            spent = out[f, _EVALS] + mine[:, _EVALS].sum()
            if best[_SCORE] > out[f, _SCORE]:
                out[f] = best
                if ops is not None:
                    out[f, _VARIANT] = _relabel(best[None, _Q], start[None, f], ops, sym)[0]
                reseeded[f] = changed = True
            out[f, _EVALS] = spent
        if not changed:
            break
    return reseeded


def _seen(q, old, equivalents, min_angle: float = 1.0) -> bool:
    cos_half = np.cos(np.deg2rad(min_angle) / 2)
    return bool((np.abs(_qmul(equivalents, q[None, :]) @ old.T) >= cos_half).any())


def refine_orientations(
    patterns: np.ndarray,
    rotations: Rotation,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern,
    energy: float,
    phase,
    binning: int = 1,
    **refine_kwargs: Any,
) -> CrystalMap:
    """Refine the orientations of a stack of patterns, quietly.

    A stack (the calibration points of a map, say) is refined with
    kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation` as a
    1D map, without kikuchipy's summary and progress bar.

    Parameters
    ----------
    patterns
        Patterns (N, rows, columns).
    rotations
        Starting orientations (N,).
    detector
        Detector of the full-resolution patterns with one PC or N PCs.
    master_pattern, energy
        Lambert master pattern of *phase* and beam energy in kV.
    phase
        orix :class:`~orix.crystal_map.Phase` of the patterns.
    binning
        Refine on patterns binned by this factor, which must divide the
        pattern shape (the PC fractions stay the same).
    **refine_kwargs
        Passed to :meth:`~kikuchipy.signals.EBSD.refine_orientation`.

    Returns
    -------
    xmap
        1D :class:`~orix.crystal_map.CrystalMap` of the N refined
        orientations with their ``scores``.

    Examples
    --------
    The four patterns of a 2 x 2 synthetic map, refined at their true
    PCs:

    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.indexing.reindex import refine_orientations
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(40, 40), seed=0)
    >>> patterns, mp = sm.signal.data.reshape(4, 40, 40), sm.master_pattern
    >>> det = sm.geometry.detector([[0, 0], [0, 1], [1, 0], [1, 1]])
    >>> xmap = refine_orientations(patterns, sm.start_xmap.rotations, det, mp, 20, mp.phase)
    >>> len(xmap.scores), bool(xmap.scores.min() > 0.99)
    (4, True)
    """
    patterns = np.asarray(patterns)
    if binning > 1:
        # Averaged in the patterns' own floating type, as kikuchipy would
        patterns = bin_pattern(patterns, binning, np.result_type(patterns.dtype, np.float32))
        detector = copy_detector(
            detector, shape=patterns.shape[1:], binning=detector.binning * binning
        )
    signal, xmap = stack_signal(patterns, rotations, phase)
    with quiet():
        return signal.refine_orientation(xmap, detector, master_pattern, energy, **refine_kwargs)


def stack_signal(patterns: np.ndarray, rotations: Rotation, phase) -> tuple[EBSD, CrystalMap]:
    """Return a stack of patterns as a 1D map and a crystal map of it.

    Parameters
    ----------
    patterns
        Patterns (N, rows, columns).
    rotations
        Orientations (N,).
    phase
        orix :class:`~orix.crystal_map.Phase` of every point.

    Returns
    -------
    signal
        :class:`~kikuchipy.signals.EBSD` with one navigation axis "x".
    xmap
        :class:`~orix.crystal_map.CrystalMap` with points at x = 0, 1, ...
    """
    n = len(patterns)
    signal = EBSD(patterns)
    # kikuchipy matches the crystal map's x coordinates to this axis
    signal.axes_manager.navigation_axes[0].name = "x"
    xmap = CrystalMap(
        rotations=rotations, x=np.arange(n, dtype=float), phase_list=PhaseList(phase)
    )
    return signal, xmap


def quiet():
    """Return a context in which kikuchipy's summaries and progress bars,
    which go to stdout, are not shown.

    Examples
    --------
    >>> from kikuchipy_geomdic.indexing.reindex import quiet
    >>> with quiet():
    ...     print("not shown")
    """
    return contextlib.redirect_stdout(io.StringIO())


def _merge(xmap, q_out, done, bad, prop, phase_id, mp_phase) -> CrystalMap:
    """The refined points (*done*) of *q_out* put back into a copy of
    *xmap* with properties *prop*; *bad* points (NaN patterns) are not
    indexed."""
    q = xmap.rotations.data.reshape(-1, 4).copy()
    q[done] = np.asarray(q_out).reshape(-1, 4)[done]
    pid = xmap.phase_id.copy()
    # Points with an invalid rotation (any phase) or a NaN pattern are not
    # indexed; masked-out points and other phases keep theirs
    with np.errstate(invalid="ignore"):
        invalid_rot = ~(
            np.isfinite(q).all(axis=1) & (np.abs(np.linalg.norm(q, axis=1) - 1) < 1e-3)
        )
    lost = bad | invalid_rot
    pid[lost] = -1
    q[lost] = [1.0, 0.0, 0.0, 0.0]
    props = {k: np.asarray(v).copy() for k, v in xmap.prop.items()}
    props.update(prop)
    props["refined"] = done.astype(np.int8)
    return map_with_phase(xmap, Rotation(q), pid, props, phase_id, mp_phase)
