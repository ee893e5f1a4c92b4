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
the basin to starts several degrees off; the last level runs at full
resolution. The per-pattern kernel is plain array code compiled with
numba (``nogil``), so dask's threads run chunks in parallel.

Layout: :func:`master_pattern_arrays` (what the kernel projects from),
:func:`pyramid_levels` (the binning schedule), :func:`refine_patterns`
(a stack of patterns with one PC each), :func:`project_patterns` (the
kernel's own projection, for checks), and :func:`neighbour_seeds` with
:func:`poor_points` (the rule for misindexed starts on a map).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.pattern import rescale_intensity
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation
from scipy import ndimage

from kikuchipy_geomdic.patterns.preprocessing import bin_pattern
from kikuchipy_geomdic.patterns.simulation import check_master_pattern

__all__ = [
    "MasterPatternArrays",
    "OrientationResult",
    "master_pattern_arrays",
    "pyramid_levels",
    "project_patterns",
    "refine_patterns",
    "refine_arrays",
    "coarse_arrays",
    "project_arrays",
    "project_derivatives",
    "detector_matrix",
    "detector_pcs",
    "poor_points",
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

_SQRT_PI_HALF = math.sqrt(math.pi / 2)
_SQRT_PI_OVER_2 = math.sqrt(math.pi) / 2
_TWO_OVER_SQRT_PI = 2 / math.sqrt(math.pi)


# --------------------------------------------------------------------- #
# Master pattern
# --------------------------------------------------------------------- #


@dataclass(frozen=True)
class MasterPatternArrays:
    """The two hemispheres the kernel projects from.

    Attributes
    ----------
    upper, lower
        Square Lambert hemispheres, float32, each rescaled to [-1, 1] as
        kikuchipy's refinement rescales them (when not float32 already).
    smoothing
        Standard deviation (degrees) of the Gaussian they were smoothed
        with; 0 for the master pattern itself.
    """

    upper: np.ndarray
    lower: np.ndarray
    smoothing: float = 0.0
    _smoothed: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def scale(self) -> float:
        """kikuchipy's factor from the Lambert square to pixels."""
        return (self.upper.shape[1] - 1) / 2

    def smoothed(self, sigma: float) -> MasterPatternArrays:
        """Return the hemispheres smoothed by a Gaussian of *sigma* degrees
        (at the Lambert centre; remembered, as every chunk asks again)."""
        if sigma <= 0:
            return self
        if sigma not in self._smoothed:
            px = sigma / math.degrees(_SQRT_PI_HALF / self.scale)
            up = _smooth_across_equator(self.upper, self.lower, px)
            lo = _smooth_across_equator(self.lower, self.upper, px)
            self._smoothed[sigma] = MasterPatternArrays(
                up.astype(np.float32), lo.astype(np.float32), sigma
            )
        return self._smoothed[sigma]


def _smooth_across_equator(hemisphere, other, sigma):
    """Gaussian smoothing of one Lambert hemisphere that continues into the
    other one across the square's edge (the equator).

    Past an edge of the square the sphere continues in the other
    hemisphere, mirrored across that edge (the square Lambert projection
    of a direction just below the equator lands just inside the other
    square's same edge). Smoothing with any padding of the hemisphere's
    own pixels puts a false seam there, and patterns that look across the
    equator (a BaTiO3 90 deg domain, c axis in the sample plane) then
    pulled Gauss-Newton degrees away from a start 0.4 deg off.
    """
    w = min(int(math.ceil(4 * sigma)), hemisphere.shape[0] - 1)
    big = np.pad(np.asarray(hemisphere, np.float64), w, mode="reflect")
    ring = np.pad(np.asarray(other, np.float64), w, mode="reflect")
    inner = (slice(w, w + hemisphere.shape[0]), slice(w, w + hemisphere.shape[1]))
    ring[inner] = big[inner]
    return ndimage.gaussian_filter(ring, sigma, mode="nearest")[inner]


def master_pattern_arrays(
    master_pattern: EBSDMasterPattern | MasterPatternArrays, energy: float
) -> MasterPatternArrays:
    """Return the hemispheres of *master_pattern* at *energy* as kikuchipy's
    refinement projects them.

    Parameters
    ----------
    master_pattern
        Lambert :class:`~kikuchipy.signals.EBSDMasterPattern`, one or both
        hemispheres (or its arrays, returned as they are).
    energy
        Beam energy in kV (selects the slice of a multi-energy pattern).

    Returns
    -------
    arrays
        :class:`MasterPatternArrays`.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import master_patterns
    >>> from kikuchipy_geomdic.indexing.orientation import master_pattern_arrays
    >>> mpa = master_pattern_arrays(master_patterns.master_pattern("Si"), 20)
    >>> mpa.upper.shape, mpa.upper.dtype.name, mpa.scale
    ((201, 201), 'float32', 100.0)
    """
    if isinstance(master_pattern, MasterPatternArrays):
        return master_pattern
    check_master_pattern(master_pattern)
    if master_pattern.data.shape[-1] != master_pattern.data.shape[-2]:
        raise ValueError(
            f"The master pattern's Lambert hemispheres must be square, not "
            f"{master_pattern.data.shape[-2:]}"
        )
    # The one private kikuchipy call: the slice selection by energy and the
    # hemisphere layout (kikuchipy is pinned to 0.13 in pyproject.toml)
    upper, lower = master_pattern._get_master_pattern_arrays_from_energy(energy=energy)
    upper, lower = np.asarray(upper), np.asarray(lower)
    if upper.dtype != np.float32:
        # As kikuchipy's refinement: each hemisphere rescaled on its own
        upper = rescale_intensity(upper, dtype_out=np.float32)
        lower = rescale_intensity(lower, dtype_out=np.float32)
    return MasterPatternArrays(
        np.ascontiguousarray(upper, dtype=np.float32),
        np.ascontiguousarray(lower, dtype=np.float32),
    )


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


# --------------------------------------------------------------------- #
# The kernel
# --------------------------------------------------------------------- #


@nb.njit(cache=True, nogil=True)
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
def _project(q, dc, upper, lower, scale, value, jac, with_jac, gradient=None):
    """Project one pattern (kikuchipy's Lambert lookup, bilinear) into
    *value*; with *with_jac*, its derivative by a crystal rotation
    ``w`` (``d -> d + w x d``) into *jac* (n, 3), and the gradient of the
    intensity by the crystal direction into *gradient* (n, 3) if given."""
    m = _rotation_matrix(q)
    npx = upper.shape[0]
    fac = scale / _SQRT_PI_HALF
    for k in range(dc.shape[0]):
        vx, vy, vz = dc[k, 0], dc[k, 1], dc[k, 2]
        x = m[0, 0] * vx + m[0, 1] * vy + m[0, 2] * vz
        y = m[1, 0] * vx + m[1, 1] * vy + m[1, 2] * vz
        z = m[2, 0] * vx + m[2, 1] * vy + m[2, 2] * vz
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
            t = math.atan(y / x)
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
            t = math.atan(x / y)
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
        value[k] = (
            m00 * (1 - di) * (1 - dj) + m10 * di * (1 - dj) + m01 * (1 - di) * dj + m11 * di * dj
        )
        if with_jac:
            dvdu = fac * ((1 - dj) * (m10 - m00) + dj * (m11 - m01))
            dvdv = fac * ((1 - di) * (m01 - m00) + di * (m11 - m10))
            # Gradient of the intensity with respect to the direction
            ix = dvdu * hx + dvdv * gx
            iy = dvdu * hy + dvdv * gy
            iz = dvdu * hz + dvdv * gz
            jac[k, 0] = y * iz - z * iy
            jac[k, 1] = z * ix - x * iz
            jac[k, 2] = x * iy - y * ix
            if gradient is not None:
                gradient[k, 0] = ix
                gradient[k, 1] = iy
                gradient[k, 2] = iz


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


@nb.njit(cache=True, nogil=True)
def _gauss_newton(e, q, dc, upper, lower, scale, max_eval, tol, max_step):
    """Refine one orientation; return (q, ncc, evaluations, converged)."""
    n = e.size
    value = np.empty(n)
    jac = np.empty((n, 3))
    em = e.mean()
    ec = e - em
    enorm = math.sqrt((ec * ec).sum())
    q_best = q.copy()
    ncc_best = -2.0
    w = np.zeros(3)
    halvings = 0
    converged = False
    evals = 0
    a_mat = np.empty((5, 5))
    rhs = np.empty(5)
    while evals < max_eval:
        _project(q, dc, upper, lower, scale, value, jac, True)
        evals += 1
        sm = value.mean()
        sxx = 0.0
        sxe = 0.0
        for k in range(n):
            t = value[k] - sm
            sxx += t * t
            sxe += t * ec[k]
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
        q_best = q
        ncc_best = ncc
        # Gain and offset at this orientation, then the 5 x 5 normal
        # equations of (w, gain, offset) on the residual they leave
        gain = sxe / sxx if sxx > 0 else 0.0
        off = em - gain * sm
        a_mat[:] = 0.0
        rhs[:] = 0.0
        col = np.empty(5)
        for k in range(n):
            col[0] = gain * jac[k, 0]
            col[1] = gain * jac[k, 1]
            col[2] = gain * jac[k, 2]
            col[3] = value[k]
            col[4] = 1.0
            r = e[k] - gain * value[k] - off
            for i in range(5):
                rhs[i] += col[i] * r
                for j in range(i, 5):
                    a_mat[i, j] += col[i] * col[j]
        for i in range(5):
            for j in range(i):
                a_mat[i, j] = a_mat[j, i]
        # Tiny Levenberg term: a flat pattern must not give a huge step
        for i in range(3):
            a_mat[i, i] *= 1.0 + 1e-9
            a_mat[i, i] += 1e-12
        x = np.linalg.solve(a_mat, rhs)
        step = math.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2)
        shrink = 1.0 if step <= max_step else max_step / step
        for i in range(3):
            w[i] = x[i] * shrink
        if step < tol:
            converged = True
            break
        q = _quat_step(w, q_best)
    return q_best, ncc_best, evals, converged


@nb.njit(cache=True, nogil=True)
def _refine_stack(
    patterns, quats, pcs, nrows, ncols, om, upper, lower, scale, max_eval, tol, step
):
    n = patterns.shape[0]
    q_out = np.empty((n, 4))
    ncc = np.empty(n)
    evals = np.zeros(n, dtype=np.int64)
    conv = np.zeros(n, dtype=np.bool_)
    for p in range(n):
        dc = _direction_cosines(pcs[p], nrows, ncols, om)
        e = patterns[p].astype(np.float64)
        if not np.isfinite(e).all():
            q_out[p] = quats[p]
            ncc[p] = np.nan
            continue
        q, c, k, ok = _gauss_newton(
            e, quats[p].copy(), dc, upper, lower, scale, max_eval, tol, step
        )
        q_out[p] = q
        ncc[p] = c
        evals[p] = k
        conv[p] = ok
    return q_out, ncc, evals, conv


@nb.njit(cache=True, nogil=True)
def _project_stack_derivatives(quats, pcs, nrows, ncols, om, upper, lower, scale):
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
        _project(quats[p], dc, upper, lower, scale, out[p], jac, True, grad)
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
def _project_stack(quats, pcs, nrows, ncols, om, upper, lower, scale):
    n = quats.shape[0]
    out = np.empty((n, nrows * ncols))
    jac = np.empty((1, 3))
    for p in range(n):
        dc = _direction_cosines(pcs[p], nrows, ncols, om)
        _project(quats[p], dc, upper, lower, scale, out[p], jac, False)
    return out


# --------------------------------------------------------------------- #
# Python API
# --------------------------------------------------------------------- #


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


def detector_pcs(detector: EBSDDetector, n: int) -> np.ndarray:
    """Return the detector's Bruker PCs as (n, 3), one repeated or n given.

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.indexing.orientation import detector_pcs
    >>> detector_pcs(EBSDDetector(pc=[0.5, 0.3, 0.6]), 2).tolist()
    [[0.5, 0.3, 0.6], [0.5, 0.3, 0.6]]
    """
    pcs = np.ascontiguousarray(detector.pc.reshape(-1, 3), dtype=np.float64)
    if pcs.shape[0] == 1:
        return np.repeat(pcs, n, axis=0)
    if pcs.shape[0] != n:
        raise ValueError(f"The detector has {pcs.shape[0]} PCs for {n} patterns; give one or {n}")
    return pcs


def detector_matrix(detector: EBSDDetector) -> np.ndarray:
    """Return the detector-to-sample matrix (3, 3) of *detector*'s angles,
    as kikuchipy projects with it.

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.indexing.orientation import detector_matrix
    >>> detector_matrix(EBSDDetector(sample_tilt=70)).shape
    (3, 3)
    """
    return np.ascontiguousarray((~detector.sample_to_detector).to_matrix().reshape(3, 3))


#: Decimals (px) to which the coarse stages round each pattern's smoothing
#: width before grouping patterns of equal width into one filter call
PX_DECIMALS = 2


def _stage(patterns, q, pcs, om, arrays, binning, sigma, max_step):
    """One stage of the schedule: every pattern binned by *binning*, both
    it and the master pattern smoothed by *sigma* degrees."""
    n, shape = patterns.shape[0], patterns.shape[1:]
    b = binning
    level = bin_pattern(patterns, b, np.float32) if b > 1 else patterns
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
        mp.upper,
        mp.lower,
        float(mp.scale),
        MAX_EVALUATIONS[b == 1],
        np.deg2rad(TOLERANCE if b == 1 else COARSE_TOLERANCE),
        np.deg2rad(max_step),
    )


