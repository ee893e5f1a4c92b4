"""The full field's linear system at a geometry and orientations
(:func:`_intensity_system`): the model patterns made as the patterns were
(:func:`_model`), residuals and Jacobians with each pattern's gain and
offset projected out (:func:`_project_out`), the pixels' noise variances
(:func:`_pixel_variances`), the system as the Gauss-Newton steps keep
it (:class:`_System`) and its solution with parameters held (:func:`_hold`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._dic_fit import _expand, _solved_values
from kikuchipy_geomdic.calibration._processing import _compared
from kikuchipy_geomdic.calibration.jacobian import INTENSITY_STEPS, _intensity_chain
from kikuchipy_geomdic.calibration.solve import JointSystem
from kikuchipy_geomdic.geometry import MapGeometry, rotations_from_vectors

#: Smallest pixel noise variance of the full field, as a fraction of its
#: pattern's mean.
MIN_PIXEL_VARIANCE = 0.3


def _project_out(a, unit, scale):
    """*a* (N, K, P), pattern planes, times each pattern's *scale* (N,),
    with each pattern's constant and *unit* (N, P) direction removed from
    every column, returned as (N, P, K) float64 in two passes over the
    pixels (numpy's broadcasting made five and was the full field's
    largest cost). A view of (N, K, P) planes: :meth:`JointSystem.build`
    stacks them so, and transposed twice they cost it a strided copy of
    the whole Jacobian (0.03-0.07 s at 100 patterns of 120 px)."""
    return np.swapaxes(_project_out_planes(a, unit, scale), 1, 2)


@nb.njit(cache=True, nogil=True)
def _project_out_planes(a, unit, scale):
    # :func:`_project_out` as (N, K, P) planes
    n, k, p = a.shape
    out = np.empty((n, k, p))
    for i in range(n):
        for c in range(k):
            mean = 0.0
            along = 0.0
            for j in range(p):
                v = a[i, c, j]
                mean += v
                along += unit[i, j] * v
            mean /= p
            # unit sums to zero, so the dot product needs no centring
            for j in range(p):
                out[i, c, j] = scale[i] * (a[i, c, j] - mean - unit[i, j] * along)
    return out


def _model(
    problem, arrays, geometry, rotations, solved, processing, jacobians=True, compare=None,
    lattice=False,
):  # fmt: skip
    """The model patterns (N, P) made by *processing* from the master
    pattern's *arrays*, and with *jacobians* their processed geometry
    (N, K, P; with *lattice* the c axis' stretch after them, K + 1) and
    rotation-and-PC (N, 6, P) derivative planes (else None, None), those
    passed through the linear filter *compare* if given (the patterns are
    not)."""
    n = len(problem.points)
    if not jacobians:
        sim = problem.simulate(geometry, rotations, arrays)
        return processing(sim.reshape(n, -1))[0], None, None
    s0, j_rot, j_pc, chain, j_lat = _intensity_chain(
        geometry, problem.points, rotations, arrays, solved, INTENSITY_STEPS, lattice
    )
    # The six columns processed (and filtered), the geometry's made of them
    # after: both are linear, and six are fewer than K + 3
    s0, planes = processing(s0, (j_rot, j_pc) if j_lat is None else (j_rot, j_pc, j_lat))
    if compare is not None:
        planes = compare(planes)
    six = planes[:, :6]
    geo = np.swapaxes(chain, 1, 2).astype(np.float32) @ six
    if j_lat is not None:
        geo = np.concatenate([geo, planes[:, 6:]], axis=1)
    return s0, geo, six


def _intensity_system(
    problem, arrays, geometry, rotations, solved, processing, jacobians=True, lattice=False,
    variances=True,
):  # fmt: skip
    """Residuals (N, P), geometry and rotation Jacobians with each
    pattern's gain and offset eliminated (with *lattice*, the c axis'
    stretch a column after the geometry's), and the pixel noise variances
    (N, P); the model made by *processing* from the master pattern's
    *arrays*. Without *jacobians*, only the residuals (the Jacobians
    None); without *variances*, None for them (the full field weighs by
    its first step's)."""
    n = len(problem.points)
    shape = tuple(problem.experimental.shape[1:])
    raw, e, ec = problem.compared_experimental
    # One crystal's patterns compared high-passed: they all share its
    # simulator's misfit, which a polycrystal's grains average (there the
    # high-pass cost more than it removed: 8-grain Ni maps of 96 px,
    # another simulator's data, PC errors 1.2-1.4e-4 -> 1.6-2.8e-4)
    compare = None if problem.crystal is None else functools.partial(_compared, shape=shape)
    model, geo, six = _model(
        problem, arrays, geometry, rotations, solved, processing, jacobians, compare, lattice
    )
    s0 = model if compare is None else compare(model)
    # Gain and offset of each pattern, then projected out of every column:
    # exactly their elimination (variable projection). The two basis
    # vectors, the constant and the centred model, are orthogonal: the
    # projection is a centring and one dot product per column
    sc = s0 - s0.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(sc, axis=1)
    unit = sc / norm[:, None]
    gain = (unit * ec).sum(axis=1) / norm
    # Model minus data, fitted gain and offset
    residual = _project_out(e[:, None], unit, -np.ones(n))[..., 0]
    jg = jr = None
    if jacobians:
        jg = _project_out(geo, unit, gain)
        jr = _project_out(six[:, :3], unit, gain)
    if not variances:
        return residual, jg, jr, None
    # Shot noise follows the intensities before the high-pass: the fitted
    # model's (the filter is linear, so the gain is the same)
    fitted = gain[:, None] * (model - model.mean(axis=1, keepdims=True))
    fitted += raw.mean(axis=1, keepdims=True)
    return residual, jg, jr, _pixel_variances(residual, fitted)


def _pixel_variances(residual: np.ndarray, model: np.ndarray) -> np.ndarray:
    """Noise variances (N, P) of the pixels, ``c0 + c1 * model`` fitted
    per pattern to the squared residuals: shot noise grows with the
    intensity, so bright bands are noisier than the background between
    them (measured at real-Ni noise: with one variance per pattern the
    errors were 1.3-1.6x the white-noise bound). Each pixel weighs at
    most 1 / :data:`MIN_PIXEL_VARIANCE` times its pattern's mean: at 0.1 one
    pattern's pcz score inflated the cluster-robust error twofold."""
    return _variances(
        np.ascontiguousarray(residual, dtype=np.float64),
        np.ascontiguousarray(model, dtype=np.float64),
        MIN_PIXEL_VARIANCE,
    )


@nb.njit(cache=True, nogil=True)
def _variances(residual, model, floor):
    # Three passes over each pattern's pixels (numpy's made eight, and
    # were a tenth of the full field's time)
    n, p = residual.shape
    out = np.empty((n, p))
    for i in range(n):
        mean = 0.0
        for j in range(p):
            mean += model[i, j]
        mean /= p
        mr2 = 0.0
        mm = 0.0
        r2 = 0.0
        for j in range(p):
            m = model[i, j] - mean
            e2 = residual[i, j] ** 2
            mr2 += m * e2
            mm += m * m
            r2 += e2
        r2 /= p
        slope = max(mr2 / mm, 0.0)
        # A variance model is no licence for a pixel to weigh without bound
        low = floor * r2
        for j in range(p):
            out[i, j] = max(r2 + slope * (model[i, j] - mean), low)
    return out


@dataclass(frozen=True)
class _System:
    """The full field's linear system at a geometry and orientations:
    residuals (model minus data), Jacobians with the nuisances eliminated,
    pixel weights, rotation offsets and the normal equations (*normal*)."""

    geometry: MapGeometry
    rotations: Rotation
    residual: np.ndarray
    jg: np.ndarray
    jr: np.ndarray
    weights: np.ndarray
    offsets: Any
    common: bool = False
    normal: JointSystem | None = None
    #: The geometry's prior (standard deviations, the lattice's stretch
    #: last) and its values against it, if the lattice is fitted
    geometry_prior: np.ndarray | None = None
    geometry_offsets: np.ndarray | None = None


def _hold(system: _System, held, start: MapGeometry, solved, split, cov):
    """The geometry, orientations and covariance with the *held*
    parameters put back to their values in *start*: the constrained
    least-squares step of the converged linear *system*, the orientations
    and a fitted lattice's stretch taking back what they had absorbed of
    the held parameters' moves (the stretch's step, standard error and the
    geometry's regression on it; None without one). No new simulation: a
    second Gauss-Newton pass from the DIC stage's state with them held
    reached the same PC within 1.1e-5 (an eighth of a standard error) on
    two processed Ni maps. The stretch stays free: held with the angles,
    a BaTiO3 crystal's pcz standard error fell from 8.4e-4 to 1.3e-4,
    2.1e-3 off."""
    idx = [i for i, nm in enumerate(solved) if nm in held]
    free = [i for i, nm in enumerate(solved) if nm not in held]
    cols = free + list(range(len(solved), system.jg.shape[-1]))
    back = (
        _solved_values(start, solved, split)[idx]
        - _solved_values(system.geometry, solved, split)[idx]
    )
    # The residual the linear model predicts once they are put back
    residual = system.residual + system.jg[..., idx] @ back
    # The free columns' normal equations cut from the last ones (their
    # orientation prior, the lattice's)
    gp, go = system.geometry_prior, system.geometry_offsets
    upd = system.normal.columns(cols, None if gp is None else gp[cols]).solve(
        residual, system.offsets, geometry_offsets=None if go is None else go[cols]
    )
    m = len(free)
    delta = {solved[i]: float(d) for i, d in zip(free, upd.delta)}
    delta.update({solved[i]: float(b) for i, b in zip(idx, back)})
    geometry = system.geometry.updated(_expand(delta, split))
    rotations = system.rotations * rotations_from_vectors(upd.rotations)
    out = cov.copy()
    out[np.ix_(free, free)] = upd.covariance[:m, :m]
    out[np.ix_(free, idx)] = out[np.ix_(idx, free)] = 0.0
    lattice = None
    if len(cols) > m:
        var = upd.covariance[m, m]
        slope = np.zeros(len(solved))
        slope[free] = upd.covariance[:m, m] / var if var > 0 else 0.0
        lattice = (float(upd.delta[m]), float(np.sqrt(max(var, 0.0))), slope)
    return geometry, rotations, out, lattice
