"""The kernel's projection, compiled with numba: detector pixels to crystal
directions to the square Lambert master pattern (kikuchipy's lookup and
bilinear interpolation), with the analytic derivatives by a crystal
rotation and by the PC.

Plain array code (``nogil``), so dask's threads run chunks in parallel;
:mod:`~kikuchipy_geomdic.indexing._projection` wraps it for arrays and
kikuchipy objects, :mod:`~kikuchipy_geomdic.indexing._gauss_newton` steps
with it.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_SQRT_PI_HALF = math.sqrt(math.pi / 2)
_SQRT_PI_OVER_2 = math.sqrt(math.pi) / 2
_TWO_OVER_SQRT_PI = 2 / math.sqrt(math.pi)

#: Odd minimax polynomial of arctan on [-1, 1] (degree 23, in t^2 from
#: t^0): max abs error 2.2e-11 rad against math.atan (dense grid with the
#: endpoints, tests/indexing), about 1e-8 of a master-pattern pixel
_ATAN_COEFFICIENTS = (
    0.9999999994302322,
    -0.33333327040819816,
    0.19999793542823519,
    -0.14282551428094534,
    0.11083671375616534,
    -0.08941119642994749,
    0.07143078008405897,
    -0.0525146185704032,
    0.032232639411184386,
    -0.014721269907144943,
    0.004293668901864392,
    -0.0005877040397836429,
)


# fastmath: the divisions become multiplications by reciprocals (1 ulp),
# half the time (0.098 -> 0.049 ms for 120 x 120 px), a third of a
# projection's by _project_stack
@nb.njit(cache=True, nogil=True, fastmath=True)
def _direction_cosines(pc, nrows, ncols, om):
    """Unit vectors (sample frame) of the detector pixels, kikuchipy's."""
    n = nrows * ncols
    out = np.empty((n, 3))
    for r in range(nrows):
        for c in range(ncols):
            x = ((c + 0.5) - pc[0] * ncols) / nrows
            y = (pc[1] * nrows - (r + 0.5)) / nrows
            z = pc[2]
            k = r * ncols + c
            sx = om[0, 0] * x + om[0, 1] * y + om[0, 2] * z
            sy = om[1, 0] * x + om[1, 1] * y + om[1, 2] * z
            sz = om[2, 0] * x + om[2, 1] * y + om[2, 2] * z
            norm = math.sqrt(sx * sx + sy * sy + sz * sz)
            out[k, 0] = sx / norm
            out[k, 1] = sy / norm
            out[k, 2] = sz / norm
    return out


@nb.njit(cache=True, nogil=True)
def _rotation_matrix(q):
    a, b, c, d = q[0], q[1], q[2], q[3]
    m = np.empty((3, 3))
    m[0, 0] = a * a + b * b - c * c - d * d
    m[0, 1] = 2 * (b * c - a * d)
    m[0, 2] = 2 * (a * c + b * d)
    m[1, 0] = 2 * (a * d + b * c)
    m[1, 1] = a * a - b * b + c * c - d * d
    m[1, 2] = 2 * (c * d - a * b)
    m[2, 0] = 2 * (b * d - a * c)
    m[2, 1] = 2 * (a * b + c * d)
    m[2, 2] = a * a - b * b - c * c + d * d
    return m


@nb.njit(cache=True, nogil=True, fastmath=True)
def _atan_unit(t):
    """Arctangent of ``|t| <= 1`` by :data:`_ATAN_COEFFICIENTS`.

    libm's ``atan`` was a quarter of a projection's time; this inlined
    polynomial takes 0.30 -> 0.24 ms for 120 x 120 px (Horner: the loop's
    pixels overlap its dependency chain)."""
    c = _ATAN_COEFFICIENTS
    u = t * t
    p = c[11]
    for i in range(10, -1, -1):
        p = p * u + c[i]
    return t * p


