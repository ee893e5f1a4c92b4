r"""The ROI grid of the DIC and what is computed per ROI (Eqs. 1 and 8).

Each pattern is split into a grid of regions of interest (ROIs); the
vectors tracked in it are filtered per ROI (the paper's ROI-crossing rule
and a robust median/MAD test, :func:`filter_vectors`), averaged per ROI
(Eq. 1, :func:`roi_average`) and weighted by their counts (Eq. 8,
:func:`roi_weights`).

ROIs are numbered in row-major order: ROI ``r = j * m + k`` is in ROI row
``j`` and ROI column ``k`` of an ``(n, m)`` grid. The grid edges are
``np.linspace(0, size, n + 1)`` rounded to whole pixels, so every pixel
belongs to exactly one ROI, and ROI sizes differ by at most one pixel when
the pattern size is not a multiple of the grid size (:func:`roi_edges`).
Pixel coordinates ``(x, y)`` put the centre of pixel ``(row j, column i)``
at ``(i, j)``.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import functools
import math

import numba as nb
import numpy as np

__all__ = [
    "roi_edges",
    "roi_centres",
    "roi_index",
    "roi_average",
    "roi_weights",
    "filter_vectors",
]

#: Vectors further than ``robust`` scaled MADs from their ROI's median
#: vector are dropped, but never when closer than this many pixels: the
#: true field varies within an ROI and tight clusters have tiny MADs.
ROBUST_FLOOR = 0.25
#: An ROI must span at least this many tracking pixels each way.
MIN_ROI_SIZE = 4

_MAD_SCALE = 1.4826  # MAD to standard deviation for normal data


# --------------------------------------------------------------------- #
# ROI grid
# --------------------------------------------------------------------- #


def _check_grid(shape, rois) -> tuple[tuple[int, int], tuple[int, int]]:
    # Asked for twice or more by every vector lookup of every pattern, the
    # same grid each time: checked once per grid (it was 2 % of the DIC)
    try:
        return _checked_grid(tuple(shape), rois if np.isscalar(rois) else tuple(rois))
    except TypeError:  # unhashable parts: checked as they are
        return _checked_grid.__wrapped__(shape, rois)


@functools.lru_cache(maxsize=32)
def _checked_grid(shape, rois) -> tuple[tuple[int, int], tuple[int, int]]:
    shape = tuple(int(s) for s in shape)
    rois = tuple(int(r) for r in np.broadcast_to(rois, (2,)))
    if len(shape) != 2 or min(shape) < 1:
        raise ValueError(f"Pattern shape must be (rows, columns), not {shape}")
    if min(rois) < 1:
        raise ValueError(f"The ROI grid must have at least one ROI each way, not {rois}")
    if rois[0] > shape[0] or rois[1] > shape[1]:
        raise ValueError(f"An ROI grid {rois} does not fit patterns of shape {shape}")
    return shape, rois


def roi_edges(
    shape: tuple[int, int], rois: tuple[int, int] = (8, 8)
) -> tuple[np.ndarray, np.ndarray]:
    """Return the pixel edges of an ROI grid.

    Parameters
    ----------
    shape
        Pattern shape (rows, columns).
    rois
        Grid shape (n, m): n ROI rows and m ROI columns.

    Returns
    -------
    row_edges, col_edges
        Integer arrays of length n + 1 and m + 1. ROI ``(j, k)`` holds the
        pixel rows ``row_edges[j]:row_edges[j + 1]`` and columns
        ``col_edges[k]:col_edges[k + 1]``; in pixel coordinates (pixel
        centres at integers) an edge ``e`` lies at ``e - 0.5``. The edges
        are ``np.linspace(0, size, n + 1)`` rounded, so leftover pixels
        are spread over the grid and every pixel is in exactly one ROI.

    Examples
    --------
    >>> from kikuchipy_geomdic.patterns.roi import roi_edges
    >>> roi_edges((10, 12), (3, 4))
    (array([ 0,  3,  7, 10]), array([ 0,  3,  6,  9, 12]))
    """
    return tuple(e.copy() for e in _edges(*_check_grid(shape, rois)))


@functools.lru_cache(maxsize=32)
def _edges(shape, rois):
    # Cached, read-only: asked for by every pattern's vectors, the same grid
    # cost more than the lookups made with it; the public roi_edges copies
    edges = tuple(np.round(np.linspace(0, s, n + 1)).astype(np.int64) for s, n in zip(shape, rois))
    for e in edges:
        e.flags.writeable = False
    return edges


def roi_centres(shape: tuple[int, int], rois: tuple[int, int] = (8, 8)) -> np.ndarray:
    """Return the centre of each ROI in pixel coordinates.

    Parameters
    ----------
    shape
        Pattern shape (rows, columns).
    rois
        Grid shape (n, m).

    Returns
    -------
    centres
        Array (n * m, 2) of ``(x, y)``, ROIs in row-major order. The
        centre of an ROI holding pixel columns ``c0:c1`` is at
        ``x = (c0 + c1 - 1) / 2`` (pixel centres are integers).

    Examples
    --------
    >>> from kikuchipy_geomdic.patterns.roi import roi_centres
    >>> roi_centres((4, 6), (1, 2))
    array([[1. , 1.5],
           [4. , 1.5]])
    """
    row_edges, col_edges = _edges(*_check_grid(shape, rois))
    yc = (row_edges[:-1] + row_edges[1:] - 1) / 2
    xc = (col_edges[:-1] + col_edges[1:] - 1) / 2
    y, x = np.meshgrid(yc, xc, indexing="ij")
    return np.stack([x.ravel(), y.ravel()], axis=1)


def roi_index(
    x: np.ndarray, y: np.ndarray, shape: tuple[int, int], rois: tuple[int, int] = (8, 8)
) -> np.ndarray:
    """Return the row-major ROI index of points, -1 outside the pattern.

    Parameters
    ----------
    x, y
        Pixel coordinates (any matching shapes). A point belongs to the
        pixel whose centre is nearest, ``(floor(y + 0.5), floor(x + 0.5))``.
    shape, rois
        Pattern shape (rows, columns) and ROI grid (n, m).

    Returns
    -------
    index
        Integer array of the broadcast shape of *x* and *y*; -1 for points
        outside the pattern or NaN.

    Examples
    --------
    >>> from kikuchipy_geomdic.patterns.roi import roi_index
    >>> roi_index([0, 5.4, 5.6, 11.4, 12], [0, 0, 0, 9, 0], (10, 12), (2, 2))
    array([ 0,  0,  1,  3, -1])
    """
    row_edges, col_edges = _edges(*_check_grid(shape, rois))
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    with np.errstate(invalid="ignore"):
        col = np.floor(x + 0.5)
        row = np.floor(y + 0.5)
        inside = (col >= 0) & (col < shape[1]) & (row >= 0) & (row < shape[0])
    col = np.where(inside, col, 0).astype(np.int64)
    row = np.where(inside, row, 0).astype(np.int64)
    j = np.searchsorted(row_edges, row, side="right") - 1
    k = np.searchsorted(col_edges, col, side="right") - 1
    return np.where(inside, j * (len(col_edges) - 1) + k, -1)


@functools.lru_cache(maxsize=32)
def _tracking_labels(shape, rois, binning, tracked_shape, margin):
    """ROI of each tracking pixel, -1 within *margin* of the edge.

    A tracking pixel belongs to the ROI of its full-resolution centre.
    Returns the label image (read-only). Cached: every pattern of a map has
    the same (built per pattern, they were a tenth of the DIC
    measurement's cost).
    """
    row_edges, col_edges = _edges(*_check_grid(shape, rois))
    lab = []
    for size, edges in zip(tracked_shape, (row_edges, col_edges)):
        centre = np.arange(size) * binning + (binning - 1) / 2
        idx = np.searchsorted(edges, np.floor(centre + 0.5), side="right") - 1
        idx[:margin] = -1
        idx[size - margin :] = -1
        lab.append(idx)
    rows, cols = lab
    labels = np.where(
        (rows[:, None] >= 0) & (cols[None, :] >= 0), rows[:, None] * rois[1] + cols[None, :], -1
    )
    labels.flags.writeable = False
    return labels


# --------------------------------------------------------------------- #
# Eq. 1 and Eq. 8
# --------------------------------------------------------------------- #


def roi_average(
    xy_a: np.ndarray,
    xy_b: np.ndarray,
    shape: tuple[int, int],
    rois: tuple[int, int] = (8, 8),
    values: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average vectors per ROI as in Eq. 1 of the paper.

    Every vector with at least one endpoint in an ROI counts in that ROI,
    so a vector whose endpoints are in two ROIs counts in both (once in
    an ROI holding both endpoints).

    Parameters
    ----------
    xy_a, xy_b
        Endpoints (n, 2) ``(x, y)`` in A and B. Points outside the pattern
        do not count.
    shape
        Pattern shape (rows, columns).
    rois
        Grid shape.
    values
        Vectors (n, 2) to average. Default ``xy_b - xy_a``; pass, e.g., the
        true displacement at *xy_a* to average a ground truth exactly as
        the measurement is averaged.

    Returns
    -------
    u
        Mean vector per ROI (R, 2); zero where no vector counts.
    counts
        Number of vectors per ROI (R,), :math:`c_{r,i}`.
    positions
        Mean A endpoint ``(x, y)`` of the vectors counted per ROI (R, 2),
        where the mean vector was measured; the ROI centre where no vector
        counts.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.patterns.roi import roi_average
    >>> a = np.array([[2.0, 2.0], [4.0, 2.0]])
    >>> b = np.array([[3.0, 2.0], [6.0, 2.0]])  # the 2nd crosses to ROI 1
    >>> u, c, _ = roi_average(a, b, (10, 10), (2, 2))
    >>> u[:2], c
    (array([[1.5, 0. ],
           [2. , 0. ]]), array([2, 1, 0, 0]))
    """
    shape, rois = _check_grid(shape, rois)
    xy_a = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)
    xy_b = np.asarray(xy_b, dtype=np.float64).reshape(-1, 2)
    values = xy_b - xy_a if values is None else np.asarray(values, np.float64).reshape(-1, 2)
    ra, rb = (_roi_index(z, shape, *_edges(shape, rois)) for z in (xy_a, xy_b))
    return _average(ra, rb, np.ascontiguousarray(values), xy_a, roi_centres(shape, rois))


