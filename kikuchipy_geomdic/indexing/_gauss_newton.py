"""The per-pattern Gauss-Newton kernel, compiled with numba: one
orientation refined on a pattern's intensities (fit ``a * S(q) + b``,
step by a small crystal rotation), and a stack of them.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from kikuchipy_geomdic.indexing._lambert import SUMS, _direction_columns, _step_sums


@nb.njit(cache=True, nogil=True)
def _quat_step(w, q):
    """``exp(w) * q`` for a rotation vector *w* (radians)."""
    angle = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if angle < 1e-300:
        return q.copy()
    s = math.sin(angle / 2) / angle
    a1, b1, c1, d1 = math.cos(angle / 2), w[0] * s, w[1] * s, w[2] * s
    a2, b2, c2, d2 = q[0], q[1], q[2], q[3]
    out = np.empty(4)
    out[0] = a1 * a2 - b1 * b2 - c1 * c2 - d1 * d2
    out[1] = a1 * b2 + b1 * a2 + c1 * d2 - d1 * c2
    out[2] = a1 * c2 - b1 * d2 + c1 * a2 + d1 * b2
    out[3] = a1 * d2 + b1 * c2 - c1 * b2 + d1 * a2
    norm = math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)
    return out / norm


#: Largest lengthening of a Gauss-Newton step by the acceleration
MAX_ACCELERATION = 10.0

#: With acceleration, an accepted step that raised the NCC by less than
#: this ends the refinement as converged: far below the NCC differences
#: of 180 deg variants (1e-3) that the comparison resolves
NCC_STALL = 1e-6


@nb.njit(cache=True, nogil=True)
def _gauss_newton(e, q, dcol, hemispheres, scale, max_eval, tol, max_step, accelerate):
    """Refine one orientation; return (q, ncc, evaluations, converged).

    With *accelerate*, a step that points along the last accepted one and
    is shorter by a ratio ``r`` is lengthened to ``1 / (1 - r)`` of it (at
    most :data:`MAX_ACCELERATION`): the remaining sum of a geometric
    series of steps. At full resolution on camera-blurred patterns the
    sharp simulation's curvature is larger than the NCC's, so plain steps
    fall short by a constant factor and converge linearly (measured on
    BaTiO3 ``Camera(dose=150)`` patterns of 120 px, variants started next
    to their optimum: 0.18 deg left after 10 evaluations, 0.04 accelerated;
    the NCC 90th percentile short of the optimum after 8 evaluations
    6e-3 plain, 6e-4 accelerated). An overshoot is halved back as any.
    Accelerated, a step that gains less than :data:`NCC_STALL` in NCC
    also ends the refinement (converged): the steps then dither between
    the master pattern's cells without reaching *tol*."""
    n = e.size
    sums = np.empty(SUMS)
    se = e.sum()
    em = se / n
    ec = e - em
    enorm = math.sqrt((ec * ec).sum())
    q_best = q.copy()
    ncc_best = -2.0
    w = np.zeros(3)
    w_last = np.zeros(3)  # the last accepted step
    halvings = 0
    converged = False
    evals = 0
    a_mat = np.empty((5, 5))
    rhs = np.empty(5)
    while evals < max_eval:
        _step_sums(q, dcol, hemispheres, scale, e, sums)
        evals += 1
        sv, svv, sve = sums[0], sums[1], sums[2]
        sm = sv / n
        sxx = svv - sv * sm
        sxe = sve - sm * se
        ncc = sxe / math.sqrt(sxx) / enorm if sxx > 0 and enorm > 0 else 0.0
        if ncc < ncc_best:
            # The step overshot: go back and try half of it
            halvings += 1
            if halvings > 6:
                converged = True  # the step left is far below tol
                break
            for i in range(3):
                w[i] *= 0.5
            q = _quat_step(w, q_best)
            continue
        halvings = 0
        gained = ncc - ncc_best
        if ncc_best > -2.0:
            w_last[:] = w
        q_best = q
        ncc_best = ncc
        if accelerate and gained < NCC_STALL:
            converged = True
            break
        # Gain and offset at this orientation, then the 5 x 5 normal
        # equations of (w, gain, offset) on the residual they leave, from
        # the pixel sums: columns (gain * j, v, 1), residual e - gain v - off
        gain = sxe / sxx if sxx > 0 else 0.0
        off = em - gain * sm
        a_mat[0, 0] = gain * gain * sums[12]
        a_mat[0, 1] = gain * gain * sums[13]
        a_mat[0, 2] = gain * gain * sums[14]
        a_mat[1, 1] = gain * gain * sums[15]
        a_mat[1, 2] = gain * gain * sums[16]
        a_mat[2, 2] = gain * gain * sums[17]
        for i in range(3):
            a_mat[i, 3] = gain * sums[6 + i]
            a_mat[i, 4] = gain * sums[3 + i]
            rhs[i] = gain * (sums[9 + i] - gain * sums[6 + i] - off * sums[3 + i])
        a_mat[3, 3] = svv
        a_mat[3, 4] = sv
        a_mat[4, 4] = n
        rhs[3] = sve - gain * svv - off * sv
        rhs[4] = se - gain * sv - off * n
        for i in range(5):
            for j in range(i):
                a_mat[i, j] = a_mat[j, i]
        # Tiny Levenberg term: a flat pattern must not give a huge step
        for i in range(3):
            a_mat[i, i] *= 1.0 + 1e-9
            a_mat[i, i] += 1e-12
        x = np.linalg.solve(a_mat, rhs)
        step = math.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2)
        if step < tol:
            converged = True
            break
        factor = _acceleration(x, w_last, step) if accelerate else 1.0
        shrink = 1.0 if step * factor <= max_step else max_step / (step * factor)
        for i in range(3):
            w[i] = x[i] * factor * shrink
        q = _quat_step(w, q_best)
    return q_best, ncc_best, evals, converged