def _schedule(shape, levels):
    """(binning, smoothing) of each stage, coarse first."""
    return [(b, s) for b in pyramid_levels(shape, levels) for s in SMOOTHING.get(b, (0.0,))]


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


def coarse_arrays(
    patterns: np.ndarray,
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
    levels: Sequence[int] | None = None,
    max_step: float = MAX_STEP,
) -> OrientationResult:
    """The coarse stages of :func:`refine_arrays` alone, scored at full
    resolution.

    Each start runs the schedule without its last (full-resolution)
    stage; the result is then the better, by full-resolution NCC, of
    where it ended and its start (the coarse stages never make a start
    worse). For a caller that refines several candidates per pattern and
    runs the last stage only from where they agree.

    Parameters
    ----------
    patterns, quaternions, pcs, om, arrays, levels, max_step
        As :func:`refine_arrays`.

    Returns
    -------
    result
        :class:`OrientationResult` with the full-resolution NCC and
        ``converged`` False (the last stage did not run).
    """
    patterns = np.asarray(patterns)
    n = patterns.shape[0]
    shape = patterns.shape[1:]
    q0 = np.ascontiguousarray(quaternions, dtype=np.float64).reshape(n, 4)
    pcs = np.ascontiguousarray(pcs, dtype=np.float64).reshape(n, 3)
    om = np.ascontiguousarray(om, dtype=np.float64)
    q = q0
    evaluations = np.zeros(n, dtype=np.float64)
    for b, sigma in _schedule(shape, levels)[:-1]:
        q, _, k, _ = _stage(patterns, q, pcs, om, arrays, b, sigma, max_step)
        evaluations += k / b**2
    flat = np.ascontiguousarray(patterns.reshape(n, -1))
    args = (pcs, shape[0], shape[1], om, arrays.upper, arrays.lower, float(arrays.scale))
    ncc = _stack_ncc(flat, np.ascontiguousarray(q), *args)
    ncc0 = _stack_ncc(flat, q0, *args)
    evaluations += 2
    worse = ncc0 > ncc
    q = np.where(worse[:, None], q0, q)
    ncc = np.where(worse, ncc0, ncc)
    return OrientationResult(Rotation(q), ncc, evaluations, np.zeros(n, dtype=bool))


