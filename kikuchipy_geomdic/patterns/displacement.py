r"""Displacement fields between simulated and experimental patterns (DIC).

Section 2.2 of Griesbach & Kochmann: each pair of a simulated pattern
:math:`\mathbf{A}_i` and an experimental pattern :math:`\mathbf{B}_i` is
split into a grid of regions of interest (ROIs); Shi-Tomasi features found
in A are tracked into B with pyramidal Lucas-Kanade (LK) optical flow; the
vectors are averaged per ROI (Eq. 1), then over patterns (Eq. 2) and
stacked into the residual vector :math:`\mathbf{b}` (Eq. 3), which comes
with the ROI weights of Eq. 8.

Conventions
-----------
Pixel coordinates ``(x, y)`` put the centre of pixel ``(row j, column i)``
at ``(i, j)``, as in :mod:`kikuchipy_geomdic.geometry`, OpenCV and
scikit-image: x to the right (columns), y down (rows). A displacement is
measured from the simulated (A) to the experimental (B) pattern, in
full-resolution pixels, also when features are tracked in binned
patterns.

ROIs are numbered in row-major order: ROI ``r = j * m + k`` is in ROI row
``j`` and ROI column ``k`` of an ``(n, m)`` grid. The grid edges are
``np.linspace(0, size, n + 1)`` rounded to whole pixels, so every pixel
belongs to exactly one ROI, and ROI sizes differ by at most one pixel when
the pattern size is not a multiple of the grid size (:func:`roi_edges`).

Preprocessing
-------------
Per pattern pair, in this order: both patterns are standardised (zero
mean, unit standard deviation); A is optionally blurred (``blur``, the
detector's point spread, which simulations lack) and gets Gaussian noise
(``noise``, as in the paper); both are binned (``binning``), smoothed
(``smoothing``) and standardised again; the OpenCV backend then maps both
to 8 bits with one common linear map. Features closer than half an LK
window to the pattern edge are not used.

Backends
--------
``dic="opencv"`` uses :func:`cv2.goodFeaturesToTrack` (run per ROI, so
that every ROI gets its quota) and :func:`cv2.calcOpticalFlowPyrLK`, as
the paper does. ``dic="skimage"`` needs no OpenCV: the same Shi-Tomasi
strength (Sobel derivatives, box window, scikit-image's
:func:`~skimage.feature.structure_tensor_eigenvalues`), the same greedy
per-ROI selection, and a pyramidal LK tracker written here with
NumPy/SciPy (Bouguet's scheme as in OpenCV, in floating point).
``dic="auto"`` takes OpenCV when it can be imported. Both backends pick the
same features and agree to a few hundredths of a pixel.

After tracking, each vector is attached to the point where LK actually
measured it, the structure-tensor weighted centre of its window, not to
the feature itself; where the displacement varies (pcz, tilt) this halved
the error per vector on simulated patterns.
"""

from __future__ import annotations

import inspect
import math
import os
import warnings
from dataclasses import dataclass
from functools import cache, partial

import numpy as np
from scipy import ndimage

__all__ = [
    "DisplacementField",
    "measure_displacements",
    "pattern_vectors",
    "filter_vectors",
    "roi_average",
    "roi_weights",
    "roi_edges",
    "roi_centres",
    "roi_index",
    "bin_pattern",
    "resolve_backend",
]

