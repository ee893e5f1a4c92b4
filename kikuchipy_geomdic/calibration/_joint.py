"""The joint solve's normal equations and result: :class:`JointSystem`,
built once from the Jacobians and weights and solved for any residual,
and :class:`JointUpdate`, what a solve gives; both are re-exported (and
documented) by :mod:`~kikuchipy_geomdic.calibration.solve`, whose
:func:`~kikuchipy_geomdic.calibration.solve.solve_joint` is a build and a
solve.

Layer 6 (calibration): plain arrays in and out; imports nothing of the
package.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class JointUpdate:
    """The result of one joint solve (:func:`solve_joint`).

    Attributes
    ----------
    delta
        Geometry update (K,), in parameter units, in the order of the
        parameters solved for.
    rotations
        Rotation updates (N, 3) in radians: rotation vectors of the right
        factor ``T`` of each orientation, ``g -> g * T``.
    covariance
        Covariance (K, K) of *delta* in parameter units: *model_covariance*
        enlarged wherever the scatter of the patterns' own contributions
        says the errors within a pattern are correlated (cluster-robust,
        never smaller than the model).
    model_covariance
        The covariance if all components were independent: the inverse
        of the reduced normal matrix (rotations eliminated, prior
        included) times the variance factor. Pseudo-inverse when
        degenerate.
    null_space
        (K, d) unit directions, in parameter units, that the data do not
        constrain at all (e.g. tilt against sample_tilt).
    rotation_sigma
        Standard errors (N, 3) of the rotation updates, radians.
    variance_factor
        Weighted residual sum of squares of the fit over its degrees of
        freedom: 1 when *weights* are true inverse variances.
    chi2
        Weighted residual sum of squares before the update (data only).
    predicted_chi2
        The same predicted after the update (data only).
    dof
        Degrees of freedom: measured components minus unknowns.
    reduced_norms, full_norms
        Square roots of the diagonals of the geometry normal matrix with
        the rotations eliminated and without: their ratio says how much
        of a parameter's signature survives once every orientation may
        move (small for the detector angles).
    """

    delta: np.ndarray
    rotations: np.ndarray
    covariance: np.ndarray
    model_covariance: np.ndarray
    null_space: np.ndarray
    rotation_sigma: np.ndarray
    variance_factor: float
    chi2: float
    predicted_chi2: float
    dof: int
    reduced_norms: np.ndarray
    full_norms: np.ndarray

    @property
    def standard_errors(self) -> np.ndarray:
        """Standard errors (K,) of *delta*; inf for parameters with a
        component in :attr:`null_space`."""
        se = np.sqrt(np.clip(np.diag(self.covariance), 0, None))
        if self.null_space.size:
            se = np.where(np.abs(self.null_space).max(axis=1) > 1e-9, np.inf, se)
        return se

    def standard_error(self, coefficients: np.ndarray) -> float:
        """Standard error of a linear combination ``c . delta``; inf if
        the combination is not determined."""
        c = np.asarray(coefficients, dtype=np.float64)
        if self.null_space.size and np.abs(c @ self.null_space).max() > 1e-9 * np.linalg.norm(c):
            return float("inf")
        return float(np.sqrt(max(c @ self.covariance @ c, 0.0)))


def _with_pattern_correlations(
    model: np.ndarray, s_inv: np.ndarray, scores: np.ndarray, k: int
) -> np.ndarray:
    """The covariance *model* (independent components), enlarged in every
    direction where the patterns' scatter says it is larger.

    DIC errors within a pattern are correlated (one misfit band moves
    all its features), which the model, built from independent vectors,
    misses: measured on 4 x 4 maps of 60 px, a step of 3.5 model standard
    errors in the azimuthal angle went away from the truth. The
    cluster-robust (sandwich) estimate ``S^-1 (sum_i s_i s_i^T) S^-1``
    of the patterns' scores ``s_i`` sees any correlation within a
    pattern; with few patterns it is itself noisy, so the result is the
    model plus the positive part of their difference, never below either.
    """
    n = int(np.count_nonzero(np.abs(scores).sum(axis=1)))
    if n <= k:
        return model
    robust = s_inv @ (scores.T @ scores) @ s_inv * n / (n - k)
    d = robust - model
    mu, v = np.linalg.eigh((d + d.T) / 2)
    return model + (v * np.clip(mu, 0, None)) @ v.T


@dataclass(frozen=True, eq=False)
class JointSystem:
    """The normal equations of :func:`solve_joint` without the residual,
    built once (:meth:`build`) for several residuals (:meth:`solve`), as
    the full field's frozen Jacobians serve: forming the weighted products
    is most of a full-field solve's cost."""

    #: Every column times the square root of its weight, (N, K + 3, M):
    #: the geometry's (with a common rotation's after), then the pattern's
    #: rotation's; the weighted products are :meth:`products`. Of a system
    #: cut by :meth:`columns`, its whole system's stack, *rows* its own
    js: np.ndarray
    sw: np.ndarray  # the weights' square roots (N, M)
    w: np.ndarray
    prior_precision: float
    a_inv: np.ndarray
    a_inv_b: np.ndarray
    bb: np.ndarray
    c: np.ndarray
    a0: np.ndarray
    s_pattern: np.ndarray  # each pattern's reduced normal matrix (N, K, K)
    geometry_precision: np.ndarray  # the geometry prior's (K,), 0 where none
    full: np.ndarray
    mu: np.ndarray
    v: np.ndarray
    keep: np.ndarray
    n_rot: int
    k: int  # geometry parameters; a common rotation's three follow
    rtol: float = 1e-10
    rows: np.ndarray | None = None  # the rows of *js* that are this system's; None: all

    @classmethod
    def build(
        cls,
        j_geo: np.ndarray,
        j_rot: np.ndarray,
        weights: np.ndarray,
        prior: float | None = None,
        rtol: float = 1e-10,
        common: bool = False,
        geometry_prior: np.ndarray | None = None,
    ) -> JointSystem:
        """Build the normal equations of a joint solve.

        Parameters
        ----------
        j_geo, j_rot, weights, prior, rtol, common, geometry_prior
            As in :func:`solve_joint`: Jacobians (N, M, K) and (N, M, 3),
            inverse variances (N, M), the prior (radians or None), the
            tolerance of undetermined directions, the common rotation,
            the geometry's prior (standard deviations (K,) or None).

        Returns
        -------
        system
            The :class:`JointSystem`, to :meth:`solve` for residuals.
        """
        jg, jr = np.asarray(j_geo), np.asarray(j_rot)
        w = np.asarray(weights, dtype=np.float64)
        if jg.ndim != 3 or jr.shape != jg.shape[:2] + (3,):
            raise ValueError(
                f"Shapes do not match: j_geo {jg.shape} (N, M, K), j_rot {jr.shape} (N, M, 3)"
            )
        if w.shape != jg.shape[:2]:
            raise ValueError(f"weights {w.shape} differ from the Jacobians' {jg.shape[:2]}")
        if not all(np.isfinite(a).all() for a in (jg, jr, w)) or (w < 0).any():
            raise ValueError("Jacobians, residual and weights must be finite, weights >= 0")
        p = 0.0 if prior is None else 1.0 / float(prior) ** 2
        if prior is not None and not (np.isfinite(p) and prior > 0):
            raise ValueError(f"prior must be a positive standard deviation, not {prior}")
        k = jg.shape[2]
        sd = np.full(k, np.inf) if geometry_prior is None else np.asarray(geometry_prior, float)
        if sd.shape != (k,) or not (sd > 0).all():
            raise ValueError(f"geometry_prior must be {k} positive standard deviations")
        precision = 1.0 / sd**2
        if common and prior is None:
            raise ValueError("a common rotation needs a prior: else it is every pattern's own")
        # Every column in one float64 stack (N, columns, M), the M vectors
        # or pixels last, weighted as it is filled: one batched product
        # (BLAS) makes every block of the normal equations, three times
        # faster than products of the (N, M, K) arrays and their weighted
        # copies
        blocks = [jg, jr, jr] if common else [jg, jr]  # a common rotation
        kg = k + 3 if common else k  # moves every pattern as its own does
        js = np.empty((jg.shape[0], kg + 3, jg.shape[1]))
        sw = np.sqrt(w)
        col = 0
        for b in blocks:
            out = js[:, col : col + b.shape[2]]
            np.multiply(np.swapaxes(b, 1, 2), sw[:, None, :], out=out)
            col += b.shape[2]
        return cls._from_stack(js, sw, w, p, k, kg, precision, rtol)

    def columns(self, index, geometry_prior: np.ndarray | None = None) -> JointSystem:
        """The system of the geometry columns *index* (K',) alone, a common
        rotation's kept, with *geometry_prior* (standard deviations (K',)
        or None): what :meth:`build` makes of those columns, to the last
        bit, from this one's weighted stack (the full field built a
        second system, with parameters held, from its Jacobians anew)."""
        index = np.asarray(index, dtype=np.int64)
        kg = self.c.shape[1]
        rows = np.concatenate([index, np.arange(self.k, kg + 3)])
        # Pattern by pattern, each one's rows copied (0.7 MB at 120 px):
        # the same products (BLAS syrk) as of the stack cut, which the
        # normal equations' blocks, cut from this system's, are not to the
        # last bit (OpenBLAS' kernels depend on the matrix's size). The
        # stack copied whole cost more than the rest of the cut system (55
        # MB at 100 patterns of 120 px, new memory each time)
        rows = rows if self.rows is None else self.rows[rows]
        normal = np.empty((len(self.js), len(rows), len(rows)))
        for i, pattern in enumerate(self.js):
            cut = pattern[rows]
            normal[i] = cut @ cut.T
        sd = np.full(len(index), np.inf) if geometry_prior is None else geometry_prior
        precision = 1.0 / np.asarray(sd, dtype=np.float64) ** 2
        k = len(index)
        return self._from_normal(
            normal, self.js, self.sw, self.w, self.prior_precision, k, kg - self.k + k,
            precision, self.rtol, rows,
        )  # fmt: skip

    @classmethod
    def _from_stack(cls, js, sw, w, p, k, kg, precision, rtol) -> JointSystem:
        # The normal equations of the weighted stack *js* (N, kg + 3, M):
        # *k* geometry columns, a common rotation's after them up to *kg*
        normal = js @ np.swapaxes(js, 1, 2)
        return cls._from_normal(normal, js, sw, w, p, k, kg, precision, rtol)

    @classmethod
    def _from_normal(cls, normal, js, sw, w, p, k, kg, precision, rtol, rows=None):
        # The system of the normal equations *normal* (N, kg + 3, kg + 3)
        # of the stack *js* (its *rows*, if given)
        if kg > k:
            precision = np.concatenate([precision, np.zeros(3)])
        a0 = normal[:, kg:, kg:]
        a = a0 + p * np.eye(3)
        bb = normal[:, kg:, :kg]
        c = normal[:, :kg, :kg]
        # A pattern without vectors and no prior: singular, no say (pinv)
        a_inv = np.linalg.pinv(a, hermitian=True)
        a_inv_b = a_inv @ bb
        s_pattern = c - np.einsum("nki,nkj->nij", bb, a_inv_b)
        full = np.sqrt(np.clip(np.diag(c.sum(axis=0)), 0, None))
        if np.any(full == 0):
            raise ValueError(
                f"Jacobian column(s) {np.flatnonzero(full == 0).tolist()} are zero after "
                "weighting: those parameters have no measurable effect"
            )
        # Scaled by the full sensitivities, its eigenvalues say how much
        # of each signature survives the elimination of the rotations
        s_scaled = (s_pattern.sum(axis=0) + np.diag(precision)) / np.outer(full, full)
        mu, v = np.linalg.eigh((s_scaled + s_scaled.T) / 2)
        keep = mu > rtol * max(mu.max(), 1.0)
        n_rot = int(np.linalg.matrix_rank(a, hermitian=True).sum())
        # In the fields' order
        return cls(js, sw, w, p, a_inv, a_inv_b, bb, c, a0, s_pattern, precision,
                   full, mu, v, keep, n_rot, k, rtol, rows)  # fmt: skip

    def stack(self) -> np.ndarray:
        """This system's weighted columns (N, K + 3, M), as :attr:`js` of
        a system built from them."""
        return self.js if self.rows is None else np.take(self.js, self.rows, axis=1)

    def products(self, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The weighted products ``J^T W b`` of a residual with the columns.

        Parameters
        ----------
        b
            Residual (N, M) of the system's patterns.

        Returns
        -------
        geometry, rotation
            The products with the geometry's columns (N, K, a common
            rotation's after them) and with each pattern's rotation's (N, 3).
        """
        wb = self.sw * b
        if self.rows is None:
            x = (self.js @ wb[..., None])[..., 0]
        else:
            # Pattern by pattern, each one's rows copied: the same product
            # (BLAS gemv) as of the stack cut, without copying it whole
            x = np.stack([self.js[i, self.rows] @ wb[i] for i in range(len(wb))])
        return x[:, :-3], x[:, -3:]

    def solve(
        self,
        residual: np.ndarray,
        offsets: np.ndarray | None = None,
        damping: float = 0.0,
        geometry_offsets: np.ndarray | None = None,
    ) -> JointUpdate:
        """Solve the system for one residual.

        Parameters
        ----------
        residual, offsets, damping, geometry_offsets
            As in :func:`solve_joint`: the measured residual (N, M), each
            orientation's rotation from its start (N, 3; default zero),
            the Levenberg-Marquardt damping and the geometry's values
            against its prior's centre (K,; default zero).

        Returns
        -------
        update
            :class:`JointUpdate`, the same as :func:`solve_joint` gives.
        """
        w, full = self.w, self.full
        mu, v, keep = self.mu, self.v, self.keep
        b = np.asarray(residual, dtype=np.float64)
        if b.shape != w.shape:
            raise ValueError(f"residual {b.shape} differs from the Jacobians' {w.shape} (N, M)")
        if not np.isfinite(b).all():
            raise ValueError("Jacobians, residual and weights must be finite, weights >= 0")
        n = w.shape[0]
        w0 = np.zeros((n, 3)) if offsets is None else np.asarray(offsets, dtype=np.float64)
        ag, ar0 = self.products(b)
        ar = ar0 + self.prior_precision * w0
        a_inv_r = np.einsum("nij,nj->ni", self.a_inv, ar)
        g_red = (ag - np.einsum("nki,nk->ni", self.bb, a_inv_r)).sum(axis=0)
        if geometry_offsets is not None:
            g_red[: self.k] += self.geometry_precision[: self.k] * geometry_offsets
        g_scaled = g_red / full
        coef = np.zeros_like(mu)
        coef[keep] = 1.0 / (mu[keep] + damping)
        delta = -(v @ (coef * (v.T @ g_scaled))) / full
        cov_scaled = (v[:, keep] / mu[keep]) @ v[:, keep].T
        null = v[:, ~keep] / full[:, None]
        if null.size:
            null = null / np.linalg.norm(null, axis=0)
        dw = -(a_inv_r + self.a_inv_b @ delta)

        # The residual after the step, its chi2 and the patterns' scores
        # from the normal equations' blocks: three passes over the
        # Jacobians fewer
        chi2 = float(np.einsum("nm,nm,nm->", w, b, b))
        scores = ag + self.c @ delta + np.einsum("nrk,nr->nk", self.bb, dw)
        chi2_after = chi2 + float(
            2 * (ag @ delta).sum()
            + 2 * np.einsum("nr,nr->", ar0, dw)
            + delta @ self.c.sum(axis=0) @ delta
            + 2 * np.einsum("nr,nrk,k->", dw, self.bb, delta)
            + np.einsum("nr,nrs,ns->", dw, self.a0, dw)
        )
        if not chi2_after > 1e-6 * chi2:
            # Expanded, a chi2 that nearly vanishes is lost to round-off
            step = np.concatenate([np.broadcast_to(delta, (n, delta.size)), dw], axis=1)
            js = self.stack()
            wr_after = self.sw * b + (step[:, None, :] @ js)[:, 0]
            chi2_after = float((wr_after**2).sum())
            scores = (js @ wr_after[..., None])[:, : delta.size, 0]
        n_obs = int((w > 0).sum())
        dof = max(n_obs - self.n_rot - int(keep.sum()), 1)
        factor = chi2_after / dof
        s_inv = cov_scaled / np.outer(full, full)
        model = factor * s_inv
        cov = _with_pattern_correlations(model, s_inv, scores, int(keep.sum()))
        # Rotation errors given the geometry (the geometry's own error adds
        # a common part, see covariance)
        rot_sigma = np.sqrt(factor * np.clip(np.diagonal(self.a_inv, axis1=1, axis2=2), 0, None))
        reduced = np.sqrt(np.clip(np.einsum("nkk->k", self.s_pattern), 0, None))
        k = self.k
        # A common rotation is part of every pattern's, marginalised out
        dw = dw + delta[k:] if delta.size > k else dw
        reduced, full, null = reduced[:k], full[:k], null[:k]
        delta, cov, model = delta[:k], cov[:k, :k], model[:k, :k]
        lengths = np.linalg.norm(null, axis=0)
        null = null[:, lengths > 1e-9] / lengths[lengths > 1e-9]
        return JointUpdate(
            delta=delta,
            rotations=dw,
            covariance=cov,
            model_covariance=model,
            null_space=null,
            rotation_sigma=rot_sigma,
            variance_factor=factor,
            chi2=chi2,
            predicted_chi2=chi2_after,
            dof=dof,
            reduced_norms=reduced,
            full_norms=full,
        )
