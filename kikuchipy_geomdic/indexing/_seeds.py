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