#: Shi-Tomasi corners weaker than this fraction of the strongest corner of
#: their ROI are not used (OpenCV's ``qualityLevel``).
QUALITY = 0.01
#: Corners weaker than this fraction of the strongest edge of the whole
#: pattern (largest structure-tensor eigenvalue) are not used either, so
#: that a featureless ROI (flat background, detector shadow, a lone band)
#: yields no vectors instead of noise.
QUALITY_FLOOR = 0.01
#: Smallest distance between two features, in tracking pixels.
MIN_DISTANCE = 3
#: Corner detection window (OpenCV's ``blockSize``).
BLOCK_SIZE = 5
#: Lucas-Kanade iterations per pyramid level and the step (in pixels of
#: that level) below which an iteration counts as converged.
LK_ITERATIONS = 30
LK_EPSILON = 0.01
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
    >>> from kikuchipy_geomdic.patterns.displacement import roi_edges
    >>> roi_edges((10, 12), (3, 4))
    (array([ 0,  3,  7, 10]), array([ 0,  3,  6,  9, 12]))
    """
    shape, rois = _check_grid(shape, rois)
    return tuple(np.round(np.linspace(0, s, n + 1)).astype(np.int64) for s, n in zip(shape, rois))


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
    >>> from kikuchipy_geomdic.patterns.displacement import roi_centres
    >>> roi_centres((4, 6), (1, 2))
    array([[1. , 1.5],
           [4. , 1.5]])
    """
    row_edges, col_edges = roi_edges(shape, rois)
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
    >>> from kikuchipy_geomdic.patterns.displacement import roi_index
    >>> roi_index([0, 5.4, 5.6, 11.4, 12], [0, 0, 0, 9, 0], (10, 12), (2, 2))
    array([ 0,  0,  1,  3, -1])
    """
    row_edges, col_edges = roi_edges(shape, rois)
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


def _roi_rowcol(index: np.ndarray, rois: tuple[int, int]):
    return index // rois[1], index % rois[1]


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
    >>> from kikuchipy_geomdic.patterns.displacement import roi_average
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
    n_rois = rois[0] * rois[1]
    ra = roi_index(xy_a[:, 0], xy_a[:, 1], shape, rois)
    rb = roi_index(xy_b[:, 0], xy_b[:, 1], shape, rois)
    rb = np.where(rb == ra, -1, rb)  # Count once in an ROI holding both
    idx = np.concatenate([ra, rb])
    keep = idx >= 0
    idx = idx[keep]
    vals = np.concatenate([values, values])[keep]
    pos = np.concatenate([xy_a, xy_a])[keep]
    counts = np.bincount(idx, minlength=n_rois)
    u = np.zeros((n_rois, 2))
    positions = roi_centres(shape, rois)
    has = counts > 0
    for d in range(2):
        u[has, d] = np.bincount(idx, vals[:, d], n_rois)[has] / counts[has]
        positions[has, d] = np.bincount(idx, pos[:, d], n_rois)[has] / counts[has]
    return u, counts, positions


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
        :math:`\\mathbf{b}`, as :attr:`DisplacementField.residual_weights`
        does.

    Examples
    --------
    >>> from kikuchipy_geomdic.patterns.displacement import roi_weights
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
# Preprocessing
# --------------------------------------------------------------------- #


def bin_pattern(pattern: np.ndarray, binning: int, dtype=np.float64) -> np.ndarray:
    """Return a pattern binned by averaging *binning* x *binning* blocks.

    Rows and columns left over at the bottom and right edges (when the
    shape is not a multiple of *binning*) are dropped. The centre of
    binned pixel ``k`` is at full-resolution coordinate
    ``k * binning + (binning - 1) / 2``.

    Parameters
    ----------
    pattern
        Array (..., rows, columns): one pattern or a stack; the last two
        axes are binned.
    binning
        Positive integer.
    dtype
        Floating type the blocks are averaged in and returned as.

    Returns
    -------
    binned
        Array of shape ``(..., rows // binning, columns // binning)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.patterns.displacement import bin_pattern
    >>> bin_pattern(np.arange(20.0).reshape(4, 5), 2)
    array([[ 3.,  5.],
           [13., 15.]])
    """
    p = np.asarray(pattern, dtype=dtype)
    if binning == 1:
        return p
    nr, nc = p.shape[-2] // binning, p.shape[-1] // binning
    p = p[..., : nr * binning, : nc * binning]
    return p.reshape(p.shape[:-2] + (nr, binning, nc, binning)).mean(axis=(-3, -1))


def _standardise(pattern: np.ndarray, index: int, name: str) -> np.ndarray:
    if not np.all(np.isfinite(pattern)):
        raise ValueError(f"{name} pattern {index} contains NaN or infinite values")
    std = pattern.std()
    if not std > 1e-12 * max(1.0, np.abs(pattern).max()):
        raise ValueError(f"{name} pattern {index} is constant: nothing to track")
    return (pattern - pattern.mean()) / std


def _to_uint8(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # OpenCV 5's LK takes only 8-bit images. One linear map for A and B
    # keeps LK's brightness constancy; the full range is kept because
    # the brightest pixels (zone axes, 5-10 std above the mean) are where
    # the corners are, and clipping them would flatten those corners
    lo, hi = min(a.min(), b.min()), max(a.max(), b.max())
    scale = 255 / (hi - lo)
    return tuple(np.rint((z - lo) * scale).astype(np.uint8) for z in (a, b))


def _tracking_labels(shape, rois, binning, tracked_shape, margin):
    """ROI of each tracking pixel, -1 within *margin* of the edge.

    A tracking pixel belongs to the ROI of its full-resolution centre.
    Returns the label image and the pixel box of each ROI.
    """
    row_edges, col_edges = roi_edges(shape, rois)
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
    boxes = []
    for j in range(rois[0]):
        rr = np.flatnonzero(rows == j)
        for k in range(rois[1]):
            cc = np.flatnonzero(cols == k)
            if rr.size and cc.size:
                boxes.append((rr[0], rr[-1] + 1, cc[0], cc[-1] + 1))
            else:
                boxes.append(None)
    return labels, boxes


# --------------------------------------------------------------------- #
# Backends
# --------------------------------------------------------------------- #


def _import_cv2():
    try:
        import cv2
    except ImportError:
        return None
    return cv2


def resolve_backend(dic: str = "auto") -> str:
    """Return the DIC backend to use: "opencv" or "skimage".

    Parameters
    ----------
    dic
        "auto" (OpenCV when importable, else scikit-image), "opencv" or
        "skimage".

    Returns
    -------
    backend

    Raises
    ------
    ImportError
        If "opencv" is asked for and :mod:`cv2` cannot be imported.

    Examples
    --------
    >>> from kikuchipy_geomdic.patterns.displacement import resolve_backend
    >>> resolve_backend("skimage")
    'skimage'
    """
    if dic not in ("auto", "opencv", "skimage"):
        raise ValueError(f"dic must be 'auto', 'opencv' or 'skimage', not {dic!r}")
    if dic == "skimage":
        return dic
    if _import_cv2() is not None:
        return "opencv"
    if dic == "opencv":
        raise ImportError(
            "dic='opencv' needs OpenCV (pip install opencv-python-headless); or use dic='skimage'"
        )
    return "skimage"


def _features_opencv(cv2, z, boxes, per_roi):
    # goodFeaturesToTrack takes float32 (only LK needs 8 bits): 8-bit
    # steps would make corners out of smooth ramps
    img = z.astype(np.float32)
    eig = cv2.cornerMinEigenVal(img, BLOCK_SIZE)
    both = cv2.cornerEigenValsAndVecs(img, BLOCK_SIZE, 3)[..., :2]
    floor = QUALITY_FLOOR * float(both.max())
    pts = []
    # One call per ROI so that every ROI gets its quota (on the whole
    # image, strong band intersections would take all the corners); the
    # crop has a margin so that corner strengths at the ROI edge are those
    # of the whole image
    margin = BLOCK_SIZE
    for box in boxes:
        if box is None:
            continue
        r0, r1, c0, c1 = box
        roi_max = float(eig[r0:r1, c0:c1].max())
        if not roi_max > floor:
            continue
        R0, R1 = max(r0 - margin, 0), min(r1 + margin, img.shape[0])
        C0, C1 = max(c0 - margin, 0), min(c1 + margin, img.shape[1])
        mask = np.zeros((R1 - R0, C1 - C0), np.uint8)
        mask[r0 - R0 : r1 - R0, c0 - C0 : c1 - C0] = 255
        found = cv2.goodFeaturesToTrack(
            img[R0:R1, C0:C1],
            maxCorners=per_roi,
            qualityLevel=max(QUALITY, floor / roi_max),
            minDistance=MIN_DISTANCE,
            mask=mask,
            blockSize=BLOCK_SIZE,
        )
        if found is not None:
            pts.append(found.reshape(-1, 2).astype(np.float64) + (C0, R0))
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def _track_opencv(cv2, img_a, img_b, pts, window, levels):
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, LK_ITERATIONS, LK_EPSILON)
    p0 = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 1, 2)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        img_a, img_b, p0, None, winSize=(window, window), maxLevel=levels, criteria=criteria
    )
    return p1.reshape(-1, 2).astype(np.float64), status.ravel().astype(bool)


def _eigenvalues(z: np.ndarray) -> np.ndarray:
    # Structure tensor as OpenCV's cornerMinEigenVal computes it (Sobel
    # derivatives, box window), so both backends rank corners alike
    from skimage.feature import structure_tensor_eigenvalues

    gx = ndimage.sobel(z, 1, mode="reflect")
    gy = ndimage.sobel(z, 0, mode="reflect")
    tensor = [
        ndimage.uniform_filter(g, BLOCK_SIZE, mode="reflect") for g in (gy * gy, gx * gy, gx * gx)
    ]
    return structure_tensor_eigenvalues(tensor)  # (largest, smallest)


def _features_skimage(z, labels, per_roi):
    edge, resp = _eigenvalues(z)
    floor = QUALITY_FLOOR * edge.max()
    n_rois = labels.max() + 1
    peak = (resp == ndimage.maximum_filter(resp, size=3, mode="nearest")) & (labels >= 0)
    peak &= resp > floor
    roi_max = np.append(ndimage.maximum(resp, labels, np.arange(n_rois)), np.inf)
    peak &= resp >= QUALITY * roi_max[labels]
    rr, cc = np.nonzero(peak)
    lab, val = labels[rr, cc], resp[rr, cc]
    order = np.lexsort((-val, lab))  # By ROI, strongest first
    rr, cc, lab = rr[order], cc[order], lab[order]
    # Greedy minimum distance within each ROI, as goodFeaturesToTrack
    chosen = []
    for group in np.split(np.arange(lab.size), np.flatnonzero(np.diff(lab)) + 1):
        kept = []
        for k in group:
            if all((rr[k] - rr[q]) ** 2 + (cc[k] - cc[q]) ** 2 >= MIN_DISTANCE**2 for q in kept):
                kept.append(k)
                if len(kept) == per_roi:
                    break
        chosen.extend(kept)
    chosen = np.sort(np.array(chosen, dtype=np.int64))
    return np.stack([cc[chosen], rr[chosen]], axis=1).astype(np.float64)


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    # OpenCV's pyrDown: 5-tap binomial blur, keep even pixels, so pixel k
    # of level L + 1 sits at pixel 2k of level L
    kernel = np.array([1, 4, 6, 4, 1]) / 16
    pyr = [img]
    for _ in range(levels):
        blurred = ndimage.convolve1d(pyr[-1], kernel, axis=0, mode="reflect")
        blurred = ndimage.convolve1d(blurred, kernel, axis=1, mode="reflect")
        pyr.append(blurred[::2, ::2])
    return pyr


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Scharr derivatives, as OpenCV's LK uses
    d = np.array([-0.5, 0.0, 0.5])
    s = np.array([3.0, 10.0, 3.0]) / 16
    gx = ndimage.correlate1d(ndimage.correlate1d(img, d, 1, mode="nearest"), s, 0, mode="nearest")
    gy = ndimage.correlate1d(ndimage.correlate1d(img, d, 0, mode="nearest"), s, 1, mode="nearest")
    return gx, gy


class _Windows:
    """Bilinear samples of square windows around many points at once.

    All pixels of a window are whole pixels away from its centre, so they
    share one pair of bilinear weights: gather a (w + 1) x (w + 1) patch
    per point and blend its four shifted views. Images are edge-padded so
    that no index needs clipping; centres are clipped to one pixel
    outside the image.
    """

    def __init__(self, images, half):
        self.pad = half + 2
        self.shape = images[0].shape
        self.flat = [np.pad(im, self.pad, mode="edge").ravel() for im in images]
        self.width = self.shape[1] + 2 * self.pad
        o = np.arange(-half, half + 2)
        self.offsets = (o[:, None] * self.width + o[None, :]).ravel()
        self.side = o.size

    def __call__(self, x, y, which=(0,)):
        x = np.clip(x, -1, self.shape[1])
        y = np.clip(y, -1, self.shape[0])
        x0, y0 = np.floor(x), np.floor(y)
        fx = (x - x0)[:, None, None]
        fy = (y - y0)[:, None, None]
        base = (y0.astype(np.int64) + self.pad) * self.width + x0.astype(np.int64) + self.pad
        idx = base[:, None] + self.offsets
        out = []
        for k in which:
            p = self.flat[k][idx].reshape(-1, self.side, self.side)
            top = p[:, :-1, :-1] + fx * (p[:, :-1, 1:] - p[:, :-1, :-1])
            bottom = p[:, 1:, :-1] + fx * (p[:, 1:, 1:] - p[:, 1:, :-1])
            out.append((top + fy * (bottom - top)).reshape(len(x), -1))
        return out


def _track_numpy(img_a, img_b, pts, window, levels):
    """Pyramidal Lucas-Kanade of *pts* from A to B (Bouguet's scheme).

    Returns the end points and a status flag, as cv2.calcOpticalFlowPyrLK.
    """
    half = window // 2
    o = np.arange(-half, half + 1)
    oy, ox = np.repeat(o, o.size), np.tile(o, o.size)
    flow = np.zeros((len(pts), 2))
    ok = np.ones(len(pts), bool)
    pyr_a, pyr_b = _pyramid(img_a, levels), _pyramid(img_b, levels)
    for level in range(levels, -1, -1):
        a, b = pyr_a[level], pyr_b[level]
        h, w = a.shape
        p = pts / 2**level
        t, tx, ty = _Windows([a, *_gradients(a)], half)(p[:, 0], p[:, 1], (0, 1, 2))
        # Template pixels outside A carry no information
        sx, sy = p[:, :1] + ox, p[:, 1:] + oy
        inside = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)
        tx, ty = tx * inside, ty * inside
        g11, g12, g22 = (tx * tx).sum(1), (tx * ty).sum(1), (ty * ty).sum(1)
        det = g11 * g22 - g12**2
        # OpenCV's minEigThreshold test, on intensities of unit variance
        min_eig = (g11 + g22 - np.sqrt((g11 - g22) ** 2 + 4 * g12**2)) / 2
        ok &= min_eig > 1e-4 * np.maximum(inside.sum(1), 1)
        target = _Windows([b], half)
        active = np.flatnonzero(ok)
        last = np.zeros_like(flow)
        for iteration in range(LK_ITERATIONS):
            if active.size == 0:
                break
            (j,) = target(p[active, 0] + flow[active, 0], p[active, 1] + flow[active, 1])
            e = t[active] - j  # tx, ty are zero outside A: no mask needed
            b1 = np.einsum("ij,ij->i", e, tx[active])
            b2 = np.einsum("ij,ij->i", e, ty[active])
            g = (g11[active], g12[active], g22[active], det[active])
            step = np.stack([(g[2] * b1 - g[1] * b2) / g[3], (g[0] * b2 - g[1] * b1) / g[3]], 1)
            # A step undoing the last one oscillates about the optimum:
            # stop halfway, as OpenCV does
            swing = ((step + last[active]) ** 2).sum(1) < LK_EPSILON**2
            swing &= iteration > 0
            step[swing] = -0.5 * last[active[swing]]
            flow[active] += step
            last[active] = step
            active = active[((step**2).sum(1) > LK_EPSILON**2) & ~swing]
        if level:
            flow *= 2
    end = pts + flow
    h, w = img_a.shape
    ok &= (end[:, 0] > -1) & (end[:, 0] < w) & (end[:, 1] > -1) & (end[:, 1] < h)
    return end, ok


def _max_levels(shape, window, levels):
    # Stop the pyramid before a level is narrower than two windows: on
    # coarser levels LK can lock onto a far-away band, and consistently so
    # when tracking back, which the forward-backward test cannot see
    top = 0
    while top < levels and min(shape) / 2 ** (top + 1) >= 2 * window:
        top += 1
    return top


# --------------------------------------------------------------------- #
# One pattern pair
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
    >>> from kikuchipy_geomdic.patterns.displacement import filter_vectors
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
    ra = roi_index(xy_a[:, 0], xy_a[:, 1], shape, rois)
    rb = roi_index(xy_b[:, 0], xy_b[:, 1], shape, rois)
    keep = (ra >= 0) & (rb >= 0)
    if max_roi_crossings is not None:
        ja, ka = _roi_rowcol(ra, rois)
        jb, kb = _roi_rowcol(rb, rois)
        keep &= np.maximum(abs(ja - jb), abs(ka - kb)) <= max_roi_crossings
    if robust is not None:
        idx = np.flatnonzero(keep)
        g = ra[idx]
        n_rois = rois[0] * rois[1]
        v = (xy_b - xy_a)[idx]
        median = np.stack([_group_median(v[:, d], g, n_rois) for d in range(2)], axis=1)
        dist = np.hypot(*(v - median[g]).T)
        limit = np.maximum(robust * _MAD_SCALE * _group_median(dist, g, n_rois), ROBUST_FLOOR)
        enough = np.bincount(g, minlength=n_rois) >= 3
        keep[idx[enough[g] & (dist > limit[g])]] = False
    return keep


def _group_median(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    # Median per group, all groups at once (NaN for empty groups)
    order = np.lexsort((values, groups))
    counts = np.bincount(groups, minlength=n_groups)
    start = np.cumsum(counts) - counts
    has = counts > 0
    lo = (start + (counts - 1) // 2)[has]
    hi = (start + counts // 2)[has]
    median = np.full(n_groups, np.nan)
    median[has] = (values[order][lo] + values[order][hi]) / 2
    return median


def pattern_vectors(
    simulated: np.ndarray,
    experimental: np.ndarray,
    rng: np.random.Generator | int | None = None,
    index: int = 0,
    **options,
) -> tuple[np.ndarray, np.ndarray]:
    """Return the displacement vectors of one pattern pair.

    Parameters
    ----------
    simulated, experimental
        One simulated and one experimental 2D pattern of one shape.
    rng
        Generator (or seed) of the noise added to *simulated*.
    index
        Names the pattern in error messages.
    **options
        The DIC options of :func:`measure_displacements` (``rois``,
        ``binning``, ``noise``, ``blur``, ``dic``, ``max_roi_crossings``,
        ``forward_backward``, ``robust``, ``features_per_roi``,
        ``window``, ``levels``, ``smoothing``), with its defaults.

    Returns
    -------
    xy_a, xy_b
        Endpoints (n, 2) of the vectors that passed every test, in
        full-resolution pixel coordinates: a feature in A and where it was
        tracked to in B.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy import ndimage
    >>> from kikuchipy_geomdic.patterns.displacement import pattern_vectors
    >>> a = ndimage.gaussian_filter(np.random.default_rng(0).random((60, 60)), 2)
    >>> b = ndimage.shift(a, (0.5, 1.0), mode="nearest")  # x + 1, y + 0.5
    >>> xy_a, xy_b = pattern_vectors(a, b, rois=(4, 4), dic="skimage")
    >>> xy_a.shape[1], np.round(np.median(xy_b - xy_a, axis=0), 1)
    (2, array([1. , 0.5]))
    """
    o = _dic_options(options)
    rois, binning, window = o["rois"], o["binning"], o["window"]
    backend = resolve_backend(o["dic"])
    a = np.asarray(simulated, dtype=np.float64)
    b = np.asarray(experimental, dtype=np.float64)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(
            f"Simulated and experimental patterns must be 2D of one shape, not "
            f"{a.shape} and {b.shape}"
        )
    shape, rois = _check_grid(a.shape, rois)
    _check_tracking(shape, rois, binning, window)
    a = _standardise(a, index, "Simulated")
    b = _standardise(b, index, "Experimental")
    if o["blur"]:
        a = ndimage.gaussian_filter(a, o["blur"], mode="nearest")
        a = _standardise(a, index, "Simulated")
    if o["noise"]:
        a = a + np.random.default_rng(rng).normal(0.0, o["noise"], a.shape)  # std(a) is 1
    a, b = _prepare(a, binning, o["smoothing"]), _prepare(b, binning, o["smoothing"])
    # Features closer than half a window to the edge are not used: their
    # LK window would reach outside the pattern
    labels, boxes = _tracking_labels(shape, rois, binning, a.shape, window // 2)
    top = _max_levels(a.shape, window, o["levels"])
    if backend == "opencv":
        cv2 = _import_cv2()
        img_a, img_b = _to_uint8(a, b)
        pts = _features_opencv(cv2, a, boxes, o["features_per_roi"])
        track = partial(_track_opencv, cv2, window=window, levels=top)
    else:
        img_a, img_b = a, b
        pts = _features_skimage(a, labels, o["features_per_roi"])
        track = partial(_track_numpy, window=window, levels=top)
    end = pts
    if len(pts):
        end, ok = track(img_a, img_b, pts)
        if o["forward_backward"] is not None and ok.any():
            back, ok_back = track(img_b, img_a, end)
            miss = np.hypot(*(back - pts).T) * binning
            ok &= ok_back & (miss <= o["forward_backward"])
        pts, end = pts[ok], end[ok]
        shift = _window_centres(a, pts, window)
        pts, end = pts + shift, end + shift
    # Binned pixel k is centred on full-resolution coordinate k b + (b - 1) / 2
    xy_a = pts * binning + (binning - 1) / 2
    xy_b = end * binning + (binning - 1) / 2
    keep = filter_vectors(xy_a, xy_b, shape, rois, o["max_roi_crossings"], o["robust"])
    return xy_a[keep], xy_b[keep]


@cache
def _dic_defaults() -> dict:
    """The DIC options of :func:`measure_displacements` with their
    defaults: its signature is their one definition."""
    params = inspect.signature(measure_displacements).parameters
    own = ("simulated", "experimental", "seed", "keep_vectors", "chunk_size")
    return {k: p.default for k, p in params.items() if k not in own}


def _dic_options(options) -> dict:
    """*options* completed with the defaults; an unknown name raises as a
    misspelt keyword argument would."""
    defaults = _dic_defaults()
    unknown = sorted(set(options) - set(defaults))
    if unknown:
        raise TypeError(f"Unknown DIC option(s) {unknown}: use {list(defaults)}")
    return {**defaults, **options}


def _window_centres(img: np.ndarray, pts: np.ndarray, window: int) -> np.ndarray:
    r"""Offsets from *pts* to where LK measured the displacement.

    Linearised, LK returns :math:`\mathbf{G}^{-1}\sum_k \mathbf{g}_k
    \mathbf{g}_k^T \mathbf{d}(\mathbf{x}_k)` over its window: the
    displacement weighted by the local structure tensors, not the one at
    the window centre. Where the displacement varies (a pcz or tilt change
    dilates and shears the pattern) it belongs at the structure-weighted
    centre :math:`\mathbf{p} + \mathbf{G}^{-1}\sum_k \mathbf{g}_k
    \mathbf{g}_k^T (\mathbf{x}_k - \mathbf{p})` (exact for a dilation,
    to first order); reporting it there halved the per-vector error on
    simulated pcz changes.
    """
    if len(pts) == 0:
        return np.zeros((0, 2))
    half = window // 2
    gx, gy = _Windows(list(_gradients(img)), half)(pts[:, 0], pts[:, 1], (0, 1))
    o = np.arange(-half, half + 1, dtype=np.float64)
    ox, oy = np.tile(o, o.size), np.repeat(o, o.size)
    g11, g12, g22 = (gx * gx).sum(1), (gx * gy).sum(1), (gy * gy).sum(1)
    v1 = (gx * gx * ox + gx * gy * oy).sum(1)
    v2 = (gx * gy * ox + gy * gy * oy).sum(1)
    det = g11 * g22 - g12**2
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.stack([(g22 * v1 - g12 * v2) / det, (g11 * v2 - g12 * v1) / det], axis=1)
    # Cannot leave the window; a degenerate tensor keeps the centre
    return np.where(np.isfinite(c), np.clip(c, -half, half), 0.0)


def _prepare(z: np.ndarray, binning: int, smoothing: float) -> np.ndarray:
    # Smoothing takes out detail near the Nyquist frequency, which aliases
    # in simulated patterns and biases bilinear LK towards half pixels
    z = bin_pattern(z, binning)
    if smoothing:
        z = ndimage.gaussian_filter(z, smoothing, mode="nearest")
    std = z.std()
    if not std > 0:
        raise ValueError("A pattern is constant after binning: nothing to track")
    # One intensity scale for A and B: LK assumes equal brightness
    return (z - z.mean()) / std


def _check_tracking(shape, rois, binning, window):
    if int(binning) != binning or binning < 1:
        raise ValueError(f"binning must be a positive integer, not {binning}")
    if int(window) != window or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd integer >= 3, not {window}")
    row_edges, col_edges = roi_edges(shape, rois)
    smallest = min(np.diff(row_edges).min(), np.diff(col_edges).min()) / binning
    if smallest < MIN_ROI_SIZE:
        raise ValueError(
            f"The ROI grid {rois} is too fine for patterns of shape {shape} with "
            f"binning {binning}: the smallest ROI spans {smallest:g} tracking pixels, "
            f"at least {MIN_ROI_SIZE} are needed to hold features"
        )


# --------------------------------------------------------------------- #
# Many patterns
# --------------------------------------------------------------------- #


@dataclass(frozen=True, eq=False)
class DisplacementField:
    """Per-ROI displacements of N pattern pairs (Eqs. 1-3 and 8).

    Parameters
    ----------
    u
        Per-pattern ROI displacements :math:`\\mathbf{u}_{r,i}` (N, R, 2),
        ``(dx, dy)`` in pixels from simulated to experimental; zero where
        an ROI has no vector.
    counts
        Vectors per ROI and pattern :math:`c_{r,i}` (N, R).
    positions
        Mean A endpoint ``(x, y)`` of the vectors of each ROI and pattern
        (N, R, 2); the ROI centre where there are none. A endpoints are
        where LK measured each vector (see Notes of
        :func:`measure_displacements`). Evaluate a model displacement here
        (or at each vector's A endpoint) to compare it with *u*.
    shape
        Pattern shape (rows, columns).
    rois
        Grid shape (n, m); R = n m, ROIs in row-major order.
    backend
        "opencv" or "skimage".
    vectors
        Per pattern an array (n_i, 4) of ``(x_a, y_a, x_b, y_b)`` of every
        vector used (full-resolution pixel coordinates), or None if not
        kept.
    """

    u: np.ndarray
    counts: np.ndarray
    positions: np.ndarray
    shape: tuple[int, int]
    rois: tuple[int, int]
    backend: str
    vectors: tuple[np.ndarray, ...] | None = None

    @property
    def n_patterns(self) -> int:
        """Number of patterns N."""
        return self.u.shape[0]

    @property
    def mean_displacement(self) -> float:
        """Mean magnitude of the average field (:attr:`mean`) over the ROIs
        with vectors, as a fraction of the detector width: the paper's
        objective. NaN when no ROI has a vector.

        Examples
        --------
        >>> import numpy as np
        >>> from kikuchipy_geomdic.patterns.displacement import DisplacementField
        >>> u = np.array([[[3.0, 4.0], [0.0, 0.0]]])  # one pattern, two ROIs
        >>> f = DisplacementField(u, np.array([[1, 0]]), np.zeros((1, 2, 2)), (50, 100),
        ...                       (1, 2), "opencv")
        >>> f.mean_displacement
        0.05
        """
        has = self.total_counts > 0
        if not has.any():
            return float("nan")
        return float(np.linalg.norm(self.mean[has], axis=1).mean() / self.shape[1])

    @property
    def mean(self) -> np.ndarray:
        """Average field :math:`\\bar{\\mathbf{u}}_r` (R, 2), Eq. 2.

        The sum over patterns is divided by N, not by the number of
        patterns with vectors in the ROI: an ROI without vectors in a
        pattern adds zero, as in the paper.
        """
        return self.u.sum(axis=0) / self.n_patterns

    @property
    def total_counts(self) -> np.ndarray:
        """Total counts :math:`c_r = \\sum_i c_{r,i}` (R,)."""
        return self.counts.sum(axis=0)

    @property
    def residual(self) -> np.ndarray:
        """Residual vector :math:`\\mathbf{b}` (2R,) of Eq. 3.

        Ordered ``[u_1x, u_1y, u_2x, u_2y, ...]``, ROIs row-major.
        """
        return self.mean.ravel()

    @property
    def weights(self) -> np.ndarray:
        """ROI weights :math:`w_r` (R,) of Eq. 8."""
        return roi_weights(self.total_counts)

    @property
    def residual_weights(self) -> np.ndarray:
        """Weights matching :attr:`residual` (2R,): each :math:`w_r` twice."""
        return np.repeat(self.weights, 2)

    @property
    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """ROI edges, see :func:`roi_edges`."""
        return roi_edges(self.shape, self.rois)

    @property
    def centres(self) -> np.ndarray:
        """ROI centres (R, 2) ``(x, y)``, see :func:`roi_centres`."""
        return roi_centres(self.shape, self.rois)

    def roi_index(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return the ROI index of points, see :func:`roi_index`."""
        return roi_index(x, y, self.shape, self.rois)

    def select(self, index) -> DisplacementField:
        """Return the field of a subset of the patterns (any NumPy index)."""
        index = np.arange(self.n_patterns)[index]
        index = np.atleast_1d(index)
        vectors = None if self.vectors is None else tuple(self.vectors[i] for i in index)
        return DisplacementField(
            self.u[index],
            self.counts[index],
            self.positions[index],
            self.shape,
            self.rois,
            self.backend,
            vectors,
        )


def _measure_block(a, b, start, seed, options):
    """Measure one block of pattern pairs; picklable for any scheduler."""
    shape, rois = options["shape"], options["rois"]
    n_rois = rois[0] * rois[1]
    n = a.shape[0]
    u = np.zeros((n, n_rois, 2))
    counts = np.zeros((n, n_rois), dtype=np.int64)
    positions = np.zeros((n, n_rois, 2))
    vectors = []
    kw = {k: v for k, v in options.items() if k not in ("shape", "keep_vectors")}
    for k in range(n):
        i = start + k
        # Noise from (seed, global index): the same whatever the chunking
        rng = np.random.default_rng([seed, i])
        xy_a, xy_b = pattern_vectors(a[k], b[k], rng=rng, index=i, **kw)
        u[k], counts[k], positions[k] = roi_average(xy_a, xy_b, shape, rois)
        if options["keep_vectors"]:
            vectors.append(np.concatenate([xy_a, xy_b], axis=1))
    return u, counts, positions, vectors


def _as_stack(patterns, name):
    import dask.array as da

    arr = patterns if isinstance(patterns, da.Array) else np.asarray(patterns)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ValueError(
            f"{name} patterns must be an array (N, rows, columns), not of shape {arr.shape}"
        )
    return arr


def measure_displacements(
    simulated,
    experimental,
    rois: tuple[int, int] = (8, 8),
    binning: int = 1,
    noise: float = 0.0,
    blur: float = 0.0,
    dic: str = "auto",
    max_roi_crossings: int | None = 2,
    forward_backward: float | None = 0.2,
    robust: float | None = 3.0,
    features_per_roi: int = 8,
    window: int = 11,
    levels: int = 3,
    smoothing: float = 0.7,
    seed: int | None = None,
    keep_vectors: bool = False,
    chunk_size: int | None = None,
) -> DisplacementField:
    """Measure per-ROI displacements from simulated to experimental patterns.

    Parameters
    ----------
    simulated, experimental
        Patterns (N, rows, columns), or one pattern (rows, columns), as
        NumPy or Dask arrays of one shape. Simulated pattern i is compared
        with experimental pattern i.
    rois
        ROI grid (n, m), see :func:`roi_edges`.
    binning
        Bin both patterns by this factor before detecting and tracking
        features (the paper uses 4 on large patterns). Results are in
        full-resolution pixels; see :func:`bin_pattern` for the edges.
    noise
        Standard deviation of zero-mean Gaussian noise added to each
        simulated pattern at full resolution, as a fraction of that
        pattern's intensity standard deviation (the paper's
        preprocessing). Pattern i draws its noise from
        ``np.random.default_rng([seed, i])``, so it is the same for any
        chunking and different for every pattern.
    blur
        Gaussian sigma, in full-resolution pixels, applied to each
        simulated pattern before the noise: the detector's point spread.
        Simulated patterns are sharper than experimental ones, and with
        LK's finite windows the difference in sharpness shifts vectors
        randomly by ~0.1 px (measured at a sigma of 1 px); matching it
        removes that.
    dic
        "auto", "opencv" or "skimage", see :func:`resolve_backend`.
    max_roi_crossings
        Drop vectors whose endpoints are more than this many ROIs apart
        (the paper's rule, see :func:`filter_vectors`); None: off.
    forward_backward
        Track each feature back from B to A and drop it if it misses its
        start by more than this many (full-resolution) pixels; None: off.
    robust
        Per-ROI median/MAD rejection threshold (see
        :func:`filter_vectors`); None: off. With this and
        *forward_backward* off, only the paper's outlier rule is used.
    features_per_roi
        Most Shi-Tomasi features taken in each ROI.
    window
        LK window side in tracking (binned) pixels, odd. Larger windows
        average noise better; smaller ones follow varying displacements
        better.
    levels
        Highest LK pyramid level (0: none). Lowered so that the coarsest
        level stays at least two windows wide: on smaller levels LK can
        lock onto a distant band, consistently both ways.
    smoothing
        Gaussian sigma in tracking pixels applied to both patterns. It
        removes detail near the Nyquist frequency, which aliases in
        simulated patterns and biases bilinear LK (halving a 0.03 px bias
        at 0.2 px shifts).
    seed
        Seed of the noise. None draws one, so that repeated calls differ.
    keep_vectors
        Keep every pattern's vectors in :attr:`DisplacementField.vectors`
        (to plot them as in the paper's Fig. 2A).
    chunk_size
        Patterns per task. Default: the chunks of Dask input, else a few
        tasks per core. The result does not depend on it.

    Returns
    -------
    field
        :class:`DisplacementField`.

    Raises
    ------
    ValueError
        For patterns of different shapes, NaN, infinite or constant
        patterns, an ROI grid too fine for the pattern size, or when no
        vector survives in any pattern.
    ImportError
        For ``dic="opencv"`` without OpenCV.

    Warns
    -----
    UserWarning
        When ROIs got no vector in any pattern (their weight is zero) or
        patterns gave no vector at all (they add zero to the mean field).

    Notes
    -----
    Each vector is reported at the point where LK measured it: linearised,
    LK returns the displacement over its window weighted by the local
    structure tensors, which belongs at the structure-weighted centre of
    the window rather than at the feature (exact for a dilation, to first
    order). ``u`` and ``positions`` use that point as the A endpoint.

    Patterns are processed in blocks with :func:`dask.compute`, so the
    active Dask scheduler runs them: threads by default, or a
    ``dask.distributed`` cluster once a ``Client`` exists. Results are
    identical for any scheduler and chunking.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy import ndimage
    >>> from kikuchipy_geomdic.patterns.displacement import measure_displacements
    >>> rng = np.random.default_rng(1)
    >>> a = ndimage.gaussian_filter(rng.random((2, 64, 64)), (0, 2, 2))
    >>> b = ndimage.shift(a, (0, 0, 0.8), mode="nearest")  # 0.8 px in x
    >>> field = measure_displacements(a, b, rois=(4, 4), dic="skimage", seed=0)
    >>> field.u.shape, field.residual.shape, field.weights.shape
    ((2, 16, 2), (32,), (16,))
    >>> np.round(field.mean.mean(axis=0), 2)
    array([0.8, 0. ])
    """
    import dask
    import dask.array as da

    backend = resolve_backend(dic)
    a = _as_stack(simulated, "Simulated")
    b = _as_stack(experimental, "Experimental")
    if a.shape != b.shape:
        raise ValueError(
            f"Simulated patterns have shape {a.shape} but experimental patterns "
            f"{b.shape}; they must match"
        )
    n = a.shape[0]
    if n == 0:
        raise ValueError("No patterns given")
    shape, rois = _check_grid(a.shape[1:], rois)
    _check_tracking(shape, rois, binning, window)
    if noise < 0 or not np.isfinite(noise):
        raise ValueError(f"noise must be a non-negative fraction, not {noise}")
    if seed is None:
        seed = int(np.random.SeedSequence().entropy % 2**63)
    elif int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer or None, not {seed}")
    if chunk_size is not None:
        chunks = int(chunk_size)
    elif isinstance(b, da.Array) or isinstance(a, da.Array):
        chunks = (b if isinstance(b, da.Array) else a).chunks[0]
    else:
        chunks = max(1, min(32, math.ceil(n / (4 * (os.cpu_count() or 1)))))
    a = da.asarray(a).rechunk((chunks, -1, -1))
    b = da.asarray(b).rechunk((chunks, -1, -1))
    options = dict(
        shape=shape,
        rois=rois,
        binning=int(binning),
        noise=float(noise),
        dic=backend,
        max_roi_crossings=max_roi_crossings,
        forward_backward=forward_backward,
        robust=robust,
        features_per_roi=int(features_per_roi),
        window=int(window),
        levels=int(levels),
        smoothing=float(smoothing),
        blur=float(blur),
        keep_vectors=bool(keep_vectors),
    )
    starts = np.concatenate([[0], np.cumsum(a.chunks[0])[:-1]])
    tasks = [
        dask.delayed(_measure_block, pure=True)(blk_a, blk_b, int(s), seed, options)
        for blk_a, blk_b, s in zip(a.to_delayed().ravel(), b.to_delayed().ravel(), starts)
    ]
    results = dask.compute(*tasks)
    u = np.concatenate([r[0] for r in results])
    counts = np.concatenate([r[1] for r in results])
    positions = np.concatenate([r[2] for r in results])
    vectors = tuple(v for r in results for v in r[3]) if keep_vectors else None
    field = DisplacementField(u, counts, positions, shape, rois, backend, vectors)

    if counts.sum() == 0:
        raise ValueError(
            "No displacement vector survived in any pattern: the patterns have too "
            "few trackable features, or they differ too much (try fewer ROIs, "
            "binning, or check that the patterns match)"
        )
    empty_patterns = np.flatnonzero(counts.sum(axis=1) == 0)
    if empty_patterns.size:
        warnings.warn(
            f"{empty_patterns.size} of {n} patterns gave no displacement vector "
            f"(first: {empty_patterns[:5].tolist()}); they add zero to the mean field",
            UserWarning,
            stacklevel=2,
        )
    empty_rois = np.flatnonzero(field.total_counts == 0)
    if empty_rois.size:
        warnings.warn(
            f"{empty_rois.size} of {counts.shape[1]} ROIs got no displacement vector "
            f"(ROIs {empty_rois.tolist()}); their weight is zero",
            UserWarning,
            stacklevel=2,
        )
    return field
