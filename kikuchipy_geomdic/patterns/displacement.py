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

The vectors of one pattern pair and the two backends are in
:mod:`~kikuchipy_geomdic.patterns.vectors`, the ROI grid, the per-ROI
filtering and averaging in :mod:`~kikuchipy_geomdic.patterns.roi`, the
preprocessing in :mod:`~kikuchipy_geomdic.patterns.preprocessing`.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass

import numpy as np

from kikuchipy_geomdic.patterns.preprocessing import _check_tracking
from kikuchipy_geomdic.patterns.roi import (
    _check_grid,
    roi_average,
    roi_centres,
    roi_edges,
    roi_index,
    roi_weights,
)
from kikuchipy_geomdic.patterns.vectors import _DIC_DEFAULTS, pattern_vectors, resolve_backend

__all__ = ["DisplacementField", "measure_displacements"]

#: Start of the warning for ROIs without a vector (a pattern for
#: ``warnings.filterwarnings``): a calibration, which measures the same
#: ROIs at every step, says it once instead.
EMPTY_ROIS_WARNING = r"\d+ of \d+ ROIs got no displacement vector"


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
        """ROI edges, see :func:`~kikuchipy_geomdic.patterns.roi.roi_edges`."""
        return roi_edges(self.shape, self.rois)

    @property
    def centres(self) -> np.ndarray:
        """ROI centres (R, 2) ``(x, y)``, see
        :func:`~kikuchipy_geomdic.patterns.roi.roi_centres`."""
        return roi_centres(self.shape, self.rois)

    def roi_index(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return the ROI index of points, see
        :func:`~kikuchipy_geomdic.patterns.roi.roi_index`."""
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
    # The DIC options of one pattern pair, with the defaults that
    # pattern_vectors completes its options with
    rois: tuple[int, int] = _DIC_DEFAULTS["rois"],
    binning: int = _DIC_DEFAULTS["binning"],
    noise: float = _DIC_DEFAULTS["noise"],
    blur: float = _DIC_DEFAULTS["blur"],
    dic: str = _DIC_DEFAULTS["dic"],
    max_roi_crossings: int | None = _DIC_DEFAULTS["max_roi_crossings"],
    forward_backward: float | None = _DIC_DEFAULTS["forward_backward"],
    robust: float | None = _DIC_DEFAULTS["robust"],
    features_per_roi: int = _DIC_DEFAULTS["features_per_roi"],
    window: int = _DIC_DEFAULTS["window"],
    levels: int = _DIC_DEFAULTS["levels"],
    smoothing: float = _DIC_DEFAULTS["smoothing"],
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
        ROI grid (n, m), see :func:`~kikuchipy_geomdic.patterns.roi.roi_edges`.
    binning
        Bin both patterns by this factor before detecting and tracking
        features (the paper uses 4 on large patterns). Results are in
        full-resolution pixels; see
        :func:`~kikuchipy_geomdic.patterns.preprocessing.bin_pattern` for
        the edges.
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
        "auto", "opencv" or "skimage", see
        :func:`~kikuchipy_geomdic.patterns.vectors.resolve_backend`.
    max_roi_crossings
        Drop vectors whose endpoints are more than this many ROIs apart
        (the paper's rule, see
        :func:`~kikuchipy_geomdic.patterns.roi.filter_vectors`); None: off.
    forward_backward
        Track each feature back from B to A and drop it if it misses its
        start by more than this many (full-resolution) pixels; None: off.
    robust
        Per-ROI median/MAD rejection threshold (see
        :func:`~kikuchipy_geomdic.patterns.roi.filter_vectors`); None:
        off. With this and *forward_backward* off, only the paper's outlier
        rule is used.
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
