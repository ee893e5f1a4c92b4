"""One fit of the DIC fields: the per-pattern linear model
(:func:`_linearise`), each pattern's weights and vector variance, the
weighted joint solve with the rotations eliminated (:func:`_joint_solve`),
the damping schedule of the loops' trial steps and the bookkeeping of
equivalent parameters (:func:`_solved_values`, :func:`_expand`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kikuchipy_geomdic.calibration.jacobian import pattern_jacobian
from kikuchipy_geomdic.calibration.solve import JointUpdate, solve_joint
from kikuchipy_geomdic.geometry import EQUIVALENT_PARAMETERS, MapGeometry
from kikuchipy_geomdic.patterns import displacement as dsp

#: Largest number of trial steps, each with ten times the damping of the
#: one before, before an iteration gives up.
MAX_TRIALS = 3

#: Factor by which the damping grows after a rejected trial step and
#: shrinks after an accepted one: Levenberg-Marquardt's usual tenfold,
#: so that :data:`MAX_TRIALS` trials span three decades.
DAMPING_FACTOR = 10

#: Paper solver: lambda of Eq. 10 when *damping* is not given, a light
#: damping that leaves a well-conditioned Gauss-Newton step almost as is.
PAPER_DAMPING = 1e-3

#: Joint solver: the smallest damping a rejected step is retried with.
#: The default start is Gauss-Newton (damping 0), which tenfold growth
#: alone would never leave; the paper solver's default damping.
MIN_RETRY_DAMPING = PAPER_DAMPING

#: Smallest vector variance (px^2) assumed: DIC is not more precise than
#: 1e-4 px, and a start at the exact truth must not give infinite weights.
MIN_VARIANCE = 1e-8

#: Unknowns per pattern besides the geometry (its small rotation): the
#: degrees of freedom its residuals lose when its variance is estimated.
ROTATION_UNKNOWNS = 3

#: Vector variance (px^2) assumed for every pattern when none has enough
#: vectors (more than :data:`ROTATION_UNKNOWNS` components) to estimate
#: its own: all patterns then weigh the same, one square pixel each.
FALLBACK_VARIANCE = 1.0


def _solved_values(geometry: MapGeometry, solved, split: Mapping[str, str]) -> np.ndarray:
    """The coordinates of *geometry* along the solved parameters: a base
    column moves its equivalents too (:func:`_expand`), so its coordinate
    is the combination, e.g. tilt - sample_tilt."""
    values = dict(zip(solved, geometry.values(solved)))
    for name, base in split.items():
        values[base] += EQUIVALENT_PARAMETERS[name][1] * float(geometry.values([name])[0])
    return np.array([values[n] for n in solved])


def _expand(delta: Mapping[str, float], split: Mapping[str, str]) -> dict[str, float]:
    """Changes of all parameters from those of the solved ones: a change
    of a base column is split with its equivalent at minimum norm (for
    tilt and sample_tilt, equal and opposite halves)."""
    out = dict(delta)
    for name, base in split.items():
        if base in delta:
            f = EQUIVALENT_PARAMETERS[name][1]
            out[base] = delta[base] / (1 + f**2)
            out[name] = f * delta[base] / (1 + f**2)
    return out


def _pattern_weights(field: dsp.DisplacementField, variances: np.ndarray | None) -> np.ndarray:
    """Inverse variances (N, 2R) of the ROI components: an ROI mean of
    ``c`` vectors has ``c`` times a vector's precision, and each pattern
    has its own vector variance (grain boundaries, worse patterns)."""
    w = np.repeat(field.counts.astype(np.float64), 2, axis=1)
    if variances is not None:
        w = w / variances[:, None]
    return w


def _pattern_variances(
    field: dsp.DisplacementField, jg: np.ndarray, jr: np.ndarray, update: JointUpdate
) -> np.ndarray:
    """Per-pattern vector variances from the residuals of a fit, never
    below the median pattern's, so that a lucky pattern gains no weight."""
    n = field.n_patterns
    b = field.u.reshape(n, -1)
    r = b + jg @ update.delta + np.einsum("nmk,nk->nm", jr, update.rotations)
    c = np.repeat(field.counts, 2, axis=1)
    m = (c > 0).sum(axis=1)
    rss = (c * r**2).sum(axis=1)
    var = np.where(m > ROTATION_UNKNOWNS, rss / np.maximum(m - ROTATION_UNKNOWNS, 1), np.nan)
    floor = np.nanmedian(var) if np.isfinite(var).any() else FALLBACK_VARIANCE
    floor = max(floor, MIN_VARIANCE)
    return np.where(np.isfinite(var), np.maximum(var, floor), floor)


def _linearise(problem, geometry, field, names):
    """Per-pattern geometry and rotation Jacobians (N, 2R, K), (N, 2R, 3)
    and displacements (N, 2R) at the measured positions."""
    n = field.n_patterns
    jg, jr = pattern_jacobian(geometry, problem.points, field.positions, names, problem.steps)
    return jg.reshape(n, -1, len(names)), jr.reshape(n, -1, 3), field.u.reshape(n, -1)


def _joint_solve(
    field: dsp.DisplacementField,
    linear: tuple[np.ndarray, np.ndarray, np.ndarray],
    columns: Sequence[int],
    offsets: np.ndarray,
    prior: float | None,
    damping: float,
    common: bool = False,
) -> tuple[JointUpdate, np.ndarray]:
    """One joint solve with the geometry *columns* of *linear*; also
    returns the per-pattern variances it weighted with. *common*: the
    rotation all patterns share is a global unknown and the *prior* holds
    their scatter about it (the crystal model)."""
    jg, jr, b = linear
    jg = jg[..., list(columns)]
    # First without the prior, to learn each pattern's noise; then with
    # the weights in inverse pixels squared, the units of the prior
    first = solve_joint(jg, jr, b, _pattern_weights(field, None), damping=damping)
    var = _pattern_variances(field, jg, jr, first)
    w = _pattern_weights(field, var)
    update = solve_joint(
        jg, jr, b, w, prior=prior, offsets=offsets, damping=damping, common=common
    )
    return update, var


def _prior_per_axis(prior: float | None) -> float | None:
    """The RMS orientation error *prior* (degrees, of the rotation angle)
    as an RMS per rotation-vector axis in radians, the solve's unit."""
    return None if prior is None else np.deg2rad(prior) / np.sqrt(3)
