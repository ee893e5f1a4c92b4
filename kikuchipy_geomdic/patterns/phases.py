"""Which phase of a crystal map a master pattern is of: one rule.

A crystal map read from a file rarely has the very phase object of the
master pattern: orix reads an ``.ang`` file's phase with its proper point
group only (432 for silicon, against m-3m in the master pattern), EMsoft
files give lattice parameters in nm and ``.ang`` files in angstrom, and
names differ ("Si", "silicon"). The rule used everywhere in the package
(calibration, reindexing, the command line) is :func:`phases_match`:

- the proper point groups (the rotation parts, which is all EBSD
  orientations can tell) must be equal;
- then the lattice parameters must agree within 2 % (angstrom or nm) if
  both are known, else the names must agree (case-insensitive) if both
  are given.

:func:`check_phase` picks the map's phase to work with and checks it
against the master pattern; :func:`replace_phase` gives a map the master
pattern's phase, as kikuchipy's own refinement requires identical phases.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import numpy as np
from kikuchipy.signals import EBSDMasterPattern
from orix.crystal_map import CrystalMap, Phase, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry.maps import check_whole_map
from kikuchipy_geomdic.patterns.simulation import check_master_pattern

__all__ = ["phases_match", "describe_phase", "check_phase", "match_phase", "replace_phase"]


def _proper_point_group(phase: Phase) -> str | None:
    pg = phase.point_group
    if pg is None:
        return None
    return _proper_subgroup(pg).name


#: Proper subgroups already derived, by point group (name and operators)
_PROPER_SUBGROUPS: dict = {}


def _proper_subgroup(point_group):
    """Return orix's ``point_group.proper_subgroup``, derived once per
    point group: orix derives it from every subgroup each time (10 ms,
    four times per reindexing: a fifth of reindexing a 10 x 10 map of
    96 px)."""
    key = (point_group.name, np.asarray(point_group.data).tobytes())
    if key not in _PROPER_SUBGROUPS:
        _PROPER_SUBGROUPS[key] = point_group.proper_subgroup
    return _PROPER_SUBGROUPS[key]


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


def describe_phase(phase: Phase) -> str:
    """Return a phase's name, point group and lattice for messages.

    Parameters
    ----------
    phase
        orix phase.

    Returns
    -------
    text
        E.g. ``"'Si' (m-3m, a b c = 5.431 5.431 5.431)"``.

    Examples
    --------
    >>> from orix.crystal_map import Phase
    >>> from kikuchipy_geomdic.patterns.phases import describe_phase
    >>> describe_phase(Phase("Si", point_group="m-3m"))
    "'Si' (m-3m)"
    """
    pg = phase.point_group.name if phase.point_group is not None else "no symmetry"
    lat = _lattice(phase)
    cell = "" if lat is None else f", a b c = {lat[0]:.4g} {lat[1]:.4g} {lat[2]:.4g}"
    return f"{phase.name or '(unnamed)'!r} ({pg}{cell})"


def phases_match(phase: Phase, other: Phase) -> bool:
    """Return whether two orix phases describe the same crystal.

    The proper point groups must be equal; then the lattice parameters
    must agree within 2 % (in angstrom or nm) if both are known, else the
    names must agree (case-insensitive) if both are given. A phase
    without a point group matches nothing.

    Parameters
    ----------
    phase, other
        Phases, e.g. of a crystal map and of a master pattern.

    Returns
    -------
    match
        Whether the two are the same phase by this rule.

    Examples
    --------
    >>> from orix.crystal_map import Phase
    >>> from kikuchipy_geomdic.patterns.phases import phases_match
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


def _phase_id(xmap: CrystalMap, phase: str | int) -> int:
    """The id of a phase of *xmap* given by name or id."""
    try:
        pid = xmap.phases.id_from_name(phase) if isinstance(phase, str) else int(phase)
        xmap.phases[pid]
    except (KeyError, ValueError, IndexError, TypeError, AttributeError):
        raise ValueError(
            f"Phase {phase!r} is not in the crystal map's phases {xmap.phases.names}"
        ) from None
    if pid < 0:
        raise ValueError(f"Phase {phase!r} is the not-indexed phase, not a crystal phase")
    return int(pid)


