"""The orientation model of one crystal (``orientation_model="crystal"``):
every calibration point is one parent orientation in one of its
pseudo-symmetric variants, with a small scatter about it
(:class:`_Crystal`), instead of a free rotation per point; and the check
that a map is one crystal at all (:func:`_one_crystal`).

With a free rotation per pattern a PC change is almost a rotation, so on
one crystal only the PC field across the map separates them, and a
misfit all patterns share does not average out. Tied to one parent (three
unknowns, the common rotation of
:func:`~kikuchipy_geomdic.calibration.solve.solve_joint`), the patterns'
changes across the map are the beam scan's, which the geometry alone
must explain.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import rotation_vectors
from kikuchipy_geomdic.indexing._quaternions import _conj, _qmul
from kikuchipy_geomdic.indexing.variants import (
    TOLERANCE,
    _choose_parent,
    _label,
    _nearest,
    _proper_rotations,
    _variant_table,
)

#: Orientation models of :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`.
ORIENTATION_MODELS = ("free", "crystal", "auto")

#: Smallest fraction of the starting orientations within
#: :data:`~kikuchipy_geomdic.indexing.variants.TOLERANCE` of one parent
#: (modulo its variants) for a map to be taken as one crystal; the
#: patterns judge the others (:func:`_other_crystal`). Users' starts
#: scatter: on a 100 um Ni single crystal indexed at a geometry 1.8 % off,
#: 42 % were within 5 deg of the parent; a polycrystal of n grains has
#: about 1/n.
MIN_CRYSTAL_FRACTION = 0.3

#: Points whose pattern fits their own start better than the parent's
#: variant refined at the start geometry, by the ratio
#: :data:`OTHER_CRYSTAL_RATIO` of their NCCs, are another crystal's; this
#: fraction of them makes the map not one crystal. A cluster of starts
#: away from the parent is not enough (on a 1 mm Ni single crystal indexed
#: at a start 1.8 % off, 22 % of the starts were 6-18 deg off together,
#: each fitting its pattern at NCC 0.03-0.09 where the parent fitted
#: 0.13-0.22), and users' starts of one crystal passed this test at up to
#: 25 % (Ni and Si, 100 um, 1.8 % off): a second crystal on less of the map
#: is not found, its points weigh little by their residuals.
OTHER_CRYSTAL_FRACTION = 0.3

#: A point fits another crystal when the parent's variant, refined at the
#: start geometry, reaches less than this fraction of its own start's NCC
#: with its pattern.
OTHER_CRYSTAL_RATIO = 0.5

#: RMS scatter (deg) of one crystal's orientations about its parent
#: assumed when ``orientation_prior`` is not given: a wafer or a domain
#: map scatters by hundredths of a degree; a tenth leaves room and still
#: keeps the PC field (over 65 um, a few tenths of a degree of apparent
#: rotation) from being taken up by the orientations.
CRYSTAL_SCATTER = 0.1


class NotOneCrystalError(ValueError):
    """The map is not one crystal: ``orientation_model="crystal"`` has no
    parent to fit."""


@dataclass(frozen=True)
class _Crystal:
    """One crystal's orientation model.

    Attributes
    ----------
    parent
        Quaternion (4,) of the parent orientation the labels refer to.
    table
        ``s * ops[k]`` (m, K + 1, 4): the crystal's proper rotations times
        the variant operators, identity first.
    fraction
        Fraction of the starting orientations within
        :data:`~kikuchipy_geomdic.indexing.variants.TOLERANCE` of the
        parent's variants.
    """

    parent: np.ndarray
    table: np.ndarray
    fraction: float

    def _nearest(self, rotations: Rotation) -> np.ndarray:
        """Index into the flattened table of each rotation's variant."""
        q = np.asarray(Rotation(rotations).flatten().data, dtype=np.float64)
        return _nearest(q, self.parent, self.table.reshape(-1, 4))[0]

    def far(self, rotations: Rotation) -> np.ndarray:
        """Whether each rotation (N,) lies beyond
        :data:`~kikuchipy_geomdic.indexing.variants.TOLERANCE` of the
        parent's variants."""
        q = np.asarray(Rotation(rotations).flatten().data, dtype=np.float64)
        return _label(q, self.parent, self.table)[1] > np.deg2rad(TOLERANCE)

    def labels(self, rotations: Rotation) -> np.ndarray:
        """Variant index (N,) of each rotation: 0 the parent's own, k
        ``ops[k - 1]`` applied."""
        return self._nearest(rotations) % self.table.shape[1]

    def anchors(self, rotations: Rotation) -> Rotation:
        """The parent in each rotation's nearest variant, ``s * op * parent``:
        the model's start, whatever the starting orientations' errors."""
        h = self.table.reshape(-1, 4)[self._nearest(rotations)]
        return Rotation(_qmul(h, self.parent[None]))

    def deviations(self, rotations: Rotation) -> tuple[np.ndarray, np.ndarray]:
        """The parent's current common rotation (4,), a sample-frame right
        factor of every anchor, and each rotation's vector (N, 3, radians)
        about it: the orientations' scatter, the prior's offsets."""
        q = np.asarray(Rotation(rotations).flatten().data, dtype=np.float64)
        anchor = np.asarray(self.anchors(rotations).data)
        d = _qmul(_conj(anchor), q)
        common = np.array([1.0, 0.0, 0.0, 0.0])
        # The mean to second order: twice about the last estimate
        for _ in range(2):
            v = rotation_vectors(Rotation(_qmul(_conj(common)[None], d)))
            common = _qmul(common, _from_vector(v.mean(axis=0)))
        return common, rotation_vectors(Rotation(_qmul(_conj(common)[None], d)))

    def fitted_parent(self, rotations: Rotation) -> Rotation:
        """The parent orientation the *rotations* share."""
        common, _ = self.deviations(rotations)
        return Rotation(_qmul(self.parent, common))


