"""Quaternion arithmetic on plain arrays (a, b, c, d), as the variant and
reseeding code needs it: Hamilton products, conjugates, and the finite
group a set of rotations generates (quaternions modulo sign).

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import numpy as np

# Largest group the operators and the crystal symmetry may generate (the
# largest finite rotation group of a lattice, 432, has 24 elements)
_MAX_GROUP = 120


def _closure(q: np.ndarray) -> np.ndarray:
    """The finite group the rotations *q* generate (quaternions mod sign)."""
    group = _unique(q)
    while True:
        prod = _unique(_qmul(group[:, None, :], group[None, :, :]).reshape(-1, 4))
        new = prod[~_member(prod, group)]
        if not len(new):
            return group
        group = np.concatenate([group, new])
        if len(group) > _MAX_GROUP:
            raise ValueError(
                "the pseudo-symmetry operators with the crystal symmetry generate more than "
                f"{_MAX_GROUP} rotations: they are not the symmetries of a lattice"
            )


def _unique(q: np.ndarray) -> np.ndarray:
    out: list[np.ndarray] = []
    for x in q:
        if not out or not (np.abs(np.asarray(out) @ x) > 1 - 1e-9).any():
            out.append(x)
    return np.asarray(out)


def _member(q: np.ndarray, group: np.ndarray) -> np.ndarray:
    return (np.abs(q @ group.T) > 1 - 1e-9).any(axis=1)


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products of quaternions (..., 4) (broadcast)."""
    a0, a1, a2, a3 = np.moveaxis(a, -1, 0)
    b0, b1, b2, b3 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0,
        ],
        axis=-1,
    )


def _conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])