def refine_arrays(
    patterns: np.ndarray,
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
    levels: Sequence[int] | None = None,
    max_step: float = MAX_STEP,
) -> OrientationResult:
    """:func:`refine_patterns` on plain arrays, for map chunks.

    Parameters
    ----------
    patterns
        Patterns (N, rows, columns).
    quaternions
        Starting quaternions (N, 4).
    pcs
        Bruker PCs (N, 3).
    om
        Detector-to-sample matrix (:func:`detector_matrix`).
    arrays
        :func:`master_pattern_arrays` of the master pattern.
    levels, max_step
        See :func:`refine_patterns`.

    Returns
    -------
    result
        :class:`OrientationResult`.
    """
    patterns = np.asarray(patterns)
    n = patterns.shape[0]
    shape = patterns.shape[1:]
    q = np.ascontiguousarray(quaternions, dtype=np.float64).reshape(n, 4)
    pcs = np.ascontiguousarray(pcs, dtype=np.float64).reshape(n, 3)
    om = np.ascontiguousarray(om, dtype=np.float64)
    q0 = q
    schedule = _schedule(shape, levels)
    evaluations = np.zeros(n, dtype=np.float64)
    for b, sigma in schedule:
        q, ncc, k, conv = _stage(patterns, q, pcs, om, arrays, b, sigma, max_step)
        evaluations += k / b**2
    if len(schedule) > 1:
        # The coarse stages never make a start worse: where the start
        # itself correlates better, the last stage runs from it instead
        start = _stack_ncc(
            np.ascontiguousarray(patterns.reshape(n, -1)), q0, pcs, shape[0], shape[1], om,
            arrays.upper, arrays.lower, float(arrays.scale),
        )  # fmt: skip
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