#: Entries of the *sums* of :func:`_project`: sums over the pixels of the
#: projection v, v * v, v * e, then of each rotation derivative j_i,
#: j_i * v, j_i * e (i = 0, 1, 2), then j_i * j_k (00, 01, 02, 11, 12, 22)
SUMS = 18


@nb.njit(inline="always", fastmath=True)
def _add_scaled(a, b, c, x, y, z, w):
    """``(a, b, c) + w * (x, y, z)``: three of :func:`_project`'s sums,
    inlined so that they stay scalars."""
    return a + x * w, b + y * w, c + z * w


@nb.njit(cache=True, nogil=True, fastmath=True)
def _project(
    q, dc, upper, lower, scale, value, jac, with_jac, gradient=None, e=None, sums=None, stretch=1.0
):
    """Project one pattern (kikuchipy's Lambert lookup, bilinear) into
    *value*; with *with_jac*, its derivative by a crystal rotation
    ``w`` (``d -> d + w x d``) into *jac* (n, 3), and the gradient of the
    intensity by the crystal direction into *gradient* (n, 3) if given.

    With *sums* (and *with_jac*), nothing per pixel is stored: *sums*
    gets the sums over the pixels that a Gauss-Newton step on the pattern
    *e* needs (:data:`SUMS`), in the same pass (a step by a stored
    pattern and Jacobian took 0.40 ms for 120 x 120 px, 0.29 of it
    projecting).

    A *stretch* other than 1 is that of the crystal's c axis (its z): the
    pattern of a lattice ``diag(1, 1, stretch)`` times the master pattern's
    shows at the crystal direction ``u`` what the master pattern holds at
    ``diag(1, 1, 1 / stretch) u``, normalised. The derivatives are the
    master pattern's at that direction (first order in the stretch)."""
    m = _rotation_matrix(q)
    inv_stretch = 1.0 / stretch
    npx = upper.shape[0]
    fac = scale / _SQRT_PI_HALF
    # The sums as scalars, not an array, so that they stay in registers
    sv = svv = sve = 0.0
    s0 = s1 = s2 = 0.0
    sv0 = sv1 = sv2 = 0.0
    se0 = se1 = se2 = 0.0
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    for k in range(dc.shape[0]):
        vx, vy, vz = dc[k, 0], dc[k, 1], dc[k, 2]
        x = m[0, 0] * vx + m[0, 1] * vy + m[0, 2] * vz
        y = m[1, 0] * vx + m[1, 1] * vy + m[1, 2] * vz
        z = m[2, 0] * vx + m[2, 1] * vy + m[2, 2] * vz
        if stretch != 1.0:
            z *= inv_stretch
            norm = 1.0 / math.sqrt(x * x + y * y + z * z)
            x *= norm
            y *= norm
            z *= norm
        az = abs(z)
        s = math.sqrt(max(2.0 * (1.0 - az), 0.0))
        gx = 0.0  # d(Lambert X)/d(x, y, z), d(Lambert Y)/d(x, y, z)
        gy = 0.0
        gz = 0.0
        hx = 0.0
        hy = 0.0
        hz = 0.0
        if s == 0.0:
            lx = 0.0
            ly = 0.0
        elif abs(y) <= abs(x):
            sg = 1.0 if x > 0 else -1.0
            t = _atan_unit(y / x)
            lx = sg * s * _SQRT_PI_OVER_2
            ly = sg * s * _TWO_OVER_SQRT_PI * t
            if with_jac:
                dsdz = -(1.0 if z > 0 else -1.0) / s
                r2 = x * x + y * y
                gz = sg * _SQRT_PI_OVER_2 * dsdz
                hx = -sg * s * _TWO_OVER_SQRT_PI * y / r2
                hy = sg * s * _TWO_OVER_SQRT_PI * x / r2
                hz = sg * _TWO_OVER_SQRT_PI * t * dsdz
        else:
            sg = 1.0 if y > 0 else -1.0
            t = _atan_unit(x / y)
            lx = sg * s * _TWO_OVER_SQRT_PI * t
            ly = sg * s * _SQRT_PI_OVER_2
            if with_jac:
                dsdz = -(1.0 if z > 0 else -1.0) / s
                r2 = x * x + y * y
                gx = sg * s * _TWO_OVER_SQRT_PI * y / r2
                gy = -sg * s * _TWO_OVER_SQRT_PI * x / r2
                gz = sg * _TWO_OVER_SQRT_PI * t * dsdz
                hz = sg * _SQRT_PI_OVER_2 * dsdz
        mp = upper if z >= 0 else lower
        # Row from Lambert Y, column from Lambert X, as kikuchipy
        u = fac * ly + scale
        v = fac * lx + scale
        i0 = int(u)
        j0 = int(v)
        i1 = i0 + 1
        j1 = j0 + 1
        if i1 >= npx:
            i1 = i0
        if j1 >= npx:
            j1 = j0
        if i0 < 0:
            i0 = i1
        if j0 < 0:
            j0 = j1
        di = u - i0
        dj = v - j0
        m00 = mp[i0, j0]
        m10 = mp[i1, j0]
        m01 = mp[i0, j1]
        m11 = mp[i1, j1]
        # Bilinear as two lerps: the differences are the derivative's too
        # (with the Jacobian 0.33 -> 0.31 ms for 120 x 120 px)
        a0 = m00 + di * (m10 - m00)
        a1 = m01 + di * (m11 - m01)
        val = a0 + dj * (a1 - a0)
        if sums is None:
            value[k] = val
        if with_jac:
            dvdu = fac * ((1 - dj) * (m10 - m00) + dj * (m11 - m01))
            dvdv = fac * ((1 - di) * (m01 - m00) + di * (m11 - m10))
            # Gradient of the intensity with respect to the direction
            ix = dvdu * hx + dvdv * gx
            iy = dvdu * hy + dvdv * gy
            iz = dvdu * hz + dvdv * gz
            j0 = y * iz - z * iy
            j1 = z * ix - x * iz
            j2 = x * iy - y * ix
            if sums is None:
                jac[k, 0] = j0
                jac[k, 1] = j1
                jac[k, 2] = j2
            else:
                ek = e[k]
                sv += val
                svv += val * val
                sve += val * ek
                s0 += j0
                s1 += j1
                s2 += j2
                sv0, sv1, sv2 = _add_scaled(sv0, sv1, sv2, j0, j1, j2, val)
                se0, se1, se2 = _add_scaled(se0, se1, se2, j0, j1, j2, ek)
                s00, s01, s02 = _add_scaled(s00, s01, s02, j0, j1, j2, j0)
                s11 += j1 * j1
                s12 += j1 * j2
                s22 += j2 * j2
            if gradient is not None:
                gradient[k, 0] = ix
                gradient[k, 1] = iy
                gradient[k, 2] = iz
    if sums is not None:
        sums[0] = sv
        sums[1] = svv
        sums[2] = sve
        sums[3] = s0
        sums[4] = s1
        sums[5] = s2
        sums[6] = sv0
        sums[7] = sv1
        sums[8] = sv2
        sums[9] = se0
        sums[10] = se1
        sums[11] = se2
        sums[12] = s00
        sums[13] = s01
        sums[14] = s02
        sums[15] = s11
        sums[16] = s12
        sums[17] = s22


