"""The systematic part of the full field's standard errors: what the
patterns' shared misfit does to the geometry, measured by solving the
converged linear system on separate parts of the data. On one crystal:
regions of the detector (:func:`_region_errors`), the full field's pixels
or the DIC stage's ROIs grouped into the detector's quadrants
(:func:`_quadrants`). On a polycrystal: its grains, each left out in
turn (:func:`_grain_errors`, :func:`_grains`).

A misfit every pattern shares (band profiles changed by the processing,
another simulator's master pattern, a CIF whose lattice is not the
crystal's, a ghost of the static background) biases the geometry the
same way in every pattern, so no variance over the patterns sees it, and
on one crystal it does not average out. It is not uniform over the
detector, though: the regions, each fitted alone, pull the geometry
apart by more than their noise allows. That excess spread is the
systematic error reported beside the statistical one. On a polycrystal
the misfit follows the orientation: a grain's patterns share one bias,
so a map of few grains averages few biases, while the variance over its
patterns counts each pattern as independent. The geometry's spread over
the solutions that leave one grain out each (a jackknife over grains)
sees the grains' biases, and shrinks as the map's grains grow in number,
as the bias of their mean does.

Layer 6 (calibration): plain arrays in and out; imports only
:mod:`~kikuchipy_geomdic.calibration.solve` and
:mod:`~kikuchipy_geomdic.indexing.variants`' quaternion helpers.
"""

from __future__ import annotations

import numpy as np

from kikuchipy_geomdic.calibration.solve import JointSystem, solve_joint
from kikuchipy_geomdic.indexing.variants import TOLERANCE, _nearest

#: Detector regions (rows, columns) of the systematic error: quadrants,
#: each still spanning the pattern centre's neighbourhood and a corner.
REGIONS = (2, 2)

#: The prior variance of the PC (:func:`_with_prior`) counts as the
#: evidence of this many parts (grains, or the detector's quadrants) beside
#: the spread over the map's own: the spread of six grains or of four
#: quadrants is itself too uncertain to stand alone (six-grain maps,
#: another simulator's data: 9 of 225 PC errors beyond 3 of its standard
#: errors, up to 7.0; a held-out domain map of 60 px: pcy at 4.5), the
#: prior in full as a floor too wide (RMS error / sigma 0.62 and 0.41).
#: Chosen on seeds 0-2 of the envelope's polycrystals (RMS 0.75, largest
#: 2.6), held on seeds 3-4 (0.83, 2.7); one part instead left a 16-grain
#: map with a detector shadow at 3.3. At 121 grains the spread nearly alone.
PRIOR_PARTS = 2.0

#: :data:`PRIOR_PARTS` on one crystal, where the prior is what the DIC
#: stage's patterns determine with a free rotation each: wider than the
#: crystal model's by design (no tie to one parent), it is an upper scale
#: rather than a second estimate, and counts as a quarter of a quadrant.
#: At two parts the envelope's 55 domain maps' PC errors had an RMS of
#: 0.50 of their standard errors (94 % within one), the 54 single Ni
#: crystals' 0.67; at a quarter 0.61 and 0.71, none beyond 3 (largest
#: 2.67, 2.80); without the prior a 2 mm domain map at 4.8. Chosen on
#: seeds 0, 1 and 3 of the base cell and ten edges, held on 2 and 4
#: (``experiments/one_crystal_parts.py``).
CRYSTAL_PRIOR_PARTS = 0.25

#: Degrees of freedom of the grains' spread at least (a map of about
#: four grains of equal weight): its variance is scaled by t's,
#: nu / (nu - 2), which grows without bound below.
MIN_DOF = 3.0