def project_patterns(
    rotations: Rotation,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern | MasterPatternArrays,
    energy: float = 20.0,
) -> np.ndarray:
    """Return patterns projected by this module's kernel.

    The same intensities as kikuchipy's ``get_patterns`` (float32
    rounding aside) before any rescaling of the output; used to check the
    kernel against kikuchipy and to score orientations.

    Parameters
    ----------
    rotations
        Orientations (N,).
    detector
        Detector with one PC or N PCs.
    master_pattern, energy
        Lambert master pattern (or its arrays) and beam energy in kV.

    Returns
    -------
    patterns
        Array (N, rows, columns), float64.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation import master_patterns
    >>> from kikuchipy_geomdic.indexing.orientation import project_patterns
    >>> mp = master_patterns.master_pattern("Si")
    >>> det = EBSDDetector((30, 40), pc=[0.5, 0.4, 0.6], sample_tilt=70)
    >>> ours = project_patterns(Rotation.random(2), det, mp, 20)
    >>> ours.shape
    (2, 30, 40)
    """
    q = np.ascontiguousarray(Rotation(rotations).flatten().data, dtype=np.float64)
    arrays = master_pattern_arrays(master_pattern, energy)
    return project_arrays(
        q, detector_pcs(detector, q.shape[0]), detector_matrix(detector), arrays, detector.shape
    )