@nb.njit(cache=True, nogil=True)
def _project_stack_derivatives(quats, pcs, nrows, ncols, om, upper, lower, scale, stretch=1.0):
    n = quats.shape[0]
    npx = nrows * ncols
    out = np.empty((n, npx))
    j_rot = np.empty((n, npx, 3))
    j_pc = np.empty((n, npx, 3))
    jac = np.empty((npx, 3))
    grad = np.empty((npx, 3))
    # d(v)/d(pcx, pcy, pcz) of the unnormalised pixel vector, detector frame
    dv = np.zeros((3, 3))
    dv[0, 0] = -ncols / nrows
    dv[1, 1] = 1.0
    dv[2, 2] = 1.0
    for p in range(n):
        pc = pcs[p]
        dc = _direction_cosines(pc, nrows, ncols, om)
        _project(quats[p], dc, upper, lower, scale, out[p], jac, True, grad, None, None, stretch)
        m = _rotation_matrix(quats[p])
        for k in range(npx):
            # Sample-frame rotation T: a crystal rotation w = R(g) T
            for j in range(3):
                j_rot[p, k, j] = jac[k, 0] * m[0, j] + jac[k, 1] * m[1, j] + jac[k, 2] * m[2, j]
            r = k // ncols
            c = k - r * ncols
            ux = ((c + 0.5) - pc[0] * ncols) / nrows
            uy = (pc[1] * nrows - (r + 0.5)) / nrows
            uz = pc[2]
            sx = om[0, 0] * ux + om[0, 1] * uy + om[0, 2] * uz
            sy = om[1, 0] * ux + om[1, 1] * uy + om[1, 2] * uz
            sz = om[2, 0] * ux + om[2, 1] * uy + om[2, 2] * uz
            norm = math.sqrt(sx * sx + sy * sy + sz * sz)
            for i in range(3):
                # d(unit direction)/d(pc_i) in the sample frame, then crystal
                ax = om[0, 0] * dv[i, 0] + om[0, 1] * dv[i, 1] + om[0, 2] * dv[i, 2]
                ay = om[1, 0] * dv[i, 0] + om[1, 1] * dv[i, 1] + om[1, 2] * dv[i, 2]
                az = om[2, 0] * dv[i, 0] + om[2, 1] * dv[i, 1] + om[2, 2] * dv[i, 2]
                dot = ax * dc[k, 0] + ay * dc[k, 1] + az * dc[k, 2]
                bx = (ax - dc[k, 0] * dot) / norm
                by = (ay - dc[k, 1] * dot) / norm
                bz = (az - dc[k, 2] * dot) / norm
                cx = m[0, 0] * bx + m[0, 1] * by + m[0, 2] * bz
                cy = m[1, 0] * bx + m[1, 1] * by + m[1, 2] * bz
                cz = m[2, 0] * bx + m[2, 1] * by + m[2, 2] * bz
                j_pc[p, k, i] = grad[k, 0] * cx + grad[k, 1] * cy + grad[k, 2] * cz
    return out, j_rot, j_pc


