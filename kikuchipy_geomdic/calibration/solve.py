"""The linear solves of one geometry update.

Two solvers, plain arrays in and out:

- :func:`solve_update`, the paper's (section 2.4, Eqs. 7-11): the
  *average* field ``b`` (2R) against a Jacobian ``J`` (2R x K, pixels per
  parameter unit) with the ROI weights (R), in the order of
  :mod:`kikuchipy_geomdic.patterns.displacement`.
- :func:`solve_joint`: every pattern's own field against the geometry
  *and* one small rotation per pattern, the rotations eliminated exactly
  (Schur complement). Averaging the fields first, as the paper does,
  attributes to the geometry whatever part of each pattern's field an
  orientation error explains (a PC shift is almost a rotation), and
  orientations indexed at a wrong geometry share such an error; the joint
  solve does not average, so it does not need the orientation errors to
  cancel.

Exact degeneracies
------------------
Some parameter combinations do not change the patterns (``tilt`` and
``sample_tilt`` enter kikuchipy's projection only as their difference):
their columns are dependent and Eq. 10 singular but for the damping.
The solve goes through the singular value decomposition instead, dropping
directions below ``rtol`` times the largest singular value: the
*minimum-norm* update in the column-normalised parameters, for the two
tilts an equal and opposite split of their difference (leave one out of
the refined parameters to keep it fixed). Dropped directions are reported
(:attr:`Update.null_space`).

Layer 6 (calibration): plain arrays in and out; imports nothing of the
package.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kikuchipy_geomdic.calibration._joint import JointSystem, JointUpdate

__all__ = [
    "Update",
    "JointUpdate",
    "JointSystem",
    "solve_update",
    "solve_joint",
    "coupling_matrix",
]


@dataclass(frozen=True)
class Update:
    """The result of one linear solve.

    Attributes
    ----------
    delta
        Parameter update (K,), in parameter units.
    singular_values
        Singular values of the weighted, column-normalised Jacobian,
        largest first.
    null_space
        (K, d) array whose columns are the unit directions, in
        column-normalised parameters, that the data do not constrain
        (``d = 0`` when there is no degeneracy).
    column_norms
        Norms ``s_k`` of the weighted Jacobian columns (Eq. 9).
    predicted_residual
        Weighted residual predicted after the update, ``w (b + J delta)``.
    """

    delta: np.ndarray
    singular_values: np.ndarray
    null_space: np.ndarray
    column_norms: np.ndarray
    predicted_residual: np.ndarray


def solve_update(
    jacobian: np.ndarray,
    residual: np.ndarray,
    weights: np.ndarray,
    damping: float = 1e-3,
    rtol: float = 1e-8,
) -> Update:
    r"""Return the weighted, column-normalised, damped least-squares update.

    Solves :math:`(\tilde{J}^T\tilde{J} + \lambda I)\Delta\tilde{p} =
    -\tilde{J}^T b_w` with :math:`\tilde{J} = W J S^{-1}`,
    :math:`b_w = W b` and :math:`\Delta p = S^{-1}\Delta\tilde{p}`
    (Eqs. 8-11), through the SVD of :math:`\tilde{J}` so that exactly
    unconstrained directions get no update (minimum norm).

    Parameters
    ----------
    jacobian
        ``J = db/dp`` of shape (2R, K).
    residual
        ``b`` of shape (2R,): displacement from simulated to experimental
        patterns.
    weights
        ROI weights (R,) of Eq. 8, or (2R,) already expanded.
    damping
        :math:`\lambda` of Eq. 10.
    rtol
        Singular values below ``rtol`` times the largest are treated as
        exactly zero (degenerate).

    Returns
    -------
    update
        :class:`Update`.

    Raises
    ------
    ValueError
        On mismatched shapes, non-finite input, or a parameter whose column
        is zero after weighting (it cannot be measured).

    Examples
    --------
    Two columns that are exact opposites (like tilt and sample_tilt):

    >>> import numpy as np
    >>> from kikuchipy_geomdic.calibration.solve import solve_update
    >>> j = np.array([[1.0, 2.0, -2.0], [0.0, 1.0, -1.0], [1.0, 0.0, 0.0]])
    >>> b = -j @ np.array([0.1, 0.3, 0.0])
    >>> u = solve_update(j, b, np.ones(3), damping=0)
    >>> np.round(u.delta, 6).tolist()
    [0.1, 0.15, -0.15]
    >>> u.null_space.shape
    (3, 1)
    """
    j = np.asarray(jacobian, dtype=np.float64)
    b = np.asarray(residual, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if j.ndim != 2 or b.shape != (j.shape[0],):
        raise ValueError(
            f"Jacobian {j.shape} and residual {b.shape} do not match: expected (2R, K) and (2R,)"
        )
    if w.shape == (j.shape[0] // 2,):
        w = np.repeat(w, 2)
    if w.shape != b.shape:
        raise ValueError(f"weights {w.shape} fit neither R nor 2R = {b.shape[0]}")
    if not (np.isfinite(j).all() and np.isfinite(b).all() and np.isfinite(w).all()):
        raise ValueError("Jacobian, residual and weights must be finite")
    jw = j * w[:, None]
    bw = b * w
    s = np.linalg.norm(jw, axis=0)
    if np.any(s == 0):
        raise ValueError(
            f"Jacobian column(s) {np.flatnonzero(s == 0).tolist()} are zero after "
            "weighting: those parameters have no measurable effect"
        )
    jt = jw / s
    u, sv, vt = np.linalg.svd(jt, full_matrices=False)
    keep = sv > rtol * sv[0]
    # Eq. 10 in the SVD basis: filter factors sigma / (sigma^2 + lambda)
    coef = np.zeros_like(sv)
    coef[keep] = sv[keep] / (sv[keep] ** 2 + damping)
    dpt = -vt.T @ (coef * (u.T @ bw))
    delta = dpt / s
    return Update(
        delta=delta,
        singular_values=sv,
        null_space=vt[~keep].T,
        column_norms=s,
        predicted_residual=bw + jw @ delta,
    )


def coupling_matrix(jacobian: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Return the normalised coupling matrix of the paper's Fig. 3C.

    The scalar products of the (weighted) sensitivity fields, normalised
    so the diagonal is 1: the cosine of the angle between two parameters'
    displacement signatures, from -1 (opposite) to 1.

    Parameters
    ----------
    jacobian
        (2R, K).
    weights
        ROI weights (R,) or (2R,); default all ones.

    Returns
    -------
    coupling
        (K, K) symmetric matrix.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.calibration.solve import coupling_matrix
    >>> coupling_matrix(np.array([[1.0, -2.0], [0.0, 0.0]])).tolist()
    [[1.0, -1.0], [-1.0, 1.0]]
    """
    j = np.asarray(jacobian, dtype=np.float64)
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape == (j.shape[0] // 2,):
            w = np.repeat(w, 2)
        j = j * w[:, None]
    n = np.linalg.norm(j, axis=0)
    n = np.where(n > 0, n, 1.0)
    jn = j / n
    return jn.T @ jn


def solve_joint(
    j_geo: np.ndarray,
    j_rot: np.ndarray,
    residual: np.ndarray,
    weights: np.ndarray,
    prior: float | None = None,
    offsets: np.ndarray | None = None,
    damping: float = 0.0,
    rtol: float = 1e-10,
    common: bool = False,
    geometry_prior: np.ndarray | None = None,
    geometry_offsets: np.ndarray | None = None,
) -> JointUpdate:
    r"""Return the geometry and per-pattern rotation updates, solved jointly.

    Minimises, over the geometry change :math:`\Delta p` and a rotation
    :math:`\delta\omega_i` per pattern,

    .. math::

        \sum_i \|W_i^{1/2}(b_i + J_{geo,i}\Delta p + J_{rot,i}\delta\omega_i)\|^2
        + \sum_i \|\omega_i + \delta\omega_i\|^2 / \sigma_\omega^2

    (the second sum only with a *prior*). Each :math:`\delta\omega_i`
    is eliminated exactly, a 3 x 3 solve per pattern (Schur complement);
    the reduced K x K system gives :math:`\Delta p`, damped as
    Levenberg-Marquardt; back-substitution gives the rotations.

    Parameters
    ----------
    j_geo
        Per-pattern geometry Jacobians (N, M, K): M measured components
        per pattern (2 per ROI), pixels per parameter unit.
    j_rot
        Per-pattern rotation Jacobians (N, M, 3), pixels per radian.
    residual
        Per-pattern measured displacements :math:`b_i` (N, M).
    weights
        Inverse variances (N, M) of the components, 0 where nothing was
        measured.
    prior
        :math:`\sigma_\omega`, the standard deviation in radians of each
        component of the orientation errors *offsets* plus the updates:
        the belief that the starting orientations are free of a common
        error. None: no prior; a rotation common to all patterns is then
        seen only through what it cannot mimic.
    offsets
        :math:`\omega_i` (N, 3): each orientation's current rotation away
        from its start, radians. Default zero.
    damping
        :math:`\lambda`: the reduced normal matrix :math:`S` becomes
        :math:`S + \lambda\,\mathrm{diag}(C)`, with :math:`C` the geometry
        normal matrix before elimination (Marquardt's scaling, on the
        parameters' full sensitivity).
    rtol
        Directions whose reduced curvature, relative to the full
        sensitivity, is below this are taken as exactly undetermined and
        get no update (minimum norm), as in :func:`solve_update`.
    common
        A rotation :math:`\Omega` common to all patterns is three more
        unknowns; the *prior* (required) holds each pattern's scatter
        :math:`\omega_i + \delta\omega_i` about it (one crystal).
        :math:`\Omega` is added to :attr:`JointUpdate.rotations`.
    geometry_prior, geometry_offsets
        Standard deviations (K,) of a prior on the geometry (``inf`` where
        none): adds :math:`\sum_k (p_k + \Delta p_k)^2 / \sigma_k^2`, with
        :math:`p_k` the parameters' values against its centre (default 0).

    Returns
    -------
    update
        :class:`JointUpdate`.

    Examples
    --------
    Two patterns, one parameter, each pattern also rotated:

    >>> import numpy as np
    >>> from kikuchipy_geomdic.calibration.solve import solve_joint
    >>> rng = np.random.default_rng(0)
    >>> jg = rng.normal(size=(2, 8, 1))
    >>> jr = rng.normal(size=(2, 8, 3))
    >>> w_true = np.array([[0.1, 0, 0], [0, -0.2, 0.05]])
    >>> b = -(jg[..., 0] * 0.3 + np.einsum("nmk,nk->nm", jr, w_true))
    >>> u = solve_joint(jg, jr, b, np.ones((2, 8)))
    >>> np.round(u.delta, 9).tolist(), np.round(u.rotations, 9).tolist()
    ([0.3], [[0.1, 0.0, 0.0], [0.0, -0.2, 0.05]])
    """
    system = JointSystem.build(j_geo, j_rot, weights, prior, rtol, common, geometry_prior)
    return system.solve(residual, offsets, damping, geometry_offsets)
