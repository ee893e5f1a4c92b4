"""The systematic part of the full field's standard errors: what the
patterns' shared misfit does to the geometry, measured by solving the
converged linear system on separate parts of the data. On one crystal:
regions of the detector (:func:`_region_errors`), the full field's pixels
or the DIC stage's ROIs grouped into the detector's quadrants
(:func:`_quadrants`). On a polycrystal: groups of grains
(:func:`_grain_errors`, :func:`_grain_groups`).

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
patterns counts each pattern as independent. The grains, each group
fitted alone, pull apart by their biases.

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

#: Groups of grains of a polycrystal's systematic error at most: more
#: grains are pooled into this many groups of about equal size. Each
#: group's solution is a full-detector fit of its patterns, so its noise
#: is about this many times the whole map's variance, and the excess over
#: it is estimated within about half the whole map's variance.
GRAIN_GROUPS = 8


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
) -> np.ndarray:
    """Systematic standard errors (K,) of the geometry from the spread of
    its solutions on the detector's :data:`REGIONS`.

    Each region's solution ``d_r`` and covariance ``C_r`` come from the
    linear system of all the pixels (*residual* (N, P), Jacobians
    *jg* (N, P, K) and *jr* (N, P, 3), *weights* (N, P), the orientation
    prior's *offsets* and *prior*, *common* rotation) with the weights of
    the pixels (or components) outside the *region* (P,, labels from
    :func:`_quadrants`) set to zero; ``d_0``, ``C_0`` from all of them. Where
    the model fits, ``d_r - d_0`` scatters with covariance
    ``C_r - C_0``; the excess, ``e = mean_r((d_r - d_0)^2 - (C_r - C_0))``,
    is the regions' own biases' scatter, and the whole detector's bias,
    their mean, has the systematic variance ``max(0, e) / (R - 1)`` per
    parameter for *R* regions.
    """
    kw = dict(prior=prior, offsets=offsets, common=common)
    all_ = solve_joint(jg, jr, residual, weights, **kw)
    excess = []
    for r in range(REGIONS[0] * REGIONS[1]):
        w = np.where(region[None, :] == r, weights, 0.0)
        upd = solve_joint(jg, jr, residual, w, **kw)
        d = upd.delta - all_.delta
        v = np.diag(upd.covariance) - np.diag(all_.covariance)
        excess.append(d**2 - np.clip(v, 0, None))
    # The regions' biases scatter about the whole detector's; the whole
    # detector's own is their mean's, a (R - 1)th of that scatter
    n = REGIONS[0] * REGIONS[1]
    return np.sqrt(np.clip(np.sum(excess, axis=0) / (n * (n - 1)), 0, None))


def _grain_groups(q: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Group label (N,) of each orientation *q* (N, 4): its grain, the
    orientations within :data:`~kikuchipy_geomdic.indexing.variants.TOLERANCE`
    of a grain's first one modulo the rotations *group* (m, 4; the crystal's
    proper rotations, times the variant operators if there are any),
    pooled into at most :data:`GRAIN_GROUPS` groups of about equal size,
    the largest grains first."""
    n = len(q)
    grain = np.full(n, -1)
    cos_tol = np.cos(np.deg2rad(TOLERANCE) / 2)
    for i in range(n):
        if grain[i] >= 0:
            continue
        free = np.flatnonzero(grain < 0)
        near = _nearest(q[free], q[i], group)[1] >= cos_tol
        grain[free[near]] = grain.max() + 1
    sizes = np.bincount(grain)
    out = np.empty(n, dtype=np.int64)
    filled = np.zeros(min(len(sizes), GRAIN_GROUPS))
    for g in np.argsort(-sizes, kind="stable"):
        r = int(np.argmin(filled))
        out[grain == g] = r
        filled[r] += sizes[g]
    return out


def _grain_errors(
    system: JointSystem, residual: np.ndarray, offsets: np.ndarray, groups: np.ndarray
) -> np.ndarray:
    """Systematic standard errors (K,) of the geometry from the spread of
    its solutions on the patterns' *groups* (N,, from :func:`_grain_groups`)
    of the free orientation model's *system* (no common rotation), for its
    *residual* (N, M) and rotation *offsets* (N, 3).

    Each group's solution ``d_r`` and variance ``V_r`` (per parameter) come
    from the sum of its patterns' reduced (Schur complement) normal
    equations, so no pattern is fitted again. Groups differ in size (a
    grain of three points determines the geometry poorly), so their
    biases' variance ``tau^2`` is the random-effects (DerSimonian-Laird)
    estimate from ``Q = sum_r (d_r - d)^2 / V_r`` about the weighted mean
    ``d``, and the whole map's bias, the groups' weighted mean, has the
    variance ``tau^2 sum_r w_r^2`` with ``w_r`` the weights ``1 / V_r``
    normalised. Groups whose system is singular are left out; zero for
    fewer than two groups.
    """
    k = system.k
    b = np.asarray(residual, dtype=np.float64)
    ar = (system.jrw_t @ b[..., None])[..., 0] + system.prior_precision * offsets
    ag = (system.jgw_t @ b[..., None])[..., 0]
    a_inv_r = np.einsum("nij,nj->ni", system.a_inv, ar)
    grad = ag - np.einsum("nki,nk->ni", system.bb, a_inv_r)
    curv = system.s_pattern
    full = system.full
    factor = system.solve(b, offsets).variance_factor
    d, v = [], []
    for g in range(int(groups.max()) + 1 if groups.size else 0):
        s = curv[groups == g].sum(axis=0) / np.outer(full, full)
        mu, vec = np.linalg.eigh((s + s.T) / 2)
        if not mu.min() > 1e-10 * max(mu.max(), 1.0):
            continue
        inv = (vec / mu) @ vec.T
        d.append(-(inv @ (grad[groups == g].sum(axis=0) / full)) / full)
        v.append(factor * np.diag(inv) / full**2)
    if len(d) < 2:
        return np.zeros(k)
    d, u = np.array(d), 1 / np.array(v)
    total = u.sum(axis=0)
    mean = (u * d).sum(axis=0) / total
    q = (u * (d - mean) ** 2).sum(axis=0)
    tau2 = np.clip(q - (len(d) - 1), 0, None) / (total - (u**2).sum(axis=0) / total)
    return np.sqrt(tau2 * ((u / total) ** 2).sum(axis=0))
