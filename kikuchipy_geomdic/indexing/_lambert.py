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


@nb.njit(cache=True, nogil=True, fastmath=True)
def _project(q, dc, upper, lower, scale, value, jac, with_jac, gradient=None, stretch=1.0):
    """Project one pattern (kikuchipy's Lambert lookup, bilinear) into
    *value*; with *with_jac*, its derivative by a crystal rotation
    ``w`` (``d -> d + w x d``) into *jac* (n, 3), and the gradient of the
    intensity by the crystal direction into *gradient* (n, 3) if given.
    (:func:`_step_sums` is the same arithmetic for a Gauss-Newton step,
    summed over the pixels in vector registers.)

    A *stretch* other than 1 is that of the crystal's c axis (its z): the
    pattern of a lattice ``diag(1, 1, stretch)`` times the master pattern's
    shows at the crystal direction ``u`` what the master pattern holds at
    ``diag(1, 1, 1 / stretch) u``, normalised. The derivatives are the
    master pattern's at that direction (first order in the stretch)."""
    m = _rotation_matrix(q)
    inv_stretch = 1.0 / stretch
    npx = upper.shape[0]
    fac = scale / _SQRT_PI_HALF
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
        value[k] = a0 + dj * (a1 - a0)
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
            jac[k, 0] = j0
            jac[k, 1] = j1
            jac[k, 2] = j2
            if gradient is not None:
                gradient[k, 0] = ix
                gradient[k, 1] = iy
                gradient[k, 2] = iz


#: Entries of the *sums* of :func:`_step_sums`: sums over the pixels of the
#: projection v, v * v, v * e, then of each rotation derivative j_i,
#: j_i * v, j_i * e (i = 0, 1, 2), then j_i * j_k (00, 01, 02, 11, 12, 22)
SUMS = 18


@nb.njit(cache=True, nogil=True)
def _direction_columns(pc, nrows, ncols, om):
    """:func:`_direction_cosines` as three rows (3, n): x, y and z of every
    pixel, the layout :func:`_step_sums` loads into vector registers."""
    return np.ascontiguousarray(_direction_cosines(pc, nrows, ncols, om).T)


