"""The linear solve of one geometry update (paper section 2.4, Eqs. 7-11).

Plain arrays in and out: a Jacobian ``J`` (2R x K, pixels per parameter
unit), the residual field ``b`` (2R) and the ROI weights (R), in the order
of :mod:`kikuchipy_geomdic.displacement`.

Exact degeneracies
------------------
Some parameter combinations do not change the patterns at all (in
kikuchipy's projection, ``tilt`` and ``sample_tilt`` enter only as their
difference: see :mod:`kikuchipy_geomdic.geometry`). Their Jacobian columns
are then exactly dependent, the normalised Jacobian has a zero singular
value, and Eq. 10 is singular but for the damping. Rather than let the
damping split the change by accident, the solve is done through the
singular value decomposition: directions with a singular value below
``rtol`` times the largest are dropped, which gives the *minimum-norm*
update in the column-normalised parameters. For tilt and sample_tilt,
whose columns have equal norms, that is an equal and opposite split of
the change of ``tilt - sample_tilt``. To keep one of the pair fixed
instead, leave it out of the refined parameters. Dropped directions are
reported (:attr:`Update.null_space`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Update", "solve_update", "coupling_matrix"]


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
    >>> from kikuchipy_geomdic.solve import solve_update
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
            f"Jacobian {j.shape} and residual {b.shape} do not match: expected "
            "(2R, K) and (2R,)"
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
    >>> from kikuchipy_geomdic.solve import coupling_matrix
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