def project_derivatives(
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return projected patterns and their analytic derivatives by a
    rotation of the crystal and by the pattern's PC.

    One pass of the kernel: the gradient of the bilinear master-pattern
    interpolant by the crystal direction, chained through the Lambert
    projection, gives both the rotation derivative (``d x grad``) and the
    PC derivative (``grad`` along how the pixel's direction moves with the
    PC). Both are the exact derivatives of the model kikuchipy evaluates
    (almost everywhere: bilinear interpolation has kinks at the master
    pattern's cell edges), so a geometry column reduced against the
    rotation columns is free of finite-difference error.

    Parameters
    ----------
    quaternions
        Orientations (N, 4).
    pcs
        Bruker PCs (N, 3).
    om
        :func:`detector_matrix`.
    arrays
        :func:`master_pattern_arrays`.
    shape
        Pattern shape (rows, columns).

    Returns
    -------
    patterns
        (N, P), P = rows * columns, float64.
    rotation
        (N, P, 3): intensity per radian of the sample-frame rotation ``T``
        of ``g -> g * T`` (orix's right factor, the refinement's update).
    pc
        (N, P, 3): intensity per unit of the pattern's PCx, PCy, PCz
        (Bruker).

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation import master_patterns
    >>> from kikuchipy_geomdic.indexing.orientation import (
    ...     detector_matrix, master_pattern_arrays, project_arrays, project_derivatives)
    >>> det = EBSDDetector((40, 40), pc=[0.5, 0.3, 0.6], sample_tilt=70)
    >>> arrays = master_pattern_arrays(master_patterns.master_pattern("Si"), 20)
    >>> om, pc = detector_matrix(det), det.pc.reshape(1, 3)
    >>> q = Rotation.from_euler(np.deg2rad([[10, 20, 30]])).data
    >>> s, j_rot, j_pc = project_derivatives(q, pc, om, arrays, (40, 40))
    >>> h = [[1e-7, 0, 0]]
    >>> fd = (project_arrays(q, pc + h, om, arrays, (40, 40)).ravel() - s[0]) / 1e-7
    >>> bool(np.corrcoef(fd, j_pc[0, :, 0])[0, 1] > 0.9999)
    True
    """
    q = np.ascontiguousarray(quaternions, dtype=np.float64).reshape(-1, 4)
    return _project_stack_derivatives(
        q,
        np.ascontiguousarray(pcs, dtype=np.float64).reshape(-1, 3),
        int(shape[0]),
        int(shape[1]),
        np.ascontiguousarray(om, dtype=np.float64),
        arrays.upper,
        arrays.lower,
        float(arrays.scale),
    )


def project_arrays(
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
    shape: tuple[int, int],
) -> np.ndarray:
    """:func:`project_patterns` on plain arrays: quaternions (N, 4), Bruker
    PCs (N, 3), the :func:`detector_matrix` and the pattern shape."""
    q = np.ascontiguousarray(quaternions, dtype=np.float64).reshape(-1, 4)
    out = _project_stack(
        q,
        np.ascontiguousarray(pcs, dtype=np.float64).reshape(-1, 3),
        int(shape[0]),
        int(shape[1]),
        np.ascontiguousarray(om, dtype=np.float64),
        arrays.upper,
        arrays.lower,
        float(arrays.scale),
    )
    return out.reshape((q.shape[0],) + tuple(shape))


# --------------------------------------------------------------------- #
# Misindexed starts on a map
# --------------------------------------------------------------------- #


def _neighbour_median(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Median of each point's valid 8-neighbours (NaN where none)."""
    rows, cols = values.shape
    padded = np.full((rows + 2, cols + 2), np.nan)
    padded[1:-1, 1:-1] = np.where(valid, values, np.nan)
    stack = [
        padded[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
        for dr in (-1, 0, 1)
        for dc in (-1, 0, 1)
        if dr or dc
    ]
    with warnings.catch_warnings():
        # All-NaN neighbourhoods (isolated points) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.stack(stack), axis=0)


#: A point is poor when its NCC is below this fraction of its neighbours'
#: median NCC ...
NEIGHBOUR_FRACTION = 0.8

#: ... or below the map's median NCC by more than this many robust
#: standard deviations (MAD x 1.4826) of the map's NCCs, and by at least
#: the same fraction (a map of near-identical scores has a tiny MAD).
MAP_DEVIATIONS = 5.0


def poor_points(scores: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Return which points of a map scored poorly for where they are.

    Grains are larger than a step, so a point whose NCC is well below its
    neighbours' has most likely converged to a wrong orientation (a start
    misindexed at a wrong geometry, a local optimum).

    Parameters
    ----------
    scores
        NCC per map point, (rows, columns) (a 1D map as (1, n)).
    valid
        Points that were refined; default all finite scores.

    Returns
    -------
    poor
        Boolean array of the map's shape: NCC below
        :data:`NEIGHBOUR_FRACTION` times the median of the point's valid
        8-neighbours, or more than :data:`MAP_DEVIATIONS` robust standard
        deviations (and that fraction) below the map's median; never a
        point not valid.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.indexing.orientation import poor_points
    >>> s = np.full((4, 4), 0.5) + np.arange(16).reshape(4, 4) * 1e-3
    >>> s[1, 2] = 0.2
    >>> np.argwhere(poor_points(s)).tolist()
    [[1, 2]]
    """
    scores = np.asarray(scores, dtype=float)
    if valid is None:
        valid = np.isfinite(scores)
    valid = valid & np.isfinite(scores)
    if not valid.any():
        return np.zeros(scores.shape, dtype=bool)
    nb_med = _neighbour_median(scores, valid)
    v = scores[valid]
    med = np.median(v)
    mad = 1.4826 * np.median(np.abs(v - med))
    with np.errstate(invalid="ignore"):
        drop = max(MAP_DEVIATIONS * mad, (1 - NEIGHBOUR_FRACTION) * med)
        poor = (scores < NEIGHBOUR_FRACTION * nb_med) | (scores < med - drop)
    return poor & valid


def neighbour_seeds(
    rotations: np.ndarray, point: tuple[int, int], usable: np.ndarray, min_angle: float = 1.0
) -> np.ndarray:
    """Return the distinct orientations of a point's 8-neighbours.

    Parameters
    ----------
    rotations
        Quaternions (rows, columns, 4) of the map.
    point
        (row, column) of the point.
    usable
        Boolean (rows, columns): neighbours that may seed (refined and not
        poor themselves).
    min_angle
        Seeds closer than this (degrees, as rotations, no symmetry) to an
        earlier seed are dropped.

    Returns
    -------
    seeds
        Quaternions (k, 4), k <= 8.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.indexing.orientation import neighbour_seeds
    >>> q = np.tile([1.0, 0, 0, 0], (3, 3, 1))
    >>> q[0, 0] = [0, 1, 0, 0]
    >>> neighbour_seeds(q, (1, 1), np.ones((3, 3), bool)).shape
    (2, 4)
    """
    r0, c0 = point
    rows, cols = usable.shape
    seeds: list[np.ndarray] = []
    cos_half = math.cos(math.radians(min_angle) / 2)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = r0 + dr, c0 + dc
            if (dr or dc) and 0 <= r < rows and 0 <= c < cols and usable[r, c]:
                q = rotations[r, c]
                if all(abs(float(np.dot(q, s))) < cos_half for s in seeds):
                    seeds.append(q)
    return np.array(seeds).reshape(-1, 4)


# --------------------------------------------------------------------- #
# Pseudo-symmetric variants
# --------------------------------------------------------------------- #


@dataclass(frozen=True)
class VariantComparison:
    """Which of a point's refined variant candidates its pattern shows.

    Attributes
    ----------
    variant
        Index (N,) of the kept candidate.
    confidence
        Confidence index (N,) of the kept candidate (see
        :func:`compare_variants`): about its NCC when the pattern decides
        clearly between it and every rival, 0 when it does not decide.
    margin
        Cross-variant margin (N,): the kept candidate's confidence index
        minus the best other candidate's.
    indices
        Confidence index (N, M) of every candidate.
    ncc
        Plain NCC (N, M) of every candidate.
    significance
        The kept candidate's weakest pairwise margin over its standard
        error from the pattern's own noise (N,): ``min_b m_ab / se_ab``
        (see :func:`compare_variants`; ``inf`` with one candidate). Below
        about 2.5 the pattern does not decide between the kept candidate
        and a rival: the call is within the noise.
    """

    variant: np.ndarray
    confidence: np.ndarray
    margin: np.ndarray
    indices: np.ndarray
    ncc: np.ndarray
    significance: np.ndarray | None = None


def standardise(a: np.ndarray) -> np.ndarray:
    """Return *a* with zero mean and unit standard deviation along its last
    axis (rows of zeros stay zero): NCC is then a mean of products."""
    a = a - a.mean(axis=-1, keepdims=True)
    sd = a.std(axis=-1, keepdims=True)
    return a / np.where(sd > 0, sd, 1.0)


def compare_variants(
    patterns: np.ndarray,
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
) -> VariantComparison:
    r"""Compare the refined variant candidates of each pattern.

    Plain NCC barely tells 180 deg (polarity) variants apart: their
    simulated patterns correlate at 0.99, so their NCCs with any pattern
    differ in the third decimal. The comparison therefore looks only along
    where two candidates differ. With ``S_a``, ``S_b`` the standardised
    simulations of candidates a and b, ``E`` the standardised pattern and
    ``rho_ab`` the correlation of ``S_a`` with ``S_b``, the pair's margin
    is the correlation of ``E`` with their difference, normalised:

    .. math::

        m_{ab} = \frac{\mathrm{NCC}_a - \mathrm{NCC}_b}{1 - \rho_{ab}}
               = \frac{E \cdot (S_a - S_b)}{\tfrac{1}{2} |S_a - S_b|^2}.

    If the pattern is ``c S_a`` plus noise (NCC ``c``), ``m_ab`` is ``c``
    in expectation, whatever ``rho_ab``; for ``c S_b`` it is ``-c``; its
    noise grows as the two simulations become alike (see *significance*). The confidence
    index of candidate a is its worst margin, ``CI_a = min_b m_ab``: about
    the NCC when the pattern decides between a and every rival, near 0
    when a rival is as likely. The kept candidate has the largest CI (the
    largest NCC: only it can have a positive CI; the sign of
    ``NCC_a - NCC_b`` is the matched-filter test, optimal under white
    noise), and the cross-variant margin is its CI minus the next largest.

    The margin is not compared with a fixed number: its noise is measured
    on the pattern itself. With ``r = E - NCC_a S_a`` the residual of the
    kept candidate and ``D = S_a - S_b``, the noise of ``m_ab`` is that of
    ``r . D / (|D|^2 / 2)``; its variance is estimated from the products
    ``r_i D_i`` summed over blocks of :data:`SIGNIFICANCE_BLOCK` pixels
    (squared sums of blocks: the phosphor blur and the background
    removal correlate neighbouring pixels, and a white-noise estimate was
    overconfident, measured). The *significance* of the call is
    ``min_b m_ab / se_ab``, a z-score: measured on BaTiO3 patterns of 120
    px from ``Camera``, a median 1.6 for right calls at 30
    counts per pixel and 3.8 at 150.

    Parameters
    ----------
    patterns
        Patterns (N, rows, columns).
    quaternions
        Refined candidates (N, M, 4) per pattern, e.g. from each variant's
        start.
    pcs
        Bruker PCs (N, 3).
    om
        :func:`detector_matrix` of the detector.
    arrays
        :func:`master_pattern_arrays`.

    Returns
    -------
    comparison
        :class:`VariantComparison`.

    Examples
    --------
    Two BaTiO3 180 deg variants of one pattern: the right one is kept,
    with a confidence index near its NCC.

    >>> import numpy as np
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation import master_patterns
    >>> from kikuchipy_geomdic.indexing.variants import variant_operators
    >>> from kikuchipy_geomdic.indexing.orientation import (
    ...     compare_variants, detector_matrix, master_pattern_arrays, project_patterns)
    >>> mp = master_patterns.master_pattern("BaTiO3")
    >>> det = EBSDDetector((60, 60), pc=[0.5, 0.3, 0.6], sample_tilt=70)
    >>> r = Rotation.from_euler(np.deg2rad([[10, 30, 50]]))
    >>> flipped = variant_operators()[1] * r
    >>> pattern = project_patterns(flipped, det, mp)
    >>> q = np.stack([r.data, flipped.data], axis=1)
    >>> arrays = master_pattern_arrays(mp, 20)
    >>> c = compare_variants(pattern, q, det.pc.reshape(-1, 3), detector_matrix(det), arrays)
    >>> int(c.variant[0]), round(float(c.confidence[0]), 3), bool(c.ncc[0, 0] > 0.95)
    (1, 1.0, True)
    """
    patterns = np.asarray(patterns)
    shape = patterns.shape[1:]
    s, e, ncc, rho = _variant_products(patterns, quaternions, pcs, om, arrays)
    n, m = ncc.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        margins = (ncc[:, :, None] - ncc[:, None, :]) / (1 - rho)
    # One pattern twice (two starts refined to one orientation): no rivalry
    margins = np.where(1 - rho < 1e-9, 0.0, margins)
    idx = np.arange(m)
    margins[:, idx, idx] = np.inf
    ci = margins.min(axis=2) if m > 1 else ncc.copy()
    order = np.argsort(-ci, axis=1, kind="stable")
    variant = order[:, 0]
    rows = np.arange(n)
    confidence = ci[rows, variant]
    margin = confidence - ci[rows, order[:, 1]] if m > 1 else np.zeros(n)
    # Significance: each rival's margin over its standard error
    sig = np.full(n, np.inf)
    sa = s[rows, variant]
    r = e[:, 0] - ncc[rows, variant][:, None] * sa
    k = s.shape[-1]
    for b in range(m):
        rival = (variant != b) & (1 - rho[rows, variant, b] >= 1e-9)
        if not rival.any():
            continue
        d = sa[rival] - s[rival, b]
        blocks = _block_sums((r[rival] * d).reshape((-1,) + shape), SIGNIFICANCE_BLOCK)
        se = np.sqrt((blocks**2).sum(axis=(1, 2))) / k / (0.5 * (d**2).mean(axis=-1))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(se > 0, margins[rows[rival], variant[rival], b] / se, np.inf)
        sig[rival] = np.minimum(sig[rival], z)
    return VariantComparison(variant, confidence, margin, ci, ncc, sig)


#: Side (px) of the blocks over which :func:`compare_variants` sums the
#: products of residual and candidate difference to estimate a margin's
#: standard error (neighbouring pixels are correlated by the blur and the
#: background removal)
SIGNIFICANCE_BLOCK = 4


def _block_sums(a: np.ndarray, block: int) -> np.ndarray:
    """Sums of *a* (N, rows, columns) over blocks of *block* x *block* px
    (the last blocks smaller where the side does not divide)."""
    r = np.arange(0, a.shape[1], block)
    c = np.arange(0, a.shape[2], block)
    return np.add.reduceat(np.add.reduceat(a, r, axis=1), c, axis=2)


def _variant_products(patterns, quaternions, pcs, om, arrays):
    """Standardised simulations (N, M, K) of the candidates, standardised
    patterns (N, 1, K), their NCCs (N, M) and the candidates' mutual
    correlations (N, M, M)."""
    n = patterns.shape[0]
    quaternions = np.asarray(quaternions, dtype=np.float64).reshape(n, -1, 4)
    m = quaternions.shape[1]
    shape = patterns.shape[1:]
    pcs = np.asarray(pcs, dtype=np.float64).reshape(n, 3)
    sims = project_arrays(quaternions.reshape(-1, 4), np.repeat(pcs, m, axis=0), om, arrays, shape)
    s = standardise(sims.reshape(n, m, -1))
    e = standardise(np.asarray(patterns, dtype=np.float64).reshape(n, 1, -1))
    ncc = (s * e).mean(axis=-1)
    rho = np.einsum("npk,nqk->npq", s, s) / s.shape[-1]
    return s, e, ncc, rho