def _from_vector(v: np.ndarray) -> np.ndarray:
    half = np.linalg.norm(v) / 2
    return np.concatenate([[np.cos(half)], v * np.sinc(half / np.pi) / 2])


def _one_crystal(
    rotations: Rotation, symmetry, pseudo_symmetry_ops: Rotation | None
) -> tuple[_Crystal | None, str]:
    """The crystal model of the starting *rotations*, or None and why the
    map is not one crystal.

    The parent is the mode of the starts modulo the crystal's proper
    rotations and the variants, averaged over those within
    :data:`~kikuchipy_geomdic.indexing.variants.TOLERANCE`
    (:func:`~kikuchipy_geomdic.indexing.variants.domain_labels`' robust
    mean). One crystal: at least :data:`MIN_CRYSTAL_FRACTION` of the points
    within that tolerance (the patterns judge the rest,
    :func:`_other_crystal`)."""
    q = np.asarray(Rotation(rotations).flatten().data, dtype=np.float64)
    if pseudo_symmetry_ops is None:
        s = _proper_rotations(symmetry)
        table = s[:, None, :]
        group = s
    else:
        table, group = _variant_table(Rotation(pseudo_symmetry_ops).flatten(), symmetry)
    tol = np.deg2rad(TOLERANCE)
    parent = _choose_parent(q, table, group, tol)
    fraction = float((_label(q, parent, table)[1] <= tol).mean())
    if fraction < MIN_CRYSTAL_FRACTION:
        why = (
            f"{100 * fraction:.0f} % of the starting orientations are within {TOLERANCE:g} deg "
            "of one parent orientation"
            + (" or its variants" if pseudo_symmetry_ops is not None else "")
            + f" (one crystal: at least {100 * MIN_CRYSTAL_FRACTION:.0f} %)"
        )
        return None, why
    return _Crystal(parent=parent, table=table, fraction=fraction), ""


def _other_crystal(ncc_own: np.ndarray, ncc_parent: np.ndarray, far: np.ndarray) -> str:
    """Why the points are not one crystal, judged by their patterns, or
    an empty string: *ncc_own* (N,) their NCC with the patterns simulated
    at their starts, *ncc_parent* (N,) at the parent's variants, *far*
    (N,) whether the start is beyond the tolerance of the parent's
    variants. A start within it is the parent's: at the paper's start
    error (pcy 4.6 %) the parent refined at the start geometry fitted 55
    % of a BaTiO3 domain map's patterns less than half as well as their
    own starts, and the map was refused; judging the far starts only, it
    calibrated to 3.3e-4 at 1.2 standard errors."""
    other = far & (ncc_parent < OTHER_CRYSTAL_RATIO * ncc_own)
    if other.mean() < OTHER_CRYSTAL_FRACTION:
        return ""
    return (
        f"{100 * other.mean():.0f} % of the points' patterns fit their own starting "
        f"orientation over {1 / OTHER_CRYSTAL_RATIO:g} times as well as the parent's (one "
        f"crystal: under "
        f"{100 * OTHER_CRYSTAL_FRACTION:.0f} %)"
    )
