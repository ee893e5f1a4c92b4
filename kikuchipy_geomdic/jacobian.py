"""The Jacobian ``J = db/dp`` of the residual field (paper section 2.3).

Two ways to build it, with the same conventions (rows as ``b`` of
:mod:`~kikuchipy_geomdic.displacement`, columns in parameter order, pixels
per parameter unit):

- :func:`finite_difference_jacobian`, the paper's Eqs. 4-5: simulate and
  measure ``b`` at ``p +- delta_k e_k``.
- :func:`analytic_jacobian`: the simulated pattern moves by the forward
  displacement ``d`` of :func:`~kikuchipy_geomdic.geometry.forward_map`,
  so ``b`` changes by ``-d``; ``d`` is evaluated at the measured feature
  positions and averaged as Eq. 2 averages (zero where an ROI had no
  vectors, divided by N). No simulation.

Columns of parameters in :data:`~kikuchipy_geomdic.geometry.EQUIVALENT_PARAMETERS`
are derived from their equivalent, never measured twice: the
``sample_tilt`` column is exactly ``-1`` times the ``tilt`` column.
"""

from __future__ import annotations

from typing import Callable, Mapping, Sequence

import numpy as np

from kikuchipy_geomdic.geometry import EQUIVALENT_PARAMETERS, MapGeometry

__all__ = ["finite_difference_jacobian", "analytic_jacobian"]


def _assemble(names, steps, column) -> np.ndarray:
    columns = {}
    for name in names:
        base, factor = EQUIVALENT_PARAMETERS.get(name, (name, 1.0))
        if base not in columns:
            columns[base] = column(base, steps.get(base, steps.get(name)))
        columns[name] = factor * columns[base]
    return np.stack([columns[n] for n in names], axis=1)


def finite_difference_jacobian(
    residual: Callable[[MapGeometry], np.ndarray],
    geometry: MapGeometry,
    names: Sequence[str],
    steps: Mapping[str, float],
) -> np.ndarray:
    """Return the central-difference Jacobian of Eqs. 4-5.

    Parameters
    ----------
    residual
        Function returning ``b`` (2R,) measured at a geometry (with the
        orientations and patterns held fixed).
    geometry
        Current geometry ``p_0``.
    names
        Parameters, one column each.
    steps
        ``{name: delta}``.

    Returns
    -------
    jacobian
        (2R, K).

    Examples
    --------
    A linear residual gives its matrix back:

    >>> import numpy as np
    >>> from kikuchipy_geomdic.geometry import MapGeometry
    >>> from kikuchipy_geomdic.jacobian import finite_difference_jacobian
    >>> geo = MapGeometry((0.5, 0.3, 0.6), (60, 60), 70, 8, (10, 10), (3, 3))
    >>> b = lambda g: np.array([2 * g.pc[0], -g.tilt])
    >>> finite_difference_jacobian(b, geo, ["pcx", "tilt"], {"pcx": 0.01, "tilt": 0.5}).round(9).tolist()
    [[2.0, 0.0], [0.0, -1.0]]
    """

    def column(name, step):
        b_plus = residual(geometry.updated({name: step}))
        b_minus = residual(geometry.updated({name: -step}))
        return (b_plus - b_minus) / (2 * step)

    return _assemble(names, steps, column)


def analytic_jacobian(
    geometry: MapGeometry,
    points: np.ndarray,
    positions: np.ndarray,
    counts: np.ndarray,
    names: Sequence[str],
    steps: Mapping[str, float],
) -> np.ndarray:
    """Return the Jacobian from the forward displacement map.

    Parameters
    ----------
    geometry
        Current geometry.
    points
        Map positions (N, 2) of the patterns.
    positions
        Feature positions (N, R, 2) ``(x, y)`` where each ROI's
        displacement was measured
        (:attr:`~kikuchipy_geomdic.displacement.DisplacementField.positions`).
    counts
        Vectors per pattern and ROI (N, R); ROIs with none contribute
        zero, as in Eq. 2.
    names
        Parameters, one column each.
    steps
        ``{name: delta}`` of the central difference of the forward map
        (no simulation is involved, so small steps are fine).

    Returns
    -------
    jacobian
        (2R, K).
    """
    x, y = positions[..., 0], positions[..., 1]
    has = (np.asarray(counts) > 0)[..., None]
    n = positions.shape[0]

    def column(name, step):
        d_plus = geometry.displacement(geometry.updated({name: step}), points, x, y)
        d_minus = geometry.displacement(geometry.updated({name: -step}), points, x, y)
        d = np.where(has, np.nan_to_num((d_plus - d_minus) / (2 * step)), 0.0)
        return -(d.sum(axis=0) / n).ravel()

    return _assemble(names, steps, column)