# error_model="numpy": Python's check of every division for zero (a
# branch that raises) kept the loop scalar; the divisions here are guarded
@nb.njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def _step_sums(q, dcol, hemispheres, scale, e, sums):
    """The sums over the pixels (:data:`SUMS`, into *sums*) that a
    Gauss-Newton step on the pattern *e* needs: :func:`_project`'s
    projection and rotation derivative, nothing stored per pixel.

    The same arithmetic as :func:`_project` (equal to rounding in the
    order of the sums), written without branches, the two hemispheres
    stacked in one array (*hemispheres*, (2 npx, npx): upper, then lower)
    and the pixel directions as rows (*dcol*, :func:`_direction_columns`),
    so that LLVM runs the loop on vector registers: 0.21 -> 0.09 ms for
    96 x 96 px (AVX-512 machine, 256-bit vectors; the branchy loop was
    scalar, and with the directions as (n, 3) the vector loop was slower
    than it)."""
    m = _rotation_matrix(q)
    npx = hemispheres.shape[1]
    fac = scale / _SQRT_PI_HALF
    m00, m01, m02 = m[0, 0], m[0, 1], m[0, 2]
    m10, m11, m12 = m[1, 0], m[1, 1], m[1, 2]
    m20, m21, m22 = m[2, 0], m[2, 1], m[2, 2]
    # The sums as scalars, not an array, so that they stay in registers
    sv = svv = sve = 0.0
    s0 = s1 = s2 = 0.0
    sv0 = sv1 = sv2 = 0.0
    se0 = se1 = se2 = 0.0
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    for k in range(dcol.shape[1]):
        vx, vy, vz = dcol[0, k], dcol[1, k], dcol[2, k]
        x = m00 * vx + m01 * vy + m02 * vz
        y = m10 * vx + m11 * vy + m12 * vz
        z = m20 * vx + m21 * vy + m22 * vz
        s = math.sqrt(max(2.0 * (1.0 - abs(z)), 0.0))
        # _project's two branches as selects: "swap" is its |y| > |x|
        # branch, where the roles of x and y (and of the Lambert X and Y)
        # exchange; s == 0 (a pole) gives zeros as there
        swap = abs(y) > abs(x)
        pole = s == 0.0
        num = x if swap else y
        den = y if swap else x
        t = _atan_unit(0.0 if den == 0.0 else num / den)
        sg = 1.0 if den > 0 else -1.0
        a = sg * s * _SQRT_PI_OVER_2
        b = sg * s * _TWO_OVER_SQRT_PI * t
        lx = 0.0 if pole else (b if swap else a)
        ly = 0.0 if pole else (a if swap else b)
        dsdz = 0.0 if pole else -(1.0 if z > 0 else -1.0) / s
        p = 0.0 if pole else sg * s * _TWO_OVER_SQRT_PI / (x * x + y * y)
        c1 = sg * _SQRT_PI_OVER_2 * dsdz
        c2 = sg * _TWO_OVER_SQRT_PI * t * dsdz
        # Row from Lambert Y, column from Lambert X, as kikuchipy; the
        # lower hemisphere's rows follow the upper's
        u = fac * ly + scale
        v = fac * lx + scale
        i0 = int(u)
        j0 = int(v)
        i1 = min(i0 + 1, npx - 1)
        j1 = min(j0 + 1, npx - 1)
        i0 = max(i0, 0)
        j0 = max(j0, 0)
        di = u - i0
        dj = v - j0
        off = 0 if z >= 0 else npx
        h00 = hemispheres[i0 + off, j0]
        h10 = hemispheres[i1 + off, j0]
        h01 = hemispheres[i0 + off, j1]
        h11 = hemispheres[i1 + off, j1]
        a0 = h00 + di * (h10 - h00)
        a1 = h01 + di * (h11 - h01)
        val = a0 + dj * (a1 - a0)
        dvdu = fac * ((1 - dj) * (h10 - h00) + dj * (h11 - h01))
        dvdv = fac * ((1 - di) * (h01 - h00) + di * (h11 - h10))
        # Gradient of the intensity by the direction: _project's
        # dvdu * h + dvdv * g, with (g, h) = ((0, 0, c1), (-p y, p x, c2)),
        # or swapped ((p y, -p x, c2), (0, 0, c1))
        w = -dvdv if swap else dvdu
        ix = -w * p * y
        iy = w * p * x
        iz = (dvdu * c1 + dvdv * c2) if swap else (dvdu * c2 + dvdv * c1)
        j0 = y * iz - z * iy
        j1 = z * ix - x * iz
        j2 = x * iy - y * ix
        ek = e[k]
        sv += val
        svv += val * val
        sve += val * ek
        s0 += j0
        s1 += j1
        s2 += j2
        sv0 += j0 * val
        sv1 += j1 * val
        sv2 += j2 * val
        se0 += j0 * ek
        se1 += j1 * ek
        se2 += j2 * ek
        s00 += j0 * j0
        s01 += j0 * j1
        s02 += j0 * j2
        s11 += j1 * j1
        s12 += j1 * j2
        s22 += j2 * j2
    sums[0], sums[1], sums[2] = sv, svv, sve
    sums[3], sums[4], sums[5] = s0, s1, s2
    sums[6], sums[7], sums[8] = sv0, sv1, sv2
    sums[9], sums[10], sums[11] = se0, se1, se2
    sums[12], sums[13], sums[14] = s00, s01, s02
    sums[15], sums[16], sums[17] = s11, s12, s22


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
        _project(quats[p], dc, upper, lower, scale, out[p], jac, True, grad, stretch)
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
def _stack_ncc(patterns, quats, pcs, nrows, ncols, om, hemispheres, scale):
    """NCC of each pattern with its projection, one pattern in memory (by
    :func:`_step_sums`: its derivative sums are not needed, but its vector
    loop is faster than :func:`_project`'s scalar one: 0.15 -> 0.09 ms
    for 96 x 96 px)."""
    n = quats.shape[0]
    out = np.empty(n)
    sums = np.empty(SUMS)
    dcol = np.empty((3, 0))
    for p in range(n):
        # A detector of one PC: the directions once
        if p == 0 or not (pcs[p] == pcs[p - 1]).all():
            dcol = _direction_columns(pcs[p], nrows, ncols, om)
        e = patterns[p].astype(np.float64)
        e -= e.mean()
        _step_sums(quats[p], dcol, hemispheres, scale, e, sums)
        sxx = sums[1] - sums[0] * sums[0] / e.size
        see = (e * e).sum()
        out[p] = sums[2] / math.sqrt(sxx * see) if sxx > 0 and see > 0 else 0.0
    return out


@nb.njit(cache=True, nogil=True)
def _project_stack(quats, pcs, nrows, ncols, om, upper, lower, scale, stretch=1.0):
    n = quats.shape[0]
    out = np.empty((n, nrows * ncols))
    jac = np.empty((1, 3))
    for p in range(n):
        dc = _direction_cosines(pcs[p], nrows, ncols, om)
        _project(quats[p], dc, upper, lower, scale, out[p], jac, False, None, stretch)
    return out