@nb.njit(cache=True, nogil=True)
def _average(ra, rb, values, xy_a, positions):
    """:func:`roi_average` of vectors in ROIs *ra* (by A) and *rb* (by B),
    the *positions* (R, 2) filled where an ROI has vectors: NumPy's
    weighted ``bincount`` over the two index lists one after the other,
    the same sums in the same order (a dozen NumPy calls per pattern were
    a tenth of the DIC measurement)."""
    n_rois = len(positions)
    counts = np.zeros(n_rois, dtype=np.int64)
    sums = np.zeros((n_rois, 2))
    at = np.zeros((n_rois, 2))
    for second in range(2):
        for i in range(len(ra)):
            r = ra[i]
            if second:
                # Counted once in an ROI holding both endpoints
                r = -1 if rb[i] == ra[i] else rb[i]
            if r < 0:
                continue
            counts[r] += 1
            for d in range(2):
                sums[r, d] += values[i, d]
                at[r, d] += xy_a[i, d]
    u = np.zeros((n_rois, 2))
    for r in range(n_rois):
        if counts[r]:
            for d in range(2):
                u[r, d] = sums[r, d] / counts[r]
                positions[r, d] = at[r, d] / counts[r]
    return u, counts, positions


@nb.njit(cache=True, nogil=True)
def _roi_index(xy, shape, row_edges, col_edges):
    """:func:`roi_index` of the points *xy* (n, 2), compiled."""
    out = np.empty(len(xy), dtype=np.int64)
    for i in range(len(xy)):
        col = math.floor(xy[i, 0] + 0.5)
        row = math.floor(xy[i, 1] + 0.5)
        # NaN fails every comparison: outside
        if not (col >= 0 and col < shape[1] and row >= 0 and row < shape[0]):
            out[i] = -1
            continue
        j = 0
        while j + 1 < len(row_edges) and row_edges[j + 1] <= row:
            j += 1
        k = 0
        while k + 1 < len(col_edges) and col_edges[k + 1] <= col:
            k += 1
        out[i] = j * (len(col_edges) - 1) + k
    return out