@nb.njit(cache=True, nogil=True)
def _acceleration(x, w_last, step):
    """Factor lengthening the step *x* (length *step*) that continues the
    last accepted step *w_last* shorter (1 where it turns or grows)."""
    last = w_last[0] ** 2 + w_last[1] ** 2 + w_last[2] ** 2
    if last <= 0.0:
        return 1.0
    dot = x[0] * w_last[0] + x[1] * w_last[1] + x[2] * w_last[2]
    ratio = dot / last
    if dot < 0.8 * step * math.sqrt(last) or not 0.0 < ratio < 1.0:
        return 1.0
    return min(1.0 / (1.0 - ratio), MAX_ACCELERATION)


@nb.njit(cache=True, nogil=True)
def _refine_stack(
    patterns, quats, pcs, nrows, ncols, om, hemispheres, scale, max_eval, tol, step,
    accelerate=False,
):  # fmt: skip
    """:func:`_gauss_newton` on each pattern of a stack (*hemispheres*: the
    master pattern's, stacked as :func:`~._lambert._step_sums` takes them)."""
    n = patterns.shape[0]
    q_out = np.empty((n, 4))
    ncc = np.empty(n)
    evals = np.zeros(n, dtype=np.int64)
    conv = np.zeros(n, dtype=np.bool_)
    dcol = np.empty((3, 0))
    for p in range(n):
        # A detector of one PC: the directions once
        if p == 0 or not (pcs[p] == pcs[p - 1]).all():
            dcol = _direction_columns(pcs[p], nrows, ncols, om)
        e = patterns[p].astype(np.float64)
        if not np.isfinite(e).all():
            q_out[p] = quats[p]
            ncc[p] = np.nan
            continue
        q, c, k, ok = _gauss_newton(
            e, quats[p].copy(), dcol, hemispheres, scale, max_eval, tol, step, accelerate
        )
        q_out[p] = q
        ncc[p] = c
        evals[p] = k
        conv[p] = ok
    return q_out, ncc, evals, conv