def check_phase(
    xmap: CrystalMap, master_pattern: EBSDMasterPattern, phase: str | int | None = None
) -> int:
    """Return the id of the map's phase to work with, checked against the
    master pattern.

    Parameters
    ----------
    xmap
        Crystal map.
    master_pattern
        Master pattern whose ``phase`` must match the chosen one (see
        :func:`phases_match`).
    phase
        Name or id of the map's phase. Default: the map's only indexed
        phase.

    Returns
    -------
    phase_id

    Raises
    ------
    ValueError
        If the master pattern has no phase symmetry, the map has no
        indexed points, it has several indexed phases and none was chosen,
        the chosen phase is not in the map, or the master pattern's phase
        does not match it (the message names both, with point groups and
        lattice parameters).

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import master_patterns, synthetic
    >>> from kikuchipy_geomdic.patterns.phases import check_phase
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(20, 20))
    >>> check_phase(sm.xmap, sm.master_pattern)
    0
    >>> bto = master_patterns.master_pattern("BaTiO3")
    >>> check_phase(sm.xmap, bto)
    Traceback (most recent call last):
    ...
    ValueError: The master pattern's phase 'BaTiO3' (4mm, ...) does not match ... 'Si' (m-3m, ...)
    """
    check_master_pattern(master_pattern)
    mp_phase = master_pattern.phase
    if mp_phase is None or _proper_point_group(mp_phase) is None:
        raise ValueError("The master pattern has no phase symmetry: set master_pattern.phase")
    if phase is None:
        ids = [int(i) for i in np.unique(xmap.phase_id) if i >= 0]
        if not ids:
            raise ValueError("The crystal map has no indexed points")
        if len(ids) > 1:
            names = [xmap.phases[i].name for i in ids]
            raise ValueError(
                f"The crystal map has several phases {names}: choose one by name or id "
                "(phase=..., --phase on the command line)"
            )
        pid = ids[0]
    else:
        pid = _phase_id(xmap, phase)
    if not phases_match(xmap.phases[pid], mp_phase):
        raise ValueError(
            f"The master pattern's phase {describe_phase(mp_phase)} does not match the "
            f"crystal map's phase {describe_phase(xmap.phases[pid])}"
        )
    return pid


def match_phase(
    xmap: CrystalMap, master_pattern: EBSDMasterPattern, phase: str | int | None = None
) -> int:
    """Return the id of the map's phase the master pattern is of.

    The same as :func:`check_phase` (kept under this name for existing
    code).

    Parameters
    ----------
    xmap, master_pattern, phase
        As for :func:`check_phase`.

    Returns
    -------
    phase_id
        The id in ``xmap.phases``.
    """
    return check_phase(xmap, master_pattern, phase)


def replace_phase(xmap: CrystalMap, phase_id: int, phase: Phase) -> CrystalMap:
    """Return a copy of a crystal map with one phase replaced.

    Used to give a map read from a file (e.g. ``.ang``, whose phase orix
    knows only by its proper point group) the master pattern's phase, as
    kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation`
    requires identical phases.

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
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.patterns.phases import replace_phase
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(20, 20))
    >>> new = replace_phase(sm.xmap, 0, Phase("silicon", point_group="m-3m"))
    >>> new.phases[0].name, sm.xmap.phases[0].name
    ('silicon', 'Si')
    """
    check_whole_map(xmap)
    return map_with_phase(
        xmap,
        Rotation(xmap.rotations.data.reshape(-1, 4).copy()),
        xmap.phase_id.copy(),
        {k: np.asarray(v).copy() for k, v in xmap.prop.items()},
        phase_id,
        phase,
    )


def map_with_phase(
    xmap: CrystalMap,
    rotations: Rotation,
    phase_ids: np.ndarray,
    prop: dict,
    phase_id: int,
    phase: Phase,
) -> CrystalMap:
    """Return a crystal map with *xmap*'s coordinates, scan unit and
    phases (copied), one phase replaced, and new rotations, phase ids and
    properties.

    Parameters
    ----------
    xmap
        Crystal map whose coordinates, scan unit and phases are copied;
        not modified.
    rotations
        Rotations of the new map (not copied).
    phase_ids
        Phase ids of the new map (not copied).
    prop
        Properties of the new map (not copied).
    phase_id
        Id of the phase to replace (added if absent; its colour is kept).
    phase
        The phase put there (copied).

    Returns
    -------
    xmap
        A new :class:`~orix.crystal_map.CrystalMap`.
    """
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