@nb.njit(cache=True, nogil=True)
def _stack_ncc(patterns, quats, pcs, nrows, ncols, om, upper, lower, scale):
    """NCC of each pattern with its projection, one pattern in memory."""
    n = quats.shape[0]
    out = np.empty(n)
    value = np.empty(nrows * ncols)
    jac = np.empty((1, 3))
    for p in range(n):
        dc = _direction_cosines(pcs[p], nrows, ncols, om)
        _project(quats[p], dc, upper, lower, scale, value, jac, False)
        e = patterns[p].astype(np.float64)
        em = e.mean()
        sm = value.mean()
        sxe = 0.0
        sxx = 0.0
        see = 0.0
        for k in range(value.size):
            a = value[k] - sm
            b = e[k] - em
            sxe += a * b
            sxx += a * a
            see += b * b
        out[p] = sxe / math.sqrt(sxx * see) if sxx > 0 and see > 0 else 0.0
    return out


@nb.njit(cache=True, nogil=True)
def _project_stack(quats, pcs, nrows, ncols, om, upper, lower, scale, stretch=1.0):
    n = quats.shape[0]
    out = np.empty((n, nrows * ncols))
    jac = np.empty((1, 3))
    for p in range(n):
        dc = _direction_cosines(pcs[p], nrows, ncols, om)
        _project(quats[p], dc, upper, lower, scale, out[p], jac, False, None, None, None, stretch)
    return out