def _quadrants(shape: tuple[int, int], repeat: int = 1) -> np.ndarray:
    """Region label (P,) of each of a row-major grid's *shape* cells (pixels
    or ROIs), each repeated *repeat* times (an ROI's two components)."""
    ny, nx = shape
    rows = np.minimum(np.arange(ny) * REGIONS[0] // ny, REGIONS[0] - 1)
    cols = np.minimum(np.arange(nx) * REGIONS[1] // nx, REGIONS[1] - 1)
    return np.repeat((rows[:, None] * REGIONS[1] + cols[None, :]).ravel(), repeat)


def _region_errors(
    residual: np.ndarray,
    jg: np.ndarray,
    jr: np.ndarray,
    weights: np.ndarray,
    offsets: np.ndarray,
    prior: float | None,
    common: bool,
    region: np.ndarray,
    geometry_prior: np.ndarray | None = None,
    geometry_offsets: np.ndarray | None = None,
    normal: JointSystem | None = None,
) -> np.ndarray:
    """Systematic standard errors (K,) of the geometry from the spread of
    its solutions on the detector's :data:`REGIONS`.

    Each region's solution ``d_r`` and covariance ``C_r`` come from the
    linear system of all the pixels (*residual* (N, P), Jacobians
    *jg* (N, P, K) and *jr* (N, P, 3), *weights* (N, P), the orientation
    prior's *offsets* and *prior*, *common* rotation, the geometry's
    *geometry_prior* and *geometry_offsets*) with
    the pixels (or components) outside the *region* (P,, labels from
    :func:`_quadrants`) left out; ``d_0``, ``C_0`` from all of them. Where
    the model fits, ``d_r - d_0`` scatters with covariance
    ``C_r - C_0``; the excess, ``e = mean_r((d_r - d_0)^2 - (C_r - C_0))``,
    is the regions' own biases' scatter, and the whole detector's bias,
    their mean, has the systematic variance ``max(0, e) / (R - 1)`` per
    parameter for *R* regions. *normal*: the whole detector's normal
    equations if they were built (:meth:`JointSystem.build` of these
    arguments), not built again.
    """
    kw = dict(
        prior=prior,
        offsets=offsets,
        common=common,
        geometry_prior=geometry_prior,
        geometry_offsets=geometry_offsets,
    )
    if normal is None:
        all_ = solve_joint(jg, jr, residual, weights, **kw)
    else:
        all_ = normal.solve(residual, offsets, geometry_offsets=geometry_offsets)
    excess = []
    for r in range(REGIONS[0] * REGIONS[1]):
        # The region's own pixels: the others' weights would be zero, and
        # building on all of them cost four whole systems more
        sel = region == r
        upd = solve_joint(jg[:, sel], jr[:, sel], residual[:, sel], weights[:, sel], **kw)
        d = upd.delta - all_.delta
        v = np.diag(upd.covariance) - np.diag(all_.covariance)
        excess.append(d**2 - np.clip(v, 0, None))
    # The regions' biases scatter about the whole detector's; the whole
    # detector's own is their mean's, a (R - 1)th of that scatter
    n = REGIONS[0] * REGIONS[1]
    return np.sqrt(np.clip(np.sum(excess, axis=0) / (n * (n - 1)), 0, None))


def _grains(q: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Grain label (N,) of each orientation *q* (N, 4): the orientations
    within :data:`~kikuchipy_geomdic.indexing.variants.TOLERANCE` of a
    grain's first one modulo the rotations *group* (m, 4; the crystal's
    proper rotations, times the variant operators if there are any)."""
    n = len(q)
    grain = np.full(n, -1)
    cos_tol = np.cos(np.deg2rad(TOLERANCE) / 2)
    for i in range(n):
        if grain[i] >= 0:
            continue
        free = np.flatnonzero(grain < 0)
        near = _nearest(q[free], q[i], group)[1] >= cos_tol
        grain[free[near]] = grain.max() + 1
    return grain


def _grain_errors(
    system: JointSystem, residual: np.ndarray, offsets: np.ndarray, grains: np.ndarray
) -> tuple[np.ndarray, float]:
    """Systematic standard errors (K,) of the geometry from its spread over
    the solutions that leave one of the *grains* (N,, from :func:`_grains`)
    out, of the free orientation model's *system* (no common rotation), for
    its *residual* (N, M) and rotation *offsets* (N, 3).

    Each solution comes from the sum of the other grains' reduced (Schur
    complement) normal equations, so no pattern is fitted again. The
    jackknife variance ``(G - 1) / G sum_g (d_g - mean)^2`` over the *G*
    grains estimates the whole map's variance with what the patterns of a
    grain share in it; where it exceeds the solve's own (cluster-robust
    over patterns) variance, the excess is the systematic part. Grains
    whose removal leaves a singular system are kept in; zero for fewer
    than three grains. Also returns the effective number of grains, the
    fewest of any parameter (grains of unequal weight count as fewer).
    """
    k = system.k
    b = np.asarray(residual, dtype=np.float64)
    ag, ar = system.products(b)
    ar = ar + system.prior_precision * offsets
    a_inv_r = np.einsum("nij,nj->ni", system.a_inv, ar)
    grad = ag - np.einsum("nki,nk->ni", system.bb, a_inv_r)
    full = system.full
    scale = np.outer(full, full)
    labels = np.unique(grains)
    s_g = np.array([system.s_pattern[grains == g].sum(axis=0) for g in labels]) / scale
    g_g = np.array([grad[grains == g].sum(axis=0) for g in labels]) / full
    # The geometry's prior (the lattice's) holds every grain's solution
    s_all = s_g.sum(axis=0) + np.diag(system.geometry_precision) / scale
    g_all = g_g.sum(axis=0)
    d = []
    for s_i, g_i in zip(s_g, g_g):
        s = s_all - s_i
        mu, vec = np.linalg.eigh((s + s.T) / 2)
        if not mu.min() > 1e-10 * max(mu.max(), 1.0):
            continue
        d.append(-((vec / mu) @ (vec.T @ (g_all - g_i))) / full)
    w = np.clip(np.diagonal(s_g, axis1=1, axis2=2), 0, None)
    effective = w.sum(axis=0) ** 2 / np.maximum((w**2).sum(axis=0), 1e-300)
    if len(d) < 3:
        return np.zeros(k), float(effective.min())
    d = np.array(d)
    n = len(d)
    jackknife = (n - 1) / n * ((d - d.mean(axis=0)) ** 2).sum(axis=0)
    # Estimated from few grains, the variance has few degrees of freedom
    # and the error over its square root spreads as Student's t: scaled
    # by t's variance, nu / (nu - 2), its RMS is 1 (six grains of unequal
    # size sharing a bias each: RMS 1.41 unscaled, 6 % beyond 3). Grains
    # of unequal weight count as fewer: (sum w)^2 / sum w^2 of each
    # parameter's information
    nu = np.maximum(effective - 1, MIN_DOF)
    model = np.diag(system.solve(b, offsets).covariance)
    return np.sqrt(np.clip(jackknife * nu / (nu - 2) - model, 0, None)), float(effective.min())


def _with_prior(se: float, prior: float, parts: float, prior_parts: float = PRIOR_PARTS) -> float:
    """The standard error *se* whose systematic part comes from the spread
    over *parts* parts of the map (its effective grains,
    :func:`_grain_errors`, or the detector's quadrants), its variance
    raised towards the *prior* one where that is larger, with the weight
    of *prior_parts* parts (:data:`PRIOR_PARTS`, :data:`CRYSTAL_PRIOR_PARTS`)
    against the spread's degrees of freedom: a shrinkage estimate of the
    variance, whose prior fades as the parts grow in number (and is all
    there is from one part)."""
    nu = max(parts - 1, 0.0)
    weight = prior_parts / (nu + prior_parts)
    return float(np.sqrt(se**2 + weight * max(prior**2 - se**2, 0.0)))