def roi_weights(counts: np.ndarray) -> np.ndarray:
    """Return the ROI weights of Eq. 8 from total vector counts.

    Parameters
    ----------
    counts
        Total counts :math:`c_r = \\sum_i c_{r,i}` per ROI (R,).

    Returns
    -------
    weights
        :math:`w_r` (R,): 0 for :math:`c_r = 0`,
        :math:`\\sqrt{c_r / c_{90}}` below the 90th percentile
        :math:`c_{90}` of the non-zero counts (NumPy's default linear
        interpolation), 1 at or above it. All zero if every count is zero.
        Repeat each weight twice (``np.repeat(w, 2)``) to weight
        :math:`\\mathbf{b}`, as
        :attr:`~kikuchipy_geomdic.patterns.displacement.DisplacementField.residual_weights`
        does.

    Examples
    --------
    >>> from kikuchipy_geomdic.patterns.roi import roi_weights
    >>> w = roi_weights([0, 1, 4, 4, 4, 4, 4, 4, 4, 4, 4, 9])  # c90 = 4
    >>> w[:3], w[-1]
    (array([0. , 0.5, 1. ]), np.float64(1.0))
    """
    counts = np.asarray(counts, dtype=np.float64)
    if np.any(counts < 0) or not np.all(np.isfinite(counts)):
        raise ValueError("Counts must be finite and non-negative")
    weights = np.zeros_like(counts)
    nonzero = counts > 0
    if not nonzero.any():
        return weights
    c90 = np.percentile(counts[nonzero], 90)
    weights[nonzero] = np.sqrt(np.minimum(counts[nonzero] / c90, 1.0))
    return weights


