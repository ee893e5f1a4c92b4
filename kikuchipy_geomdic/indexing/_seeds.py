"""Misindexed points of a map: the rule that finds points scoring poorly
for where they are, and the distinct orientations of a point's
neighbours to refine it again from (the reseeding stage of
:func:`~kikuchipy_geomdic.indexing.reindex.refine_map`,
:mod:`~kikuchipy_geomdic.indexing._reseed`).

The public names are presented by
:mod:`~kikuchipy_geomdic.indexing.orientation`.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from kikuchipy_geomdic.indexing._quaternions import _qmul


def _neighbour_median(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Median of each point's valid 8-neighbours (NaN where none)."""
    rows, cols = values.shape
    padded = np.full((rows + 2, cols + 2), np.nan)
    padded[1:-1, 1:-1] = np.where(valid, values, np.nan)
    stack = [
        padded[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
        for dr in (-1, 0, 1)
        for dc in (-1, 0, 1)
        if dr or dc
    ]
    with warnings.catch_warnings():
        # All-NaN neighbourhoods (isolated points) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.stack(stack), axis=0)


#: A point is poor when its NCC is below this fraction of its neighbours'
#: median NCC ...
NEIGHBOUR_FRACTION = 0.8

#: ... or below the map's median NCC by more than this many robust
#: standard deviations (MAD x 1.4826) of the map's NCCs, and by at least
#: the same fraction (a map of near-identical scores has a tiny MAD).
MAP_DEVIATIONS = 5.0


def poor_points(scores: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Return which points of a map scored poorly for where they are.

    Grains are larger than a step, so a point whose NCC is well below its
    neighbours' has most likely converged to a wrong orientation (a start
    misindexed at a wrong geometry, a local optimum).

    Parameters
    ----------
    scores
        NCC per map point, (rows, columns) (a 1D map as (1, n)).
    valid
        Points that were refined; default all finite scores.

    Returns
    -------
    poor
        Boolean array of the map's shape: NCC below
        :data:`NEIGHBOUR_FRACTION` times the median of the point's valid
        8-neighbours, or more than :data:`MAP_DEVIATIONS` robust standard
        deviations (and that fraction) below the map's median; never a
        point not valid.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.indexing.orientation import poor_points
    >>> s = np.full((4, 4), 0.5) + np.arange(16).reshape(4, 4) * 1e-3
    >>> s[1, 2] = 0.2
    >>> np.argwhere(poor_points(s)).tolist()
    [[1, 2]]
    """
    scores = np.asarray(scores, dtype=float)
    if valid is None:
        valid = np.isfinite(scores)
    valid = valid & np.isfinite(scores)
    if not valid.any():
        return np.zeros(scores.shape, dtype=bool)
    nb_med = _neighbour_median(scores, valid)
    v = scores[valid]
    med = np.median(v)
    mad = 1.4826 * np.median(np.abs(v - med))
    with np.errstate(invalid="ignore"):
        drop = max(MAP_DEVIATIONS * mad, (1 - NEIGHBOUR_FRACTION) * med)
        poor = (scores < NEIGHBOUR_FRACTION * nb_med) | (scores < med - drop)
    return poor & valid


#: A point further than this (degrees) from its neighbours by
#: :func:`neighbour_disagreement` is refined again from the neighbours
#: closer than this to theirs. Measured on the users maps of BaTiO3
#: (dose 30, seed 0, 13 x 13): right points 0.15 deg from their
#: neighbours (median), 0.32 (90th percentile); points refined to a local
#: optimum next to the truth, their score within the map's spread,
#: 0.35-0.8. Seeds only from neighbours that agree with theirs keep a map
#: whose points all differ (fine grains, strong deformation, much noise)
#: from being refined again everywhere
DISAGREEMENT = 0.3

#: ... up to this (degrees): further, a point is across a boundary from
#: most of its neighbours (a polycrystal's grains are tens of degrees
#: apart), and a local optimum that far scores poorly (measured:
#: ``bench_orientations.py far`` 0.8 -> 1.2 s without this bound, the
#: same points right)
DISAGREEMENT_MAX = 2.0


def neighbour_disagreement(
    rotations: np.ndarray, valid: np.ndarray, equivalents: np.ndarray | None = None
) -> np.ndarray:
    """Return how far each point of a map is from its neighbours.

    A point whose orientation differs from most of its neighbours' by a
    fraction of a degree is either on a boundary or in a local optimum
    next to theirs, which its score cannot show where the noise spreads
    the scores more than the optimum costs. Refining it again from its
    neighbours' orientations tells the two apart.

    Parameters
    ----------
    rotations
        Quaternions (rows, columns, 4) of the map.
    valid
        Boolean (rows, columns): points that were refined.
    equivalents
        Quaternions (E, 4) that make two orientations the same (the
        crystal's proper symmetry, times the pseudo-symmetry operators if
        any); default the identity alone.

    Returns
    -------
    angles
        Degrees, of the map's shape: the median, over the point's valid
        8-neighbours, of the smallest angle between the point and a
        neighbour's equivalents; NaN at points not valid or without
        valid neighbours.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.indexing.orientation import neighbour_disagreement
    >>> q = np.tile([1.0, 0, 0, 0], (3, 3, 1))
    >>> q[1, 1] = [np.cos(np.deg2rad(0.25)), np.sin(np.deg2rad(0.25)), 0, 0]
    >>> neighbour_disagreement(q, np.ones((3, 3), bool)).round(2)
    array([[0. , 0. , 0. ],
           [0. , 0.5, 0. ],
           [0. , 0. , 0. ]])
    """
    rows, cols = valid.shape
    if equivalents is None:
        equivalents = np.array([[1.0, 0.0, 0.0, 0.0]])
    padded = np.zeros((rows + 2, cols + 2, 4))
    padded[1:-1, 1:-1] = rotations
    ok = np.zeros((rows + 2, cols + 2), dtype=bool)
    ok[1:-1, 1:-1] = valid
    angles = []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if not (dr or dc):
                continue
            nb = padded[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
            eq = _qmul(equivalents[None, None], nb[:, :, None, :])  # (rows, cols, E, 4)
            cos = np.abs(np.einsum("rceq,rcq->rce", eq, rotations)).max(axis=2)
            ang = np.rad2deg(2 * np.arccos(np.minimum(cos, 1.0)))
            usable = ok[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
            angles.append(np.where(usable, ang, np.nan))
    with warnings.catch_warnings():
        # Points without valid neighbours are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(np.stack(angles), axis=0)
    return np.where(valid, med, np.nan)


def neighbour_seeds(
    rotations: np.ndarray, point: tuple[int, int], usable: np.ndarray, min_angle: float = 1.0
) -> np.ndarray:
    """Return the distinct orientations of a point's 8-neighbours.

    Parameters
    ----------
    rotations
        Quaternions (rows, columns, 4) of the map.
    point
        (row, column) of the point.
    usable
        Boolean (rows, columns): neighbours that may seed (refined and not
        poor themselves).
    min_angle
        Seeds closer than this (degrees, as rotations, no symmetry) to an
        earlier seed are dropped.

    Returns
    -------
    seeds
        Quaternions (k, 4), k <= 8.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.indexing.orientation import neighbour_seeds
    >>> q = np.tile([1.0, 0, 0, 0], (3, 3, 1))
    >>> q[0, 0] = [0, 1, 0, 0]
    >>> neighbour_seeds(q, (1, 1), np.ones((3, 3), bool)).shape
    (2, 4)
    """
    r0, c0 = point
    rows, cols = usable.shape
    seeds: list[np.ndarray] = []
    cos_half = math.cos(math.radians(min_angle) / 2)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = r0 + dr, c0 + dc
            if (dr or dc) and 0 <= r < rows and 0 <= c < cols and usable[r, c]:
                q = rotations[r, c]
                if all(abs(float(np.dot(q, s))) < cos_half for s in seeds):
                    seeds.append(q)
    return np.array(seeds).reshape(-1, 4)
