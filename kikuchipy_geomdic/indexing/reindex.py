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

The stages live in private modules: ``_map_refinement`` (the dask graph
over the chunks, this package's solver), ``_point_refinement`` (a batch
of points from their starts and variants), ``_reseed`` (poor points
again from their neighbours), ``_kikuchipy`` (kikuchipy's route),
``_map_output`` (the refined crystal map) and ``_phase_maps`` (a map of
several phases, phase by phase, and the phase decision). The phases
refined are :class:`~kikuchipy_geomdic.indexing.phases_to_refine.PhaseToRefine`
(:func:`~kikuchipy_geomdic.indexing.phases_to_refine.phases_to_refine`).

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry.maps import (
    check_signal_and_detector,
    check_whole_map,
    navigation_shape,
    usable_points,
)
from kikuchipy_geomdic.indexing._kikuchipy import quiet, refine_orientations, stack_signal
from kikuchipy_geomdic.indexing._map_refinement import VARIANT_SIGNIFICANCE, refine_map
from kikuchipy_geomdic.indexing._phase_maps import _decide, _reindex_phases
from kikuchipy_geomdic.indexing.phases_to_refine import (
    check_energy,
    phases_to_refine,
    unrefined_phases,
)

__all__ = [
    "reindex",
    "refine_map",
    "refine_orientations",
    "stack_signal",
    "quiet",
    "VARIANT_SIGNIFICANCE",
]


# --------------------------------------------------------------------- #
# Reindexing
# --------------------------------------------------------------------- #

#: Methods of :func:`reindex`.
METHODS = ("geomdic", "kikuchipy")

#: Options of ``method="geomdic"`` (those of
#: :func:`~kikuchipy_geomdic.indexing.orientation.refine_patterns`).
GEOMDIC_OPTIONS = ("levels", "max_step")


def reindex(
    signal: EBSD,
    xmap: CrystalMap,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern | Sequence[EBSDMasterPattern],
    energy: float,
    *,
    phase: str | int | None = None,
    navigation_mask: np.ndarray | None = None,
    method: str = "geomdic",
    pseudo_symmetry_ops: Rotation | Sequence[Rotation | None] | None = None,
    decide_phase: bool = False,
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
        Lambert master pattern of one of the map's phases, or a list of
        them, one per phase, each matched to the map's phase it is of
        (:func:`~kikuchipy_geomdic.indexing.phases_to_refine.phases_to_refine`).
        Each phase's points are refined with its master pattern; points of
        a phase without one keep theirs (with a warning).
    energy
        Beam energy in kV, one for every phase.
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
        *min_significance*) gets ``converged`` = 0. With a list of master
        patterns, a list of operators, one per master pattern (None where
        a phase has none).
    decide_phase
        With several master patterns and ``method="geomdic"``: refine every
        point against every phase given, from its own orientation and,
        where it scores poorly, from its neighbours' refined in that phase
        (*reseed*), and keep the phase its pattern shows (compared as the
        variants are, :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`).
        Writes ``phase_margin`` (the significance of the call: the kept
        phase's margin over the best other phase's, over its standard
        error from the pattern's noise), ``phase_score_k`` (NCC in the
        k-th phase given) and ``phase_changed`` (1 where the phase is not
        the input's); a call below *min_significance* gets ``converged`` =
        0. It costs one refinement of the map per phase. Default False:
        each point keeps its phase.
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
        Mismatched shapes, a master pattern of another phase (or of no
        phase in a point of the map), two master patterns of one phase,
        different energies, *decide_phase* with one phase, no point to
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
    phases = phases_to_refine(xmap, master_pattern, phase, pseudo_symmetry_ops, energy)
    todo = _points_to_refine(
        signal, xmap, detector, phases, navigation_mask, method, refine_kwargs, decide_phase
    )
    options = dict(
        method=method, reseed=reseed, dic_rms=dic_rms, min_significance=min_significance,
        min_phase_significance=min_significance, refine_kwargs=refine_kwargs,
        show_progressbar=_show_progressbar(show_progressbar),
    )  # fmt: skip
    stage = _decide if decide_phase else _reindex_phases
    # One number as given (kikuchipy's route takes it as it is), a list as one
    energy = check_energy(energy) if np.ndim(energy) else energy
    return stage(signal, xmap, detector, phases, energy, todo, options)


def _points_to_refine(
    signal, xmap, detector, phases, navigation_mask, method, refine_kwargs, decide_phase=False
) -> np.ndarray:
    """Check :func:`reindex`'s inputs (*refine_kwargs* loses ``compute``) and
    return the points to refine (the map's shape): those of the *phases*."""
    if decide_phase and len(phases) < 2:
        raise ValueError(
            "decide_phase=True needs master patterns of two phases or more to decide between; "
            f"one was given ({phases[0].name!r})"
        )
    if decide_phase and method != "geomdic":
        raise ValueError("decide_phase=True needs method='geomdic'")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, not {method!r}")
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
    todo = np.zeros(xmap.shape, dtype=bool)
    for p in phases:
        todo |= usable_points(xmap, p.phase_id)
    left = unrefined_phases(xmap, phases)
    if len(phases) > 1 and left:
        listed = ", ".join(f"{name!r} ({n} points)" for name, n in left.items())
        warnings.warn(
            f"No master pattern of the phases {listed}: their points keep their orientations",
            UserWarning,
            stacklevel=3,
        )
    if navigation_mask is not None:
        navigation_mask = np.asarray(navigation_mask, dtype=bool)
        if navigation_mask.shape != nav:
            raise ValueError(f"navigation_mask has shape {navigation_mask.shape}, the map {nav}")
        todo &= ~navigation_mask
    if not todo.any():
        raise ValueError("No point of the map can be refined (none indexed with the phase)")
    return todo


def _show_progressbar(show_progressbar: bool | None) -> bool:
    """*show_progressbar*, or HyperSpy's preference if None."""
    if show_progressbar is None:
        import hyperspy.api as hs

        return bool(hs.preferences.General.show_progressbar)
    return bool(show_progressbar)
