"""The systematic part of the full field's standard errors: what the
patterns' shared misfit does to the geometry, measured by solving the
converged linear system on separate regions of the detector
(:func:`_region_errors`), the full field's pixels or the DIC stage's ROIs
grouped into the detector's quadrants (:func:`_quadrants`).

A misfit every pattern shares (band profiles changed by the processing,
another simulator's master pattern, a CIF whose lattice is not the
crystal's, a ghost of the static background) biases the geometry the
same way in every pattern, so no variance over the patterns sees it, and
on one crystal it does not average out. It is not uniform over the
detector, though: the regions, each fitted alone, pull the geometry
apart by more than their noise allows. That excess spread is the
systematic error reported beside the statistical one.

Layer 6 (calibration): plain arrays in and out; imports only
:mod:`~kikuchipy_geomdic.calibration.solve`.
"""

from __future__ import annotations

import numpy as np

from kikuchipy_geomdic.calibration.solve import solve_joint

#: Detector regions (rows, columns) of the systematic error: quadrants,
#: each still spanning the pattern centre's neighbourhood and a corner.
REGIONS = (2, 2)


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
