"""Per-pattern orientation refinement at a fixed, calibrated geometry.

Each pattern's orientation is refined by Gauss-Newton on its pixel
intensities: the experimental pattern ``e`` is fitted as
``a * S(q) + b``, with ``S(q)`` the pattern projected from the master
pattern at orientation ``q`` and the pattern's own PC, and a gain ``a``
and offset ``b``. Minimising that residual over ``a`` and ``b`` is
maximising the squared normalised cross-correlation, so the optimum is
kikuchipy's ``refine_orientation`` optimum (same projection, same bilinear
interpolation of the master pattern, same per-hemisphere rescaling), but
reached with a handful of projections instead of Nelder-Mead's hundred.

The derivative of ``S`` with respect to a small rotation ``w`` of the
crystal (``q -> exp(w) q``, kikuchipy's active quaternion convention, so
every crystal direction ``d`` moves by ``w x d``) is analytic: the
gradient of the bilinear interpolant of the master pattern, chained
through the square Lambert projection, gives ``dS/dw = d x grad I(d)``.
It is the exact derivative of the model kikuchipy evaluates (almost
everywhere), so the fixed point is the same.

Coarse to fine: the first levels run on patterns binned by 4 and 2
against a master pattern smoothed to the binned pixel size, which widens
the basin to starts several degrees off (a pattern too small to bin by 4
takes the heavy smoothings binned by 2); the last level runs at full
resolution. The per-pattern kernel is plain array code compiled with
numba (``nogil``, its step sums on vector registers), so dask's threads
run chunks in parallel.

Layout: the solver is this module's (:func:`pyramid_levels`, the binning
schedule; :func:`refine_patterns`, a stack of patterns with one PC each,
and :func:`refine_arrays` on plain arrays); it also presents, from the
private modules that hold them, :func:`master_pattern_arrays` (what the
kernel projects from), :func:`project_patterns` (the kernel's own
projection, for checks), :func:`neighbour_seeds` with
:func:`poor_points` and :func:`neighbour_disagreement` (what finds
misindexed starts on a map) and
:func:`compare_variants` (which pseudo-symmetric variant a pattern
shows). The numba kernels are in ``_lambert`` (projection) and
``_gauss_newton`` (the per-pattern step).

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation
from scipy import ndimage

from kikuchipy_geomdic.indexing._gauss_newton import _refine_stack
from kikuchipy_geomdic.indexing._lambert import _stack_ncc
from kikuchipy_geomdic.indexing._projection import (
    MasterPatternArrays,
    detector_matrix,
    detector_pcs,
    master_pattern_arrays,
    project_arrays,
    project_derivatives,
    project_patterns,
)
from kikuchipy_geomdic.indexing._seeds import neighbour_disagreement, neighbour_seeds, poor_points
from kikuchipy_geomdic.indexing._variant_comparison import (
    VariantComparison,
    compare_variants,
    standardise,
)
from kikuchipy_geomdic.patterns.preprocessing import bin_pattern

__all__ = [
    "MasterPatternArrays",
    "OrientationResult",
    "master_pattern_arrays",
    "pyramid_levels",
    "project_patterns",
    "refine_patterns",
    "refine_arrays",
    "project_arrays",
    "project_derivatives",
    "detector_matrix",
    "detector_pcs",
    "poor_points",
    "neighbour_disagreement",
    "neighbour_seeds",
    "VariantComparison",
    "compare_variants",
    "standardise",
]

#: Smallest side (px) of a binned pattern in the coarse-to-fine schedule:
#: below it too few bands remain to fix an orientation.
MIN_COARSE_SIDE = 24

#: Largest rotation (degrees) of one Gauss-Newton step at each level,
#: coarse first: a step beyond the basin is shortened, not taken.
MAX_STEP = 3.0

#: The last level stops when its step is below this angle (degrees) ...
TOLERANCE = 1e-3

#: ... a coarse one below this: the next level refines further.
COARSE_TOLERANCE = 0.1

#: Smoothing (degrees, Gaussian sigma on the sphere) of the master pattern
#: at each binning: heavy smoothing first widens the basin to starts
#: several degrees off; more than this drowned starts under 2 degrees in
#: featureless patterns (measured on 120 px Si patterns, dose 300: with
#: 6 then 3 degrees at binning 4, 96 % of starts of 4 degrees RMS and
#: all of 2 degrees RMS reached the truth; with 10, 5, 2.5 degrees 94 %
#: of the 2-degree starts did).
SMOOTHING = {4: (6.0, 3.0), 2: (1.0,), 1: (0.0,)}

#: Evaluations (projections) allowed per level, coarse and last: on
#: heavily smoothed, noisy patterns the coarse steps dither at the
#: tolerance, and the next level starts well inside its basin anyway.
MAX_EVALUATIONS = (12, 30)


def pyramid_levels(shape: tuple[int, int], levels: Sequence[int] | None = None) -> tuple[int, ...]:
    """Return the binning factors of the coarse-to-fine schedule.

    Parameters
    ----------
    shape
        Pattern shape (rows, columns).
    levels
        Binning factors, coarse first, ending with 1. Default: 4, 2, 1,
        keeping only factors that divide the shape and leave at least
        :data:`MIN_COARSE_SIDE` pixels on the shorter side.

    Returns
    -------
    levels
        Tuple of binning factors ending with 1.

    Examples
    --------
    >>> from kikuchipy_geomdic.indexing.orientation import pyramid_levels
    >>> pyramid_levels((120, 120)), pyramid_levels((60, 60)), pyramid_levels((30, 30))
    ((4, 2, 1), (2, 1), (1,))
    """
    if levels is None:
        levels = [b for b in (4, 2) if min(shape) // b >= MIN_COARSE_SIDE] + [1]
    levels = tuple(int(b) for b in levels)
    if not levels or levels[-1] != 1 or any(b < 1 for b in levels):
        raise ValueError(f"levels must be positive binning factors ending with 1, not {levels}")
    bad = [b for b in levels if shape[0] % b or shape[1] % b]
    if bad:
        raise ValueError(f"Binning factors {bad} do not divide the pattern shape {shape}")
    return levels


@dataclass(frozen=True)
class OrientationResult:
    """Refined orientations of a stack of patterns.

    Attributes
    ----------
    rotations
        Refined :class:`~orix.quaternion.Rotation` (N,).
    scores
        NCC with the pattern simulated at the refined orientation (NaN
        where the pattern holds NaN).
    evaluations
        Pattern projections at full resolution (the cost; coarse levels
        are cheaper by the square of their binning).
    converged
        Whether the last level's step fell below :data:`TOLERANCE`.
    """

    rotations: Rotation
    scores: np.ndarray
    evaluations: np.ndarray
    converged: np.ndarray


#: Decimals (px) to which the coarse stages round each pattern's smoothing
#: width before grouping patterns of equal width into one filter call
PX_DECIMALS = 2


def _stage(
    patterns, q, pcs, om, arrays, binning, sigma, max_step, max_evaluations=None, accelerate=False,
    binned=None,
):  # fmt: skip
    """One stage of the schedule: every pattern binned by *binning* (or
    given so, *binned*), both it and the master pattern smoothed by
    *sigma* degrees; at most *max_evaluations* projections per pattern
    (default :data:`MAX_EVALUATIONS`), Gauss-Newton steps accelerated or
    not (``_gauss_newton``)."""
    if max_evaluations is None:
        max_evaluations = MAX_EVALUATIONS[binning == 1]
    n, shape = patterns.shape[0], patterns.shape[1:]
    b = binning
    level = binned if binned is not None else _binned(patterns, b)
    if sigma > 0:
        # The same blur on both sides, so that the smoothed optimum is the
        # orientation's (a sharp pattern against a smoothed simulation
        # pulled it degrees away): sigma in binned pixels at the PC, where
        # one pixel spans 1 / (pcz * rows) rad. Each pattern by its own
        # pcz (rounded to groups), not the batch's median: a point's result
        # must not depend on the chunk it is refined in
        px = np.round(np.deg2rad(sigma) * pcs[:, 2] * shape[0] / b, PX_DECIMALS)
        level = np.array(level, dtype=np.float32)
        for w in np.unique(px):
            i = px == w
            level[i] = ndimage.gaussian_filter(level[i], (0, w, w), mode="nearest")
    level = np.ascontiguousarray(level.reshape(n, -1), dtype=np.float32)
    mp = arrays.smoothed(sigma)
    return _refine_stack(
        level,
        np.ascontiguousarray(q),
        np.ascontiguousarray(pcs),
        shape[0] // b,
        shape[1] // b,
        om,
        mp.hemispheres,
        float(mp.scale),
        max_evaluations,
        np.deg2rad(TOLERANCE if b == 1 else COARSE_TOLERANCE),
        np.deg2rad(max_step),
        accelerate,
    )


def _binned(patterns, binning):
    """The patterns binned by *binning* as float32 (as they are at 1)."""
    return bin_pattern(patterns, binning, np.float32) if binning > 1 else patterns


def _schedule(shape, levels):
    """(binning, smoothing) of each stage, coarse first.

    The smoothings of binnings coarser than the coarsest level (a pattern
    too small for them) run first at the coarsest binned level: they are
    what widens the basin to starts several degrees off (measured on
    ``bench_orientations.py far`` at 60 px, binned by 2 at most: 116 of
    225 points more than 1 deg wrong, 79 of them not flagged, with only
    the binning's own 1 deg; none with 6, 3 and 1 deg, in an eighth of
    the time). Without a binned level the schedule is the last stage."""
    levels = pyramid_levels(shape, levels)
    stages = [(b, s) for b in levels for s in SMOOTHING.get(b, (0.0,))]
    if levels[0] > 1:
        coarser = sorted((b for b in SMOOTHING if b > levels[0]), reverse=True)
        stages = [(levels[0], s) for b in coarser for s in SMOOTHING[b]] + stages
    return stages


def refine_patterns(
    patterns: np.ndarray,
    rotations: Rotation,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern | MasterPatternArrays,
    energy: float = 20.0,
    levels: Sequence[int] | None = None,
    max_step: float = MAX_STEP,
) -> OrientationResult:
    """Refine the orientation of each pattern of a stack at its PC.

    Parameters
    ----------
    patterns
        Patterns (N, rows, columns), any real type.
    rotations
        Starting orientations (N,).
    detector
        Detector of the patterns' shape with one PC or N PCs (e.g. the
        calibrated detector's PCs at the patterns' map points).
    master_pattern
        Lambert master pattern (or its :func:`master_pattern_arrays`).
    energy
        Beam energy in kV.
    levels
        Binning factors of the coarse-to-fine schedule
        (:func:`pyramid_levels`).
    max_step
        Largest rotation (degrees) of one step.

    Returns
    -------
    result
        :class:`OrientationResult`.

    Examples
    --------
    Four patterns of a synthetic silicon map, from starts 2 degrees off:

    >>> import numpy as np
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.validation.orientations import perturb_rotations
    >>> from kikuchipy_geomdic.indexing.orientation import refine_patterns
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(60, 60), seed=0)
    >>> rng = np.random.default_rng(0)
    >>> start = perturb_rotations(sm.xmap.rotations, 2.0, rng)
    >>> res = refine_patterns(sm.signal.data.reshape(4, 60, 60), start, sm.detector,
    ...                       sm.master_pattern, 20)
    >>> err = np.rad2deg((~sm.xmap.rotations * res.rotations).angle)
    >>> bool(err.max() < 0.01), bool(res.scores.min() > 0.99)
    (True, True)
    """
    patterns = np.asarray(patterns)
    if patterns.ndim != 3:
        raise ValueError(
            f"patterns must be a stack (N, rows, columns), not of shape {patterns.shape}"
        )
    n = patterns.shape[0]
    shape = patterns.shape[1:]
    if tuple(detector.shape) != shape:
        raise ValueError(
            f"The detector's shape {detector.shape} differs from the patterns' {shape}"
        )
    q = np.ascontiguousarray(Rotation(rotations).flatten().data, dtype=np.float64)
    if q.shape[0] != n:
        raise ValueError(f"{q.shape[0]} starting orientations for {n} patterns")
    arrays = master_pattern_arrays(master_pattern, energy)
    return refine_arrays(
        patterns, q, detector_pcs(detector, n), detector_matrix(detector), arrays, levels, max_step
    )


def _coarse_stages(patterns, quaternions, pcs, om, arrays, levels, max_step):
    """The coarse stages of :func:`refine_arrays` alone, scored at full
    resolution.

    Each start runs the schedule without its last (full-resolution)
    stage; the result is then the better, by full-resolution NCC, of
    where it ended and its start (the coarse stages never make a start
    worse). For a caller that refines several candidates per pattern and
    runs the last stage only from where they agree. Arguments as
    :func:`refine_arrays`'s; the result an :class:`OrientationResult`
    with the full-resolution NCC and ``converged`` False (the last stage
    did not run).
    """
    patterns, q0, pcs, om = _as_stack(patterns, quaternions, pcs, om)
    schedule = _schedule(patterns.shape[1:], levels)[:-1]
    q, _, _, evaluations = _descend(patterns, q0, pcs, om, arrays, schedule, max_step)
    ncc0 = _full_ncc(patterns, q0, pcs, om, arrays)
    if not schedule:
        # No coarse stage (seeds next to their optimum): the seeds scored
        zero = np.zeros(len(q0), dtype=bool)
        return OrientationResult(Rotation(q0), ncc0, evaluations + 1, zero)
    ncc = _full_ncc(patterns, q, pcs, om, arrays)
    evaluations += 2
    worse = ncc0 > ncc
    q = np.where(worse[:, None], q0, q)
    ncc = np.where(worse, ncc0, ncc)
    return OrientationResult(Rotation(q), ncc, evaluations, np.zeros(len(q), dtype=bool))


def _fine_stage(patterns, quaternions, pcs, om, arrays, max_step, max_evaluations):
    """The full-resolution stage alone with accelerated steps, from
    *quaternions*: for candidates started next to their optimum (the
    variants of a refined orientation). An :class:`OrientationResult`."""
    patterns, q0, pcs, om = _as_stack(patterns, quaternions, pcs, om)
    q, ncc, k, conv = _stage(
        patterns, q0, pcs, om, arrays, 1, 0.0, max_step, max_evaluations, accelerate=True
    )
    q = np.where(q[:, :1] < 0, -q, q)
    return OrientationResult(Rotation(q), ncc, k.astype(np.float64), conv)


def _as_stack(patterns, quaternions, pcs, om):
    """Patterns (N, rows, columns), starting quaternions (N, 4), PCs (N, 3)
    and the detector matrix as the kernel takes them."""
    patterns = np.asarray(patterns)
    n = patterns.shape[0]
    q = np.ascontiguousarray(quaternions, dtype=np.float64).reshape(n, 4)
    pcs = np.ascontiguousarray(pcs, dtype=np.float64).reshape(n, 3)
    return patterns, q, pcs, np.ascontiguousarray(om, dtype=np.float64)


def _descend(patterns, q, pcs, om, arrays, schedule, max_step):
    """Run the stages of *schedule* from *q*: return the quaternions, NCCs
    and convergence of the last stage, and the evaluations in
    full-resolution equivalents (a stage binned by b costs 1 / b**2)."""
    ncc = conv = None
    evaluations = np.zeros(patterns.shape[0], dtype=np.float64)
    binned = {}  # each binning once, for all its smoothings
    for b, sigma in schedule:
        if b not in binned:
            binned[b] = _binned(patterns, b)
        q, ncc, k, conv = _stage(
            patterns, q, pcs, om, arrays, b, sigma, max_step, binned=binned[b]
        )  # fmt: skip
        evaluations += k / b**2
    return q, ncc, conv, evaluations


def _full_ncc(patterns, q, pcs, om, arrays):
    """NCC of each pattern with its projection at *q*, full resolution."""
    n, shape = patterns.shape[0], patterns.shape[1:]
    return _stack_ncc(
        np.ascontiguousarray(patterns.reshape(n, -1)), np.ascontiguousarray(q), pcs, shape[0],
        shape[1], om, arrays.hemispheres, float(arrays.scale),
    )  # fmt: skip


def refine_arrays(
    patterns: np.ndarray,
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
    levels: Sequence[int] | None = None,
    max_step: float = MAX_STEP,
) -> OrientationResult:
    """:func:`refine_patterns` on plain arrays, for map chunks: the detector
    as its PCs and matrix, the master pattern as its arrays.

    Parameters
    ----------
    patterns, quaternions
        Patterns (N, rows, columns) and starting quaternions (N, 4).
    pcs, om
        Bruker PCs (N, 3) and the detector-to-sample matrix
        (:func:`detector_matrix`).
    arrays
        :func:`master_pattern_arrays` of the master pattern.
    levels, max_step
        See :func:`refine_patterns`.

    Returns
    -------
    result
        :class:`OrientationResult`.
    """
    patterns, q0, pcs, om = _as_stack(patterns, quaternions, pcs, om)
    schedule = _schedule(patterns.shape[1:], levels)
    q, ncc, conv, evaluations = _descend(patterns, q0, pcs, om, arrays, schedule, max_step)
    if len(schedule) > 1:
        # The coarse stages never make a start worse: where the start
        # itself correlates better, the last stage runs from it instead
        start = _full_ncc(patterns, q0, pcs, om, arrays)
        evaluations += 1
        worse = np.flatnonzero(start > ncc)
        if worse.size:
            q2, ncc2, k2, conv2 = _stage(
                patterns[worse], q0[worse], pcs[worse], om, arrays, 1, 0.0, max_step
            )
            better = ncc2 > ncc[worse]
            q[worse[better]], ncc[worse[better]] = q2[better], ncc2[better]
            conv[worse[better]] = conv2[better]
            evaluations[worse] += k2
    # One sign per rotation, as orix writes and reads them back (a >= 0)
    q = np.where(q[:, :1] < 0, -q, q)
    return OrientationResult(Rotation(q), ncc, evaluations, conv)
