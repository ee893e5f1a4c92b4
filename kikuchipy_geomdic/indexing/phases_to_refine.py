"""One notion of a phase to refine: :class:`PhaseToRefine` (its master
pattern, its orix phase, its pseudo-symmetry operators and the id of the
crystal map's phase it is matched to), and :func:`phases_to_refine`, which
matches one master pattern or a list of them, one per phase, to a crystal
map by the package's one phase rule
(:func:`~kikuchipy_geomdic.patterns.phases.phases_match`). A tuple of them
is the multi-phase case, one of them the one-phase case: calibration and
reindexing carry this tuple instead of a master pattern and its company.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from kikuchipy.signals import EBSDMasterPattern
from orix.crystal_map import CrystalMap, Phase
from orix.quaternion import Rotation

from kikuchipy_geomdic.indexing._projection import MasterPatternArrays, master_pattern_arrays
from kikuchipy_geomdic.patterns.phases import check_phase, describe_phase, phases_match
from kikuchipy_geomdic.patterns.simulation import check_master_pattern

__all__ = ["PhaseToRefine", "phases_to_refine", "unrefined_phases"]


@dataclass(frozen=True)
class PhaseToRefine:
    """A phase of a crystal map to refine.

    Attributes
    ----------
    master_pattern
        Lambert master pattern of the phase.
    phase_id
        Id of the crystal map's phase it is matched to.
    pseudo_symmetry_ops
        Operators of the phase's pseudo-symmetric variants (crystal frame,
        ``op * rotation``), or None.
    """

    master_pattern: EBSDMasterPattern
    phase_id: int
    pseudo_symmetry_ops: Rotation | None = None
    _arrays: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def phase(self) -> Phase:
        """The master pattern's orix phase (kikuchipy refuses phases whose
        atom lists differ in order, as after an h5ebsd round trip)."""
        return self.master_pattern.phase

    @property
    def name(self) -> str:
        """The phase's name."""
        return self.phase.name

    def arrays(self, energy: float) -> MasterPatternArrays:
        """The master pattern's hemispheres at *energy* (kV), made once."""
        key = float(energy)
        if key not in self._arrays:
            self._arrays[key] = master_pattern_arrays(self.master_pattern, key)
        return self._arrays[key]


def phases_to_refine(
    xmap: CrystalMap,
    master_pattern: EBSDMasterPattern | Sequence[EBSDMasterPattern],
    phase: str | int | None = None,
    pseudo_symmetry_ops: Rotation | Sequence[Rotation | None] | None = None,
    energy: float | Sequence[float] | None = None,
) -> tuple[PhaseToRefine, ...]:
    """Match master patterns to a crystal map's phases.

    One master pattern is matched as the package always did
    (:func:`~kikuchipy_geomdic.patterns.phases.check_phase`: the map's only
    indexed phase, or *phase*). A list of them, one per phase, is matched
    each to the map's indexed phase it is of
    (:func:`~kikuchipy_geomdic.patterns.phases.phases_match`).

    Parameters
    ----------
    xmap
        Crystal map; not modified.
    master_pattern
        Lambert master pattern, or a list of them, one per phase.
    phase
        Name or id of the map's phase (one master pattern only).
    pseudo_symmetry_ops
        Pseudo-symmetry operators: a ``Rotation`` for one master pattern,
        or a list of them (None where a phase has none), one per master
        pattern.
    energy
        Beam energy in kV (a list of equal values is taken as one): a
        master pattern with an energy axis must hold it.

    Returns
    -------
    phases
        A :class:`PhaseToRefine` per master pattern, in the given order.

    Raises
    ------
    ValueError
        A master pattern whose phase is in no point of the map, or matches
        several of its phases; two master patterns of one phase; different
        energies, or a master pattern without the beam's; *phase* with a
        list; operators not one per master pattern.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import master_patterns, synthetic
    >>> from kikuchipy_geomdic.indexing.phases_to_refine import phases_to_refine
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(20, 20))
    >>> [(p.name, p.phase_id) for p in phases_to_refine(sm.xmap, sm.master_pattern)]
    [('Si', 0)]
    >>> ni = master_patterns.master_pattern("Ni")
    >>> phases_to_refine(sm.xmap, [sm.master_pattern, ni])
    Traceback (most recent call last):
    ...
    ValueError: The master pattern of 'Ni' (m-3m, ...) is of no phase in a point of the map ...
    """
    energy = check_energy(energy)
    if isinstance(master_pattern, EBSDMasterPattern):
        pid = check_phase(xmap, master_pattern, phase)
        return (PhaseToRefine(master_pattern, pid, pseudo_symmetry_ops),)
    mps = list(master_pattern)
    if not mps:
        raise ValueError("No master pattern given")
    ops = _operators(pseudo_symmetry_ops, len(mps))
    if len(mps) == 1:
        return (PhaseToRefine(mps[0], check_phase(xmap, mps[0], phase), ops[0]),)
    if phase is not None:
        raise ValueError(
            f"phase={phase!r} chooses the phase of one master pattern; with {len(mps)} master "
            "patterns each is matched to its own phase of the map"
        )
    present = [int(i) for i in np.unique(xmap.phase_id) if i >= 0]
    ids = [_match(xmap, mp, present) for mp in mps]
    for i, pid in enumerate(ids):
        if pid in ids[:i]:
            first = mps[ids.index(pid)]
            raise ValueError(
                f"Two master patterns, of {describe_phase(first.phase)} and of "
                f"{describe_phase(mps[i].phase)}, are of one phase of the map, "
                f"{describe_phase(xmap.phases[pid])}: give one master pattern per phase"
            )
    for mp in mps:
        _check_energy_axis(mp, energy)
    return tuple(PhaseToRefine(mp, pid, op) for mp, pid, op in zip(mps, ids, ops))


