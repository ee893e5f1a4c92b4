"""Whole-map orientation refinement with a calibrated detector.

After the geometry is calibrated on a few hundred points, every
orientation of the map is refined with the calibrated detector: the
expensive part, one optimisation per pattern. :func:`reindex` is a thin
wrapper over kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation`
that adds what a whole real map needs:

- the map's phase is matched to the master pattern's (orix reads an
  ``.ang`` file's phase with its proper point group only, e.g. 432 for
  silicon, which kikuchipy would refuse against an m-3m master pattern),
  and a master pattern of another phase is refused with a clear message;
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
from orix.crystal_map import CrystalMap, Phase, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.simulation import check_master_pattern

__all__ = ["phases_match", "match_phase", "replace_phase", "usable_points", "reindex"]


# --------------------------------------------------------------------- #
# Phases
# --------------------------------------------------------------------- #


def _proper_point_group(phase: Phase) -> str | None:
    pg = phase.point_group
    if pg is None:
        return None
    return pg.proper_subgroup.name


def _lattice(phase: Phase) -> np.ndarray | None:
    """(a, b, c, alpha, beta, gamma), or None if unset (orix's default
    unit cube)."""
    try:
        abc = np.asarray(phase.structure.lattice.abcABG(), dtype=float)
    except Exception:  # pragma: no cover - orix without a structure
        return None
    if np.allclose(abc, [1, 1, 1, 90, 90, 90]):
        return None
    return abc


def _lattices_agree(a: np.ndarray, b: np.ndarray, rtol: float = 0.02) -> bool:
    """Equal within *rtol*, allowing nm against angstrom (orix reads
    angstrom from .ang/.ctf files, kikuchipy nm from EMsoft files)."""
    if not np.allclose(a[3:], b[3:], atol=1.0):
        return False
    return any(np.allclose(a[:3] * f, b[:3], rtol=rtol) for f in (1.0, 10.0, 0.1))


def _describe(phase: Phase) -> str:
    pg = phase.point_group.name if phase.point_group is not None else "no symmetry"
    lat = _lattice(phase)
    cell = "" if lat is None else f", a b c = {lat[0]:.4g} {lat[1]:.4g} {lat[2]:.4g}"
    return f"{phase.name or '(unnamed)'!r} ({pg}{cell})"


def phases_match(phase: Phase, other: Phase) -> bool:
    """Return whether two orix phases describe the same crystal.

    The proper point groups must be equal; then the lattice parameters
    must agree within 2 % (in angstrom or nm) if both are known, else the
    names must agree (case-insensitive) if both are given.

    Parameters
    ----------
    phase, other
        Phases, e.g. of a crystal map and of a master pattern.

    Returns
    -------
    match

    Examples
    --------
    >>> from orix.crystal_map import Phase
    >>> from kikuchipy_geomdic.reindex import phases_match
    >>> si = Phase("Si", point_group="m-3m")
    >>> phases_match(si, Phase("si", point_group="432"))
    True
    >>> phases_match(si, Phase("BaTiO3", point_group="4mm"))
    False
    """
    pa, pb = _proper_point_group(phase), _proper_point_group(other)
    if pa is None or pb is None or pa != pb:
        return False
    la, lb = _lattice(phase), _lattice(other)
    if la is not None and lb is not None:
        return _lattices_agree(la, lb)
    if phase.name and other.name:
        return phase.name.lower() == other.name.lower()
    return True


def match_phase(
    xmap: CrystalMap, master_pattern: EBSDMasterPattern, phase: str | int | None = None
) -> int:
    """Return the id of the map's phase the master pattern is of.

    Parameters
    ----------
    xmap
        Crystal map.
    master_pattern
        Master pattern whose ``phase`` is matched (see :func:`phases_match`).
    phase
        Name or id of the phase to use; checked against the master
        pattern. Default: the one indexed phase matching it.

    Returns
    -------
    phase_id

    Raises
    ------
    ValueError
        If the chosen phase does not match the master pattern, if no
        indexed phase does, or if several do and none was chosen.

    Examples
    --------
    >>> from kikuchipy_geomdic import synthetic
    >>> from kikuchipy_geomdic.reindex import match_phase
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(20, 20))
    >>> match_phase(sm.xmap, sm.master_pattern)
    0
    """
    check_master_pattern(master_pattern)
    mp_phase = master_pattern.phase
    if _proper_point_group(mp_phase) is None:
        raise ValueError("The master pattern has no phase symmetry: set master_pattern.phase")
    if phase is not None:
        try:
            pid = xmap.phases.id_from_name(phase) if isinstance(phase, str) else int(phase)
            p = xmap.phases[pid]
        except (KeyError, ValueError, IndexError, TypeError):
            raise ValueError(
                f"Phase {phase!r} is not in the map's phases {xmap.phases.names}"
            ) from None
        if not phases_match(p, mp_phase):
            raise ValueError(
                f"The master pattern's phase {_describe(mp_phase)} does not match the "
                f"map's phase {_describe(p)}"
            )
        return int(pid)
    ids = [int(i) for i in np.unique(xmap.phase_id) if i >= 0]
    if not ids:
        raise ValueError("The crystal map has no indexed points")
    hits = [i for i in ids if phases_match(xmap.phases[i], mp_phase)]
    if not hits:
        found = ", ".join(_describe(xmap.phases[i]) for i in ids)
        raise ValueError(
            f"The master pattern's phase {_describe(mp_phase)} matches none of the "
            f"map's phases: {found}"
        )
    if len(hits) > 1:
        names = [xmap.phases[i].name for i in hits]
        raise ValueError(f"Several phases of the map match the master pattern {names}: choose one")
    return hits[0]


def replace_phase(xmap: CrystalMap, phase_id: int, phase: Phase) -> CrystalMap:
    """Return a copy of a crystal map with one phase replaced.

    Used to give a map read from a file (e.g. ``.ang``, whose phase orix
    knows only by its proper point group) the master pattern's phase, as
    kikuchipy requires identical phases.

    Parameters
    ----------
    xmap
        Crystal map; not modified. All its points must be in the data.
    phase_id
        Id of the phase to replace.
    phase
        The new phase (copied; it keeps the old phase's colour).

    Returns
    -------
    xmap_new
        Same rotations, phase ids, coordinates, properties and scan unit.

    Examples
    --------
    >>> from orix.crystal_map import Phase
    >>> from kikuchipy_geomdic import synthetic
    >>> from kikuchipy_geomdic.reindex import replace_phase
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(20, 20))
    >>> new = replace_phase(sm.xmap, 0, Phase("silicon", point_group="m-3m"))
    >>> new.phases[0].name, sm.xmap.phases[0].name
    ('silicon', 'Si')
    """
    _check_in_data(xmap)
    return _new_map(
        xmap,
        Rotation(xmap.rotations.data.reshape(-1, 4).copy()),
        xmap.phase_id.copy(),
        {k: np.asarray(v).copy() for k, v in xmap.prop.items()},
        phase_id,
        phase,
    )


def _new_map(xmap, rotations, phase_ids, prop, phase_id, phase) -> CrystalMap:
    phases = {int(i): p.deepcopy() for i, p in xmap.phases if i >= 0}
    new = phase.deepcopy()
    if phase_id in phases:
        new.color = phases[phase_id].color
    phases[phase_id] = new
    return CrystalMap(
        rotations=rotations,
        phase_id=phase_ids,
        x=None if xmap.x is None else xmap.x.copy(),
        y=None if xmap.y is None else xmap.y.copy(),
        phase_list=PhaseList(phases),
        prop=prop,
        scan_unit=xmap.scan_unit,
    )


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
    _check_in_data(xmap)
    q = xmap.rotations.data.reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(q).all(axis=1) & (np.abs(np.linalg.norm(q, axis=1) - 1) < 1e-3)
    pid = xmap.phase_id
    ok &= pid >= 0 if phase_id is None else pid == phase_id
    return ok.reshape(xmap.shape)


def _check_in_data(xmap: CrystalMap) -> None:
    if not isinstance(xmap, CrystalMap):
        raise TypeError(f"xmap must be an orix CrystalMap, not {type(xmap).__name__}")
    if not np.all(xmap.is_in_data):
        raise ValueError(
            "The crystal map has points outside its data (a sliced or masked map): "
            "pass the whole map and exclude points with navigation_mask"
        )
    if xmap.rotations_per_point != 1:
        raise ValueError("The crystal map must have one rotation per point")


# --------------------------------------------------------------------- #
# Reindexing
# --------------------------------------------------------------------- #


def _nav_shape(signal: EBSD) -> tuple[int, ...]:
    return tuple(signal.axes_manager.navigation_shape[::-1])


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
        Name or id of the map's phase to refine; default the one matching
        the master pattern (:func:`match_phase`).
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
    if not isinstance(signal, EBSD):
        raise TypeError(f"signal must be a kikuchipy EBSD signal, not {type(signal).__name__}")
    if not isinstance(detector, EBSDDetector):
        raise TypeError(f"detector must be a kikuchipy EBSDDetector, not {type(detector).__name__}")
    _check_in_data(xmap)
    nav = _nav_shape(signal)
    if len(nav) not in (1, 2):
        raise ValueError(f"The signal must be a 1D or 2D map, not navigation shape {nav}")
    if tuple(xmap.shape) != nav:
        raise ValueError(
            f"The crystal map's shape {tuple(xmap.shape)} differs from the patterns' "
            f"navigation shape {nav}"
        )
    sig = tuple(signal.axes_manager.signal_shape[::-1])
    if tuple(detector.shape) != sig:
        raise ValueError(f"The detector's shape {detector.shape} differs from the patterns' {sig}")
    if detector.navigation_size not in (1, int(np.prod(nav))):
        raise ValueError(
            f"The detector has {detector.navigation_size} PCs, neither one nor one per "
            f"map point of {nav}"
        )
    phase_id = match_phase(xmap, master_pattern, phase)

    todo = usable_points(xmap, phase_id)
    if navigation_mask is not None:
        navigation_mask = np.asarray(navigation_mask, dtype=bool)
        if navigation_mask.shape != nav:
            raise ValueError(
                f"navigation_mask has shape {navigation_mask.shape}, the map {nav}"
            )
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
    out = contextlib.nullcontext() if show_progressbar else contextlib.redirect_stdout(io.StringIO())
    with out:
        ref = signal.refine_orientation(kx, det, master_pattern, energy, **refine_kwargs)
    return _merge(xmap, ref, flat, phase_id, mp_phase)


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
        invalid_rot = ~(np.isfinite(q).all(axis=1) & (np.abs(np.linalg.norm(q, axis=1) - 1) < 1e-3))
    lost = bad | invalid_rot
    pid[lost] = -1
    q[lost | invalid_rot] = [1.0, 0.0, 0.0, 0.0]

    prop = {k: np.asarray(v).copy() for k, v in xmap.prop.items()}
    prop.update(scores=scores, num_evals=num_evals, refined=done.astype(np.int8))
    if "pseudo_symmetry_index" in ref.prop:
        psi = np.zeros(n, dtype=np.int64)
        psi[ref.id] = ref.prop["pseudo_symmetry_index"]
        prop["pseudo_symmetry_index"] = psi
    return _new_map(xmap, Rotation(q), pid, prop, phase_id, mp_phase)