# --------------------------------------------------------------------- #
# Outliers
# --------------------------------------------------------------------- #


def filter_vectors(
    xy_a: np.ndarray,
    xy_b: np.ndarray,
    shape: tuple[int, int],
    rois: tuple[int, int] = (8, 8),
    max_roi_crossings: int | None = 2,
    robust: float | None = 3.0,
) -> np.ndarray:
    """Return which vectors pass the ROI-crossing and robust tests.

    Parameters
    ----------
    xy_a, xy_b
        Endpoints (n, 2) in A and B, full-resolution pixel coordinates.
    shape
        Pattern shape (rows, columns).
    rois
        Grid shape.
    max_roi_crossings
        The paper's rule: drop a vector whose endpoints are in ROIs more
        than this many ROI rows or columns apart (Chebyshev distance on
        the grid). None to switch off. Vectors with an endpoint outside
        the pattern are always dropped.
    robust
        Drop a vector further from the median vector of its ROI (by its A
        endpoint) than *robust* times the scaled median absolute deviation
        of the distances, but never one closer than :data:`ROBUST_FLOOR`
        px. Needs three vectors in the ROI. None to switch off.

    Returns
    -------
    keep
        Boolean mask (n,).

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.patterns.roi import filter_vectors
    >>> a = np.array([[5.0, 5], [6, 5], [5, 6], [6, 6], [5, 7]])
    >>> b = a + [[1, 0], [1, 0], [1.1, 0], [1, 0.1], [40, 0]]
    >>> filter_vectors(a, b, (60, 60), (6, 6))
    array([ True,  True,  True,  True, False])
    >>> filter_vectors(a, b, (60, 60), (6, 6), max_roi_crossings=None)
    array([ True,  True,  True,  True, False])
    >>> filter_vectors(a, b, (60, 60), (6, 6), None, None)
    array([ True,  True,  True,  True,  True])
    """
    shape, rois = _check_grid(shape, rois)
    xy_a = np.asarray(xy_a, np.float64).reshape(-1, 2)
    xy_b = np.asarray(xy_b, np.float64).reshape(-1, 2)
    ra, rb = (_roi_index(z, shape, *_edges(shape, rois)) for z in (xy_a, xy_b))
    return _filter(
        ra,
        rb,
        np.ascontiguousarray(xy_b - xy_a),
        rois[1],
        -1 if max_roi_crossings is None else int(max_roi_crossings),
        np.nan if robust is None else robust * _MAD_SCALE,
        rois[0] * rois[1],
    )


@nb.njit(cache=True, nogil=True)
def _filter(ra, rb, v, m, crossings, scaled, n_rois):
    """:func:`filter_vectors` of vectors *v* (n, 2) in ROIs *ra* (by A)
    and *rb* (by B) of a grid *m* ROIs wide: the ROI crossings (off if
    negative), then the robust test with *scaled* MADs (off if NaN),
    medians the mean of the middle two where even."""
    n = len(v)
    keep = np.empty(n, dtype=np.bool_)
    for i in range(n):
        keep[i] = ra[i] >= 0 and rb[i] >= 0
        if keep[i] and crossings >= 0:
            far = max(abs(ra[i] // m - rb[i] // m), abs(ra[i] % m - rb[i] % m))
            keep[i] = far <= crossings
    if math.isnan(scaled):
        return keep
    idx = np.flatnonzero(keep)
    g = ra[idx]
    counts = np.bincount(g, minlength=n_rois)
    median = np.empty((n_rois, 2))
    for d in range(2):
        median[:, d] = _medians(v[idx, d], g, counts)
    dist = np.empty(len(idx))
    for q in range(len(idx)):
        i = idx[q]
        dist[q] = np.hypot(v[i, 0] - median[g[q], 0], v[i, 1] - median[g[q], 1])
    limit = _medians(dist, g, counts)
    for q in range(len(idx)):
        if counts[g[q]] >= 3 and dist[q] > max(scaled * limit[g[q]], ROBUST_FLOOR):
            keep[idx[q]] = False
    return keep


@nb.njit(cache=True, nogil=True)
def _medians(values, groups, counts):
    """The median of *values* in each group of *groups*, whose sizes are
    *counts* (NaN where empty)."""
    start = np.cumsum(counts) - counts
    filled = start.copy()
    grouped = np.empty(len(values))
    for i in range(len(values)):
        grouped[filled[groups[i]]] = values[i]
        filled[groups[i]] += 1
    out = np.full(len(counts), np.nan)
    for r in range(len(counts)):
        if counts[r]:
            z = np.sort(grouped[start[r] : start[r] + counts[r]])
            out[r] = (z[(counts[r] - 1) // 2] + z[counts[r] // 2]) / 2
    return out