def check_energy(energy: float | Sequence[float] | None) -> float | None:
    """Return the one beam energy of *energy* (a number, or a list of equal
    ones); raise a ``ValueError`` naming different energies.

    Examples
    --------
    >>> from kikuchipy_geomdic.indexing.phases_to_refine import check_energy
    >>> check_energy([20, 20.0])
    20.0
    """
    if energy is None or np.ndim(energy) == 0:
        return None if energy is None else float(energy)
    values = np.asarray(energy, dtype=float).ravel()
    if values.size == 0 or not np.all(values == values[0]):
        raise ValueError(
            f"Different energies {values.tolist()} kV: the patterns of every phase are of one "
            "beam, give its energy once"
        )
    return float(values[0])


def unrefined_phases(xmap: CrystalMap, phases: Sequence[PhaseToRefine]) -> dict[str, int]:
    """Return the map's indexed phases without a master pattern among
    *phases*, as {name: number of points}.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.indexing.phases_to_refine import phases_to_refine
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(20, 20))
    >>> unrefined_phases(sm.xmap, phases_to_refine(sm.xmap, sm.master_pattern))
    {}
    """
    given = {p.phase_id for p in phases}
    ids, counts = np.unique(xmap.phase_id, return_counts=True)
    return {
        xmap.phases[int(i)].name: int(c)
        for i, c in zip(ids, counts)
        if i >= 0 and int(i) not in given
    }


def _operators(ops, n: int) -> list:
    """One entry of pseudo-symmetry operators (or None) per master pattern."""
    if ops is None:
        return [None] * n
    if isinstance(ops, Rotation):
        if n == 1:
            return [ops]
        raise ValueError(
            f"One set of pseudo_symmetry_ops for {n} master patterns: give a list of them, one "
            "per master pattern (None where a phase has none)"
        )
    ops = list(ops)
    if len(ops) != n:
        raise ValueError(
            f"{len(ops)} entries of pseudo_symmetry_ops for {n} master patterns: give one per "
            "master pattern (None where a phase has none)"
        )
    return [None if o is None else Rotation(o) for o in ops]


def _match(xmap: CrystalMap, mp: EBSDMasterPattern, present: list[int]) -> int:
    """The id of the map's indexed phase *mp* is of."""
    check_master_pattern(mp)
    if mp.phase is None or mp.phase.point_group is None:
        raise ValueError("A master pattern has no phase symmetry: set master_pattern.phase")
    found = [pid for pid in present if phases_match(xmap.phases[pid], mp.phase)]
    if not found:
        names = [describe_phase(xmap.phases[pid]) for pid in present]
        raise ValueError(
            f"The master pattern of {describe_phase(mp.phase)} is of no phase in a point of "
            f"the map (its indexed phases: {', '.join(names) or 'none'})"
        )
    if len(found) > 1:
        names = [describe_phase(xmap.phases[pid]) for pid in found]
        raise ValueError(
            f"The master pattern of {describe_phase(mp.phase)} matches several phases of the "
            f"map ({', '.join(names)}): merge them, or give their names distinct lattices"
        )
    return found[0]


def _check_energy_axis(mp: EBSDMasterPattern, energy: float | None) -> None:
    """Raise if *mp* has an energy axis without the beam's *energy*."""
    if energy is None:
        return
    try:
        axis = np.asarray(mp.axes_manager["energy"].axis, dtype=float)
    except (KeyError, ValueError, AttributeError):
        return  # One energy, not recorded: the user's word
    if not np.isclose(axis, energy, atol=1e-3).any():
        raise ValueError(
            f"The master pattern of {describe_phase(mp.phase)} holds energies "
            f"{axis.min():g}-{axis.max():g} kV, not the beam's {energy:g} kV: every phase's "
            "master pattern must hold the beam energy"
        )
