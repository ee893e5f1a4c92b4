"""The Cramer-Rao bound of the geometry: the best precision a map allows.

Whatever the method, no unbiased estimate of the geometry from a set of
patterns can scatter less than the Cramer-Rao bound of those patterns.
:func:`cramer_rao_bound` computes it for a user's map, at a given geometry
and orientations, from the patterns themselves, so that a calibration's
standard errors can be judged against what the data could give at best
(:meth:`CramerRaoBound.table`, or
:meth:`~kikuchipy_geomdic.calibration.result.GeometryRefinementResult.compare_bound`).

The model
---------
Each observed pattern is modelled as ``a * s(p, g) + b`` plus white
noise: ``s`` the pattern simulated at the geometry ``p`` and orientation
``g``, ``a`` and ``b`` a gain and an offset of the pattern's own. The
unknowns of pattern ``i`` are the geometry (shared by all patterns) and
the nuisances: a small rotation of its crystal (``g -> g * T``, as the
refinement updates orientations), ``a_i`` and ``b_i``. With Gaussian
white noise of variance ``sigma_i^2`` the Fisher information of pattern
``i`` is ``J_i^T J_i / sigma_i^2``, ``J_i`` the derivatives of the model
by every unknown (:func:`~kikuchipy_geomdic.calibration.jacobian.intensity_jacobian`:
analytic for the rotation and each pattern's PC, and a detector angle as
the crystal rotation plus the change of the PC field it amounts to). Each
pattern's nuisances are eliminated by a Schur complement, the reduced
matrices summed over the patterns and inverted: the square roots of the
diagonal are the bound. On a multi-phase map each pattern is simulated
from its phase's master pattern.

The noise variance is estimated from each pattern's residual after the
fit of ``a`` and ``b``, so anything the simulation does not reproduce
(band profiles, background, detector artefacts, Poisson noise whose
variance follows the intensity) counts as noise: on experimental patterns
the bound is conservative, larger than it would be for a perfect model.
Correlated noise (e.g. after a background-removal filter) is treated as
white, which can make it either way wrong.

Degeneracies
------------
``tilt`` and ``sample_tilt`` enter kikuchipy's projection only through
their difference (:data:`~kikuchipy_geomdic.geometry.parameters.EQUIVALENT_PARAMETERS`):
with both given there is one column for both, the bound of their
difference is reported as ``"tilt-sample_tilt"`` and each alone is
``inf``, as in ``GeometryRefinementResult.standard_errors``. With free
orientations the detector angles are seen only through the PC field
across the map; a parameter in a direction the patterns do not constrain
at all gets ``inf``.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._points import _map_points, calibration_points
from kikuchipy_geomdic.calibration.jacobian import INTENSITY_STEPS, intensity_jacobian
from kikuchipy_geomdic.calibration.uncertainty import TILT_DIFFERENCE
from kikuchipy_geomdic.geometry import (
    DEFAULT_PARAMETERS,
    UNITS,
    MapGeometry,
    check_parameters,
    solved_parameters,
)
from kikuchipy_geomdic.geometry.maps import flat_index, navigation_shape
from kikuchipy_geomdic.indexing.orientation import master_pattern_arrays
from kikuchipy_geomdic.indexing.phases_to_refine import phases_to_refine
from kikuchipy_geomdic.patterns.simulation import check_master_pattern

__all__ = ["CramerRaoBound", "cramer_rao_bound", "BOUND_STEPS"]

#: Steps per geometry parameter (PC fractions, degrees) of the
#: differences of the PC field and detector matrix: those of the
#: intensity Jacobian.
BOUND_STEPS = INTENSITY_STEPS

#: Memory budget (bytes) of one chunk's derivatives, float64.
MAX_BYTES = 128 * 2**20

#: Directions whose reduced information, relative to the full, is below
#: this are taken as not constrained at all (``inf``), as in
#: :func:`~kikuchipy_geomdic.calibration.solve.solve_joint`.
RTOL = 1e-10

# Nuisance columns per pattern after the geometry: rotation (3), gain, offset
_N_ROT = 3

_PC = ("pcx", "pcy", "pcz")


@dataclass(frozen=True)
class CramerRaoBound:
    """The Cramer-Rao bound of the geometry of a map
    (:func:`cramer_rao_bound`).

    Attributes
    ----------
    parameter_names
        The parameters asked for, in canonical order.
    sigma
        ``{name: bound}``: the smallest standard deviation, in the
        parameter's unit, of any unbiased estimate with every orientation
        free; ``"tilt-sample_tilt"`` too when either tilt is asked for.
        ``inf`` where the patterns do not constrain a parameter (each of
        tilt and sample_tilt when both are asked for).
    sigma_known_orientations
        The same with the orientations known exactly (only gain and
        offset free per pattern): never larger than *sigma*.
    columns
        The parameters with a column in the Fisher matrix (of tilt and
        sample_tilt only one).
    covariance, covariance_known_orientations
        The bounding covariances (K, K) in the order of *columns*
        (pseudo-inverses where degenerate).
    points
        Map positions (N, 2) of the patterns used.
    noise
        Noise standard deviation (N,) per pixel of each pattern, in its
        intensity unit: estimated from the residual of the fit, or given.
    gain, offset
        The fitted ``a`` and ``b`` (N,) of ``observed = a * simulated + b``.
    r_squared
        Fraction (N,) of each pattern's variance the fit explains.
    """

    parameter_names: tuple[str, ...]
    sigma: dict[str, float]
    sigma_known_orientations: dict[str, float]
    columns: tuple[str, ...]
    covariance: np.ndarray
    covariance_known_orientations: np.ndarray
    points: np.ndarray
    noise: np.ndarray
    gain: np.ndarray
    offset: np.ndarray
    r_squared: np.ndarray

    def __repr__(self) -> str:
        return self.table()

    def table(self, standard_errors: Mapping[str, float] | None = None) -> str:
        """Return the bound per parameter as text.

        Parameters
        ----------
        standard_errors
            ``{name: sigma}`` of an estimate, e.g.
            ``GeometryRefinementResult.standard_errors``: added as a
            column with its ratio to the bound (1 at the limit).

        Returns
        -------
        table
        """
        head = (
            f"{type(self).__name__} ({len(self.points)} patterns, median R^2 "
            f"{np.median(self.r_squared):.2f}, white-noise model)"
        )
        cols = f"{'parameter':<17}{'bound':>10}{'ori known':>11}"
        if standard_errors is not None:
            cols += f"{'sigma':>10}{'ratio':>8}"
        lines = [head, cols + "  unit"]
        for name, bound in self.sigma.items():
            known = self.sigma_known_orientations[name]
            line = f"{name:<17}" + _number(bound, 10) + _number(known, 11)
            if standard_errors is not None:
                se = standard_errors.get(name, float("nan"))
                line += _number(se, 10)
                ratio = se / bound if np.isfinite(bound) and bound > 0 else float("nan")
                line += f"{ratio:>8.2f}" if np.isfinite(ratio) else f"{'-':>8}"
            unit = "deg" if name == TILT_DIFFERENCE else UNITS[name]
            lines.append(line + "  " + ("PC" if unit.startswith("fraction") else unit))
        if any(not np.isfinite(self.sigma.get(n, 0)) for n in ("tilt", "sample_tilt")):
            lines.append("tilt and sample_tilt: only their difference is determined")
        return "\n".join(lines)


def _number(value: float, width: int) -> str:
    return f"{value:>{width}.2e}" if np.isfinite(value) else f"{'-':>{width}}"


def cramer_rao_bound(
    patterns: EBSD | np.ndarray,
    rotations: Rotation | CrystalMap,
    geometry: MapGeometry,
    master_pattern: EBSDMasterPattern | Sequence[EBSDMasterPattern],
    energy: float,
    *,
    points: int | np.ndarray | None = None,
    parameters: Sequence[str] = DEFAULT_PARAMETERS,
    noise: float | np.ndarray | None = None,
    steps: Mapping[str, float] | None = None,
    max_bytes: int = MAX_BYTES,
) -> CramerRaoBound:
    """Return the Cramer-Rao bound of the geometry parameters of a map.

    Per pattern: the pattern simulated at *geometry* and its orientation
    is fitted to the observed one as ``a * simulated + b`` (least
    squares); the residual gives the noise variance (white-noise model:
    model mismatch counts as noise, so the bound is conservative); the
    derivatives of ``a * simulated + b`` by the geometry, by a small
    rotation of the crystal and by ``a`` and ``b`` give the Fisher
    information, from which the rotation, gain and offset are eliminated
    (Schur complement). The sum over the patterns, inverted, bounds the
    covariance of any unbiased estimate of the geometry.

    Parameters
    ----------
    patterns
        The map (``EBSD`` or ``LazyEBSD``, navigation shape that of
        *geometry*) or an array (N, rows, columns) of the calibration
        patterns. Processed as for the calibration (background removed);
        a pattern with NaN raises.
    rotations
        Orientations of the patterns: N, or one per map point (a
        ``CrystalMap`` of the whole map or a ``Rotation`` of its size),
        then taken at *points*.
    geometry
        The geometry at which the bound is evaluated (the refined or the
        true one), with the map's navigation shape and step sizes.
    master_pattern
        Lambert master pattern of the phase, or a list of them, one per
        phase of a multi-phase map (*rotations* a ``CrystalMap``), matched
        to its phases as the calibration matches them
        (:func:`~kikuchipy_geomdic.indexing.phases_to_refine.phases_to_refine`);
        the patterns of a phase without one are left out, with a warning.
    energy
        Beam energy in kV.
    points
        Map positions (N, 2) of the patterns, (row, column) integers; an
        int picks that many points spread over the map, as
        :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic` does
        (signal only). Default: every map point (an array must then hold
        one pattern per map point, row-major).
    parameters
        Geometry parameters, from
        :data:`~kikuchipy_geomdic.geometry.parameters.PARAMETERS`; default those
        ``refine_geometry_dic`` refines. Parameters left out are taken as
        known.
    noise
        Known noise standard deviation per pixel (a number or one per
        pattern), in the patterns' intensity unit. Default: estimated
        from each pattern's residual.
    steps
        Central-difference steps ``{name: step}`` replacing
        :data:`BOUND_STEPS`.
    max_bytes
        Memory budget of one chunk's derivatives; patterns are processed
        in chunks.

    Returns
    -------
    bound
        :class:`CramerRaoBound`.

    Raises
    ------
    TypeError
        For a *geometry*, *patterns*, *rotations* or *master_pattern* of
        the wrong type.
    ValueError
        If shapes or counts do not match, a pattern holds NaN or infinite
        values, a simulated pattern is blank, or a pattern fits exactly
        (no noise to estimate: pass *noise*).

    Examples
    --------
    >>> from kikuchipy_geomdic.calibration.bound import cramer_rao_bound
    >>> from kikuchipy_geomdic.validation.synthetic import synthetic_map
    >>> sm = synthetic_map("Si", (2, 2), shape=(40, 40), dose=100, seed=0)
    >>> crb = cramer_rao_bound(
    ...     sm.signal, sm.xmap, sm.geometry, sm.master_pattern, sm.energy,
    ...     parameters=["pcx", "pcy", "pcz"],
    ... )
    >>> crb.columns
    ('pcx', 'pcy', 'pcz')
    >>> bool(crb.sigma_known_orientations["pcx"] <= crb.sigma["pcx"] < 1e-2)
    True
    """
    if not isinstance(geometry, MapGeometry):
        raise TypeError(f"geometry must be a MapGeometry, not {type(geometry).__name__}")
    names = check_parameters(parameters)
    columns, split = solved_parameters(names)
    step = _steps(columns, steps)
    exp, pts = _patterns(patterns, geometry, points)
    which, arrays = _phases(master_pattern, rotations, pts, geometry.navigation_shape, energy)
    rot = _rotations(rotations, pts, geometry.navigation_shape)
    sigma = _noise(noise, len(pts))
    if (which < 0).any():
        kept = which >= 0
        exp, pts, rot, which = exp[kept], pts[kept], rot[kept], which[kept]
        sigma = None if sigma is None else sigma[kept]

    n, k = len(pts), len(columns)
    n_px = exp.shape[1] * exp.shape[2]
    # Derivatives (chunk, pixels, K + 5), the PC and rotation ones they are
    # built from and the patterns, all float64
    chunk = max(1, int(max_bytes // (n_px * (k + 2 * _N_ROT + 7) * 8)))
    fisher = np.empty((n, k + _N_ROT + 2, k + _N_ROT + 2))
    fit = np.empty((4, n))
    for phase, phase_arrays in enumerate(arrays):
        of_phase = np.flatnonzero(which == phase)
        for start in range(0, len(of_phase), chunk):
            sl = of_phase[start : start + chunk]
            fisher[sl], fit[:, sl] = _fisher(
                exp[sl],
                rot[sl],
                pts[sl],
                geometry,
                phase_arrays,
                columns,
                step,
                None if sigma is None else sigma[sl],
            )

    geo = np.arange(k)
    free = np.arange(k, k + _N_ROT + 2)
    known = np.arange(k + _N_ROT, k + _N_ROT + 2)
    full = fisher[:, geo][:, :, geo].sum(axis=0)
    cov = _covariance(_reduce(fisher, geo, free), full)
    cov_known = _covariance(_reduce(fisher, geo, known), full)
    gain, offset, noise_sd, r2 = fit
    return CramerRaoBound(
        parameter_names=names,
        sigma=_sigmas(cov, names, columns, split),
        sigma_known_orientations=_sigmas(cov_known, names, columns, split),
        columns=columns,
        covariance=cov,
        covariance_known_orientations=cov_known,
        points=pts,
        noise=noise_sd,
        gain=gain,
        offset=offset,
        r_squared=r2,
    )


# --------------------------------------------------------------------- #
# Inputs
# --------------------------------------------------------------------- #


def _steps(columns, steps) -> dict[str, float]:
    out = dict(BOUND_STEPS)
    if steps:
        check_parameters(list(steps))
        out.update({k: float(v) for k, v in steps.items()})
    # The angles' columns are built from the PC columns
    out = {n: out[n] for n in dict.fromkeys((*_PC, *columns))}
    if not all(np.isfinite(v) and v > 0 for v in out.values()):
        raise ValueError(f"Finite-difference steps must be positive, not {out}")
    return out


def _patterns(patterns, geometry: MapGeometry, points) -> tuple[np.ndarray, np.ndarray]:
    """The patterns (N, rows, columns) as float64 and their map positions."""
    nav = geometry.navigation_shape
    if isinstance(patterns, EBSD):
        if navigation_shape(patterns) != nav:
            raise ValueError(
                f"The signal's navigation shape {navigation_shape(patterns)} differs "
                f"from the geometry's {nav}"
            )
        if points is not None and np.ndim(points) == 0:
            pts = calibration_points(nav, int(points))
        else:
            pts = _check_points(points, nav)
        data = patterns.data.reshape((nav[0] * nav[1],) + patterns.data.shape[-2:])
        data = data[flat_index(pts, nav)]
        if hasattr(data, "compute"):
            data = data.compute()
    elif isinstance(patterns, np.ndarray):
        data = patterns
        if data.ndim != 3:
            raise ValueError(
                f"patterns must be an EBSD signal or an (N, rows, columns) array, not "
                f"an array of shape {data.shape}"
            )
        if points is not None and np.ndim(points) == 0:
            raise ValueError("points as a number needs an EBSD signal; give (N, 2) positions")
        if points is None and len(data) != nav[0] * nav[1]:
            raise ValueError(
                f"{len(data)} patterns for a map of {nav[0]} x {nav[1]} points: pass their "
                "map positions as points"
            )
        pts = _check_points(points, nav)
        if len(pts) != len(data):
            raise ValueError(f"{len(data)} patterns but {len(pts)} points")
    else:
        raise TypeError(
            f"patterns must be an EBSD signal or a NumPy array, not {type(patterns).__name__}"
        )
    data = np.asarray(data, dtype=np.float64)
    if data.shape[1:] != tuple(geometry.shape):
        raise ValueError(
            f"Pattern shape {data.shape[1:]} differs from the geometry's detector shape "
            f"{geometry.shape}"
        )
    if len(data) == 0:
        raise ValueError("No patterns given")
    bad = ~np.isfinite(data).all(axis=(1, 2))
    if bad.any():
        raise ValueError(
            f"{bad.sum()} pattern(s) contain NaN or infinite values, e.g. at (row, col) "
            f"{pts[bad][0].tolist()}: leave them out of points"
        )
    return data, pts


def _check_points(points, nav: tuple[int, int]) -> np.ndarray:
    if points is None:
        rows, cols = np.indices(nav)
        return np.stack([rows.ravel(), cols.ravel()], axis=1)
    return _map_points(points, nav)


def _rotations(rotations, pts: np.ndarray, nav: tuple[int, int]) -> Rotation:
    if isinstance(rotations, CrystalMap):
        rotations = rotations.rotations
    if not isinstance(rotations, Rotation):
        raise TypeError(
            f"rotations must be an orix Rotation or CrystalMap, not {type(rotations).__name__}"
        )
    q = rotations.data.reshape(-1, 4)
    return Rotation(_at_points(q, pts, nav, f"{len(q)} rotations"))


def _at_points(values: np.ndarray, pts: np.ndarray, nav: tuple[int, int], what: str):
    """*values*, one per pattern or one per map point, at the patterns'
    points *pts*; *what* names them in the error."""
    if len(values) == len(pts):
        return values
    if len(values) == nav[0] * nav[1]:
        return values[flat_index(pts, nav)]
    raise ValueError(
        f"{what} for {len(pts)} patterns: give one per pattern or one per map point "
        f"({nav[0] * nav[1]})"
    )


def _phases(master_pattern, rotations, pts: np.ndarray, nav, energy) -> tuple[np.ndarray, list]:
    """Which of the master patterns' arrays (the list returned) each point
    of *pts* is simulated with: its phase's (-1: none, the point left out,
    with a warning). One master pattern serves every point."""
    if not isinstance(master_pattern, (list, tuple)):
        check_master_pattern(master_pattern)
        return np.zeros(len(pts), dtype=int), [master_pattern_arrays(master_pattern, energy)]
    if not isinstance(rotations, CrystalMap):
        raise TypeError(
            "A list of master patterns needs rotations as a CrystalMap, whose phases "
            f"they are matched to, not {type(rotations).__name__}"
        )
    phases = phases_to_refine(rotations, master_pattern, energy=energy)
    # A calibration's xmap (one point per pattern) or the whole map's
    what = f"A CrystalMap of {rotations.size} points"
    of_point = _at_points(rotations.phase_id, pts, nav, what)
    which = np.full(len(pts), -1)
    for i, phase in enumerate(phases):
        which[of_point == phase.phase_id] = i
    if (which < 0).all():
        raise ValueError("No pattern of the given points is of a phase with a master pattern")
    if (which < 0).any():
        warnings.warn(
            f"{int((which < 0).sum())} of {len(pts)} patterns are of phases without a master "
            "pattern: left out of the bound",
            UserWarning,
            stacklevel=3,
        )
    return which, [phase.arrays(energy) for phase in phases]


def _noise(noise, n: int) -> np.ndarray | None:
    if noise is None:
        return None
    sd = np.broadcast_to(np.asarray(noise, dtype=np.float64), (n,)).copy()
    if not (np.isfinite(sd).all() and (sd > 0).all()):
        raise ValueError("noise must be positive and finite")
    return sd


# --------------------------------------------------------------------- #
# Fisher information
# --------------------------------------------------------------------- #


def _fisher(exp, rot, pts, geometry, arrays, columns, step, sigma):
    """Per-pattern Fisher matrices (n, K + 5, K + 5), columns geometry,
    rotation (3, radians), gain, offset; and gain, offset, noise SD and
    R^2 (4, n) of the fits."""
    n = len(pts)
    s0, j_geo, j_rot = intensity_jacobian(geometry, pts, rot, arrays, columns, step)
    y = exp.reshape(n, -1)
    sc = s0 - s0.mean(axis=1, keepdims=True)
    yc = y - y.mean(axis=1, keepdims=True)
    ss = (sc**2).sum(axis=1)
    if (ss == 0).any():
        raise ValueError(
            f"The simulated pattern at (row, col) {pts[ss == 0][0].tolist()} is blank: "
            "check the orientation, geometry and master pattern"
        )
    gain = (sc * yc).sum(axis=1) / ss
    offset = y.mean(axis=1) - gain * s0.mean(axis=1)
    rss = ((yc - gain[:, None] * sc) ** 2).sum(axis=1)
    r2 = 1 - rss / np.maximum((yc**2).sum(axis=1), np.finfo(float).tiny)
    if sigma is None:
        # Two fitted numbers per pattern; the other unknowns are few
        # against thousands of pixels
        var = rss / (y.shape[1] - 2)
        # A float32 simulation fitted by the float64 kernel leaves only
        # round-off, about 1e-14 of the variance
        var = np.where(r2 > 1 - 1e-10, 0.0, var)
        if (var <= 0).any():
            raise ValueError(
                f"The pattern at (row, col) {pts[var <= 0][0].tolist()} is fitted exactly "
                "by the simulation: no noise to estimate; pass noise"
            )
    else:
        var = sigma**2
    jac = np.concatenate([j_geo, j_rot], axis=-1) * gain[:, None, None]
    jac = np.concatenate([jac, s0[..., None], np.ones_like(s0)[..., None]], axis=-1)
    fisher = np.einsum("npi,npj->nij", jac, jac) / var[:, None, None]
    return fisher, np.stack([gain, offset, np.sqrt(var), r2])


def _reduce(fisher: np.ndarray, geo: np.ndarray, nuisance: np.ndarray) -> np.ndarray:
    """Sum over patterns of the geometry block with the *nuisance*
    columns eliminated (Schur complement)."""
    g = fisher[:, geo][:, :, geo]
    c = fisher[:, geo][:, :, nuisance]
    a = fisher[:, nuisance][:, :, nuisance]
    # Rotation and offset columns differ by orders of magnitude: invert
    # the correlation form
    d = np.sqrt(np.diagonal(a, axis1=1, axis2=2))
    d = np.where(d > 0, d, 1.0)
    a_inv = np.linalg.pinv(a / d[:, :, None] / d[:, None, :], hermitian=True)
    a_inv = a_inv / d[:, :, None] / d[:, None, :]
    return (g - c @ a_inv @ np.swapaxes(c, 1, 2)).sum(axis=0)


def _covariance(reduced: np.ndarray, full: np.ndarray) -> np.ndarray:
    """The inverse of *reduced*, with directions whose information is a
    negligible part of the full (*full*: before elimination) set to inf."""
    scale = np.sqrt(np.clip(np.diag(full), 0, None))
    if np.any(scale == 0):
        raise ValueError(
            "A geometry parameter has no effect on the simulated patterns; check the steps"
        )
    m = reduced / np.outer(scale, scale)
    mu, v = np.linalg.eigh((m + m.T) / 2)
    keep = mu > RTOL * max(mu.max(), 1.0)
    cov = (v[:, keep] / mu[keep]) @ v[:, keep].T / np.outer(scale, scale)
    null = v[:, ~keep]
    if null.size:
        undetermined = np.abs(null).max(axis=1) > 1e-9
        cov[undetermined, :] = np.inf
        cov[:, undetermined] = np.inf
    return cov


def _sigmas(cov, names, columns, split) -> dict[str, float]:
    se = dict(zip(columns, map(float, np.sqrt(np.clip(np.diag(cov), 0, None)))))
    if "tilt" in names or "sample_tilt" in names:
        se[TILT_DIFFERENCE] = se["tilt" if "tilt" in columns else "sample_tilt"]
    for name, base in split.items():
        # Only their difference is determined
        se[name] = se[base] = float("inf")
    return {k: se[k] for k in (*names, TILT_DIFFERENCE) if k in se}
