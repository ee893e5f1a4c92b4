"""Whole-map orientation refinement with a calibrated detector.

After the geometry is calibrated on a few hundred points, every
orientation of the map is refined with the calibrated detector: the
expensive part, one optimisation per pattern. :func:`reindex` is a thin
wrapper over kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation`
that adds what a whole real map needs:

- the map's phase is matched to the master pattern's by the package's
  one rule (:mod:`kikuchipy_geomdic.phases`: orix reads an ``.ang``
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
from typing import Any

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.displacement import bin_pattern
from kikuchipy_geomdic.geometry import copy_detector
from kikuchipy_geomdic.maps import check_signal_and_detector, check_whole_map, navigation_shape

# Defined in kikuchipy_geomdic.phases; importable from here for existing code
from kikuchipy_geomdic.phases import (  # noqa: F401
    check_phase,
    map_with_phase,
    match_phase,
    phases_match,
    replace_phase,
)

__all__ = ["usable_points", "reindex", "refine_orientations"]


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
    >>> from kikuchipy_geomdic.reindex import usable_points
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


def reindex(
    signal: EBSD,
    xmap: CrystalMap,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern,
    energy: float,
    *,
    phase: str | int | None = None,
    navigation_mask: np.ndarray | None = None,
    show_progressbar: bool | None = None,
    **refine_kwargs: Any,
) -> CrystalMap:
    """Refine every orientation of a map with a (calibrated) detector.

    Parameters
    ----------
    signal
        ``EBSD`` or ``LazyEBSD`` map. A lazy signal is not loaded: kikuchipy
        reads and refines it chunk by chunk.
    xmap
        Starting orientations of the map's shape (e.g. Hough indexing).
    detector
        Detector with one PC or one per map point, e.g. ``res.detector``
        from :func:`~kikuchipy_geomdic.refinement.refine_geometry_dic`.
    master_pattern
        Lambert master pattern of one of the map's phases.
    energy
        Beam energy in kV.
    phase
        Name or id of the map's phase to refine; default the map's only
        indexed phase. It must match the master pattern's phase
        (:func:`~kikuchipy_geomdic.phases.check_phase`).
    navigation_mask
        Boolean array of the map's shape, ``True`` for points *not* to
        refine (kikuchipy's convention).
    show_progressbar
        Show kikuchipy's summary and dask progress bar (on stdout).
        Default: on.
    **refine_kwargs
        Passed to :meth:`~kikuchipy.signals.EBSD.refine_orientation`:
        ``method``, ``method_kwargs``, ``trust_region``, ``signal_mask``,
        ``pseudo_symmetry_ops``, ``rechunk``, ``chunk_kwargs``, ...

    Returns
    -------
    xmap_refined
        :class:`~orix.crystal_map.CrystalMap` of the input's shape,
        coordinates and phases, with the master pattern's phase in place of
        the matched one. Refined points carry their refined orientation;
        points not refined keep theirs. Properties: the input's, plus
        ``scores`` (NCC; 0 where not refined), ``num_evals``, ``refined``
        (1 or 0) and, with ``pseudo_symmetry_ops``,
        ``pseudo_symmetry_index``. Points with unusable rotations or whose
        pattern holds NaN are not indexed (phase -1). The inputs are not
        modified.

    Raises
    ------
    ValueError
        Mismatched shapes, a master pattern of another phase, no point to
        refine, or ``compute=False`` (use kikuchipy directly for a lazy
        result).

    Examples
    --------
    >>> from kikuchipy_geomdic import synthetic
    >>> from kikuchipy_geomdic.reindex import reindex
    >>> sm = synthetic.synthetic_map("Si", (3, 4), shape=(40, 40), seed=0)
    >>> xmap = reindex(
    ...     sm.signal, sm.start_xmap, sm.detector, sm.master_pattern, 20,
    ...     show_progressbar=False,
    ... )
    >>> xmap.shape, bool(xmap.scores.min() > 0.99)
    ((3, 4), True)
    """
    if show_progressbar is None:
        show_progressbar = True
    if refine_kwargs.get("compute", True) is not True:
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

    # What kikuchipy sees: one phase (the master pattern's), the points to
    # refine indexed, every other point not indexed
    q_in = xmap.rotations.data.reshape(-1, 4)
    flat = todo.ravel()
    q = np.tile([1.0, 0.0, 0.0, 0.0], (flat.size, 1))
    q[flat] = q_in[flat]
    mp_phase = master_pattern.phase.deepcopy()
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
    with contextlib.nullcontext() if show_progressbar else _quiet():
        ref = signal.refine_orientation(kx, det, master_pattern, energy, **refine_kwargs)
    return _merge(xmap, ref, flat, phase_id, mp_phase)


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

    >>> from kikuchipy_geomdic import synthetic
    >>> from kikuchipy_geomdic.reindex import refine_orientations
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
    signal, xmap = _stack_signal(patterns, rotations, phase)
    with _quiet():
        return signal.refine_orientation(xmap, detector, master_pattern, energy, **refine_kwargs)


def _stack_signal(patterns: np.ndarray, rotations: Rotation, phase) -> tuple[EBSD, CrystalMap]:
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


def _quiet():
    """Context in which kikuchipy's summaries and progress bars, which go
    to stdout, are not shown."""
    return contextlib.redirect_stdout(io.StringIO())


def _merge(xmap, ref, flat, phase_id, mp_phase) -> CrystalMap:
    """The refined points of *ref* put back into a copy of *xmap*."""
    n = flat.size
    done = np.zeros(n, dtype=bool)
    done[ref.id] = True
    done &= flat
    scores = np.zeros(n)
    scores[ref.id] = ref.prop["scores"]
    bad = done & ~np.isfinite(scores)  # NaN patterns give NaN scores
    done &= ~bad
    scores[~done] = 0.0
    num_evals = np.zeros(n, dtype=np.int64)
    num_evals[ref.id] = ref.prop["num_evals"]

    q = xmap.rotations.data.reshape(-1, 4).copy()
    q[done] = ref.rotations.data.reshape(-1, 4)[np.searchsorted(ref.id, np.flatnonzero(done))]
    pid = xmap.phase_id.copy()
    # Points with an invalid rotation (any phase) or a NaN pattern are not
    # indexed; masked-out points and other phases keep theirs
    with np.errstate(invalid="ignore"):
        invalid_rot = ~(
            np.isfinite(q).all(axis=1) & (np.abs(np.linalg.norm(q, axis=1) - 1) < 1e-3)
        )
    lost = bad | invalid_rot
    pid[lost] = -1
    q[lost | invalid_rot] = [1.0, 0.0, 0.0, 0.0]

    prop = {k: np.asarray(v).copy() for k, v in xmap.prop.items()}
    prop.update(scores=scores, num_evals=num_evals, refined=done.astype(np.int8))
    if "pseudo_symmetry_index" in ref.prop:
        psi = np.zeros(n, dtype=np.int64)
        psi[ref.id] = ref.prop["pseudo_symmetry_index"]
        prop["pseudo_symmetry_index"] = psi
    return map_with_phase(xmap, Rotation(q), pid, prop, phase_id, mp_phase)
