"""The Jacobian ``J = db/dp`` of the residual field (paper section 2.3).

Two ways to build it, with the same conventions (rows as ``b`` of
:mod:`~kikuchipy_geomdic.patterns.displacement`, columns in parameter order, pixels
per parameter unit):

- :func:`finite_difference_jacobian`, the paper's Eqs. 4-5: simulate and
  measure ``b`` at ``p +- delta_k e_k``.
- :func:`analytic_jacobian`: the simulated pattern moves by the forward
  displacement ``d`` of :func:`~kikuchipy_geomdic.geometry.projection.forward_map`,
  so ``b`` changes by ``-d``; ``d`` is evaluated at the measured feature
  positions and averaged as Eq. 2 averages (zero where an ROI had no
  vectors, divided by N). No simulation.

The joint solve (:func:`~kikuchipy_geomdic.calibration.solve.solve_joint`) needs the
same derivatives per pattern instead of averaged, and also with respect
to a small rotation of each pattern's crystal: :func:`pattern_jacobian`
returns both, from the same forward map.

Columns of parameters in :data:`~kikuchipy_geomdic.geometry.parameters.EQUIVALENT_PARAMETERS`
are derived from their equivalent, never measured twice: the
``sample_tilt`` column is exactly ``-1`` times the ``tilt`` column.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from kikuchipy_geomdic.geometry import EQUIVALENT_PARAMETERS, MapGeometry

__all__ = [
    "finite_difference_jacobian",
    "analytic_jacobian",
    "pattern_jacobian",
    "intensity_jacobian",
    "INTENSITY_STEPS",
    "parameter_derivatives",
    "lattice_derivative",
    "UNIQUE_AXIS_SYSTEMS",
]

#: Crystal systems with one unique axis (crystal z, orix's c): their
#: lattice may differ from a CIF's by a stretch along it, a change of c/a,
#: which moves every band. A cubic lattice's only freedom, its scale,
#: moves none.
UNIQUE_AXIS_SYSTEMS = ("tetragonal", "hexagonal", "trigonal")

#: Rotation step (radians) of the central difference of the rotation
#: columns: the forward map is exact, so only round-off limits it.
ROTATION_STEP = 1e-4


#: Steps of :func:`parameter_derivatives` in :func:`intensity_jacobian`
#: (PC fractions, degrees): the PC field and the detector matrix are
#: smooth in the parameters, so the differences are exact to round-off.
INTENSITY_STEPS = {
    "pcx": 1e-4,
    "pcy": 1e-4,
    "pcz": 1e-4,
    "tilt": 0.01,
    "azimuthal": 0.01,
    "sample_tilt": 0.01,
    "twist": 0.01,
}


def _assemble(names, steps, column, axis=1) -> np.ndarray:
    columns = {}
    for name in names:
        base, factor = EQUIVALENT_PARAMETERS.get(name, (name, 1.0))
        if base not in columns:
            columns[base] = column(base, steps.get(base, steps.get(name)))
        columns[name] = factor * columns[base]
    return np.stack([columns[n] for n in names], axis=axis)


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
    >>> from kikuchipy_geomdic.calibration.jacobian import finite_difference_jacobian
    >>> geo = MapGeometry((0.5, 0.3, 0.6), (60, 60), 70, 8, (10, 10), (3, 3))
    >>> b = lambda g: np.array([2 * g.pc[0], -g.tilt])
    >>> steps = {"pcx": 0.01, "tilt": 0.5}
    >>> finite_difference_jacobian(b, geo, ["pcx", "tilt"], steps).round(9).tolist()
    [[2.0, 0.0], [0.0, -1.0]]
    """

    def column(name, step):
        b_plus = residual(geometry.updated({name: step}))
        b_minus = residual(geometry.updated({name: -step}))
        return (b_plus - b_minus) / (2 * step)

    return _assemble(names, steps, column)


def pattern_jacobian(
    geometry: MapGeometry,
    points: np.ndarray,
    positions: np.ndarray,
    names: Sequence[str],
    steps: Mapping[str, float],
    rotations: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Return per-pattern Jacobians of the ROI displacements.

    For pattern ``i`` and ROI ``r``, the measured displacement
    ``u[i, r]`` (simulated to experimental) is modelled after a geometry
    change ``dp`` and a crystal rotation ``dw_i`` as
    ``u + J_geo dp + J_rot dw_i``; both Jacobians are minus the forward
    displacement of the simulated pattern, evaluated where each ROI's
    displacement was measured.

    Parameters
    ----------
    geometry
        Current geometry.
    points
        Map positions (N, 2) of the patterns.
    positions
        Feature positions (N, R, 2) ``(x, y)`` where each ROI's
        displacement was measured
        (:attr:`~kikuchipy_geomdic.patterns.displacement.DisplacementField.positions`).
    names
        Geometry parameters, one column each.
    steps
        ``{name: delta}`` of the central difference of the forward map.
    rotations
        Also return the rotation Jacobian.

    Returns
    -------
    j_geo
        (N, R, 2, K), pixels per parameter unit.
    j_rot
        (N, R, 2, 3), pixels per radian of a rotation ``g -> g * T`` of
        each crystal about the sample axes X, Y and Z (orix's right
        factor, see :func:`~kikuchipy_geomdic.geometry.projection.forward_map`), or
        None.

    Examples
    --------
    A rotation of the crystal about the detector normal turns the pattern
    about the PC:

    >>> import numpy as np
    >>> from kikuchipy_geomdic.geometry import MapGeometry
    >>> from kikuchipy_geomdic.calibration.jacobian import pattern_jacobian
    >>> geo = MapGeometry((0.5, 0.5, 0.6), (60, 60), 70, 8, (10, 10), (1, 1))
    >>> pos = np.array([[[29.5, 9.5]]])  # 20 px above the PC
    >>> jg, jr = pattern_jacobian(geo, [[0, 0]], pos, ["pcx"], {"pcx": 0.01})
    >>> jg[0, 0, :, 0].round(6).tolist()  # pcx moves the pattern along x
    [-60.0, 0.0]
    >>> jr.shape
    (1, 1, 2, 3)
    """
    x, y = positions[..., 0], positions[..., 1]
    n = positions.shape[0]

    def column(name, step):
        d_plus = geometry.displacement(geometry.updated({name: step}), points, x, y)
        d_minus = geometry.displacement(geometry.updated({name: -step}), points, x, y)
        return -np.nan_to_num((d_plus - d_minus) / (2 * step))

    j_geo = _assemble(names, steps, column, axis=-1)
    if not rotations:
        return j_geo, None
    h = ROTATION_STEP
    cols = []
    for k in range(3):
        mats = [np.broadcast_to(_axis_rotation(k, s * h), (n, 3, 3)) for s in (1, -1)]
        d_plus = geometry.displacement(geometry, points, x, y, mats[0])
        d_minus = geometry.displacement(geometry, points, x, y, mats[1])
        cols.append(-np.nan_to_num((d_plus - d_minus) / (2 * h)))
    return j_geo, np.stack(cols, axis=-1)


def analytic_jacobian(
    geometry: MapGeometry,
    points: np.ndarray,
    positions: np.ndarray,
    counts: np.ndarray,
    names: Sequence[str],
    steps: Mapping[str, float],
) -> np.ndarray:
    """Return the Jacobian of the average field from the forward map.

    The per-pattern Jacobians of :func:`pattern_jacobian` averaged as
    Eq. 2 averages the displacements: zero where an ROI had no vectors,
    divided by N.

    Parameters
    ----------
    geometry, points, positions, names, steps
        As in :func:`pattern_jacobian` (no simulation is involved, so
        small steps are fine).
    counts
        Vectors per pattern and ROI (N, R); ROIs with none contribute
        zero, as in Eq. 2.

    Returns
    -------
    jacobian
        (2R, K).
    """
    j_geo, _ = pattern_jacobian(geometry, points, positions, names, steps, rotations=False)
    has = (np.asarray(counts) > 0)[..., None, None]
    j = np.where(has, j_geo, 0.0).sum(axis=0) / positions.shape[0]
    return j.reshape(-1, j.shape[-1])


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    from orix.quaternion import Rotation

    return Rotation.from_axes_angles(np.eye(3)[axis], angle).to_matrix().reshape(3, 3)


def parameter_derivatives(
    geometry: MapGeometry, points: np.ndarray, name: str, step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return what a geometry parameter's change is made of, per unit.

    At a fixed PC, detector ``M -> M'`` shows what the crystal rotated by
    ``T = M'^T M`` (``g -> g * T``, sample frame) shows at ``M``; the rest
    of a parameter's effect is its change of the PC field across the map
    (all of it for a PC parameter, whose rotation is zero).

    Parameters
    ----------
    geometry
        Current geometry.
    points
        Map positions (N, 2).
    name
        A parameter of :data:`~kikuchipy_geomdic.geometry.parameters.DEFAULT_STEPS`.
    step
        Central-difference step (its unit: PC fraction or degrees).

    Returns
    -------
    rotation
        Rotation vector (3,) of ``T`` (radians per unit).
    pc
        PC changes (N, 3) per unit.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.geometry import MapGeometry
    >>> from kikuchipy_geomdic.calibration.jacobian import parameter_derivatives
    >>> geo = MapGeometry((0.5, 0.3, 0.6), (60, 60), 70, 8, (10, 10), (3, 3))
    >>> rot, pc = parameter_derivatives(geo, [[0, 0], [2, 2]], "azimuthal", 0.01)
    >>> bool(np.isclose(np.linalg.norm(rot), np.deg2rad(1), rtol=1e-3)), pc.shape
    (True, (2, 3))
    """
    from kikuchipy_geomdic.geometry import sample_to_detector_matrix

    plus, minus = geometry.updated({name: step}), geometry.updated({name: -step})
    m0 = sample_to_detector_matrix(*geometry.angles)
    vec = []
    for g in (plus, minus):
        t = sample_to_detector_matrix(*g.angles).T @ m0
        # The rotation vector of a small rotation matrix from its skew
        # part; orix's from_matrix rounds rotations below ~1e-3 deg to none
        vec.append(np.array([t[2, 1] - t[1, 2], t[0, 2] - t[2, 0], t[1, 0] - t[0, 1]]) / 2)
    pts = np.asarray(points)
    return (vec[0] - vec[1]) / (2 * step), (plus.pc_at(pts) - minus.pc_at(pts)) / (2 * step)


def intensity_jacobian(
    geometry: MapGeometry,
    points: np.ndarray,
    rotations,
    arrays,
    names: Sequence[str],
    steps: Mapping[str, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return per-pattern Jacobians of the simulated intensities.

    The full-field counterpart of :func:`pattern_jacobian`: derivatives of
    every pixel of each simulated pattern instead of ROI displacements,
    all analytic and from one pass of the projection
    (:func:`~kikuchipy_geomdic.indexing.orientation.project_derivatives`): the
    rotation columns and the pattern's own PC columns; a geometry
    parameter's column is the crystal rotation it amounts to plus its
    change of the PC field across the map (:func:`parameter_derivatives`).
    Measured directly, what is left of an angle's column once the
    orientations are free drowned in finite-difference errors at the
    kinks of the master pattern's interpolation; and central differences
    of the PC reduced against analytic rotation columns moved the bound of
    pcx by 9 % between steps of 1e-4 and 4e-4. Analytic throughout, every
    column is the exact derivative of the same model.

    Parameters
    ----------
    geometry, points
        As in :func:`parameter_derivatives`.
    rotations
        Orientations (N,) (orix rotations or quaternions (N, 4)).
    arrays
        :func:`~kikuchipy_geomdic.indexing.orientation.master_pattern_arrays`.
    names
        Geometry parameters, one column each.
    steps
        ``{name: delta}`` of :func:`parameter_derivatives` (its
        differences are of smooth functions; any small step will do).

    Returns
    -------
    simulated
        Patterns (N, P) at the current geometry, P pixels, float64.
    j_geo
        (N, P, K), intensity per parameter unit.
    j_rot
        (N, P, 3), intensity per radian of ``g -> g * T``.

    Examples
    --------
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation import master_patterns
    >>> from kikuchipy_geomdic.geometry import MapGeometry
    >>> from kikuchipy_geomdic.calibration.jacobian import intensity_jacobian
    >>> from kikuchipy_geomdic.indexing.orientation import master_pattern_arrays
    >>> geo = MapGeometry((0.5, 0.3, 0.6), (40, 40), 70, 8, (10, 10), (2, 2))
    >>> arrays = master_pattern_arrays(master_patterns.master_pattern("Si"), 20)
    >>> s, jg, jr = intensity_jacobian(
    ...     geo, [[0, 0], [1, 1]], Rotation.random(2), arrays, ["pcx", "tilt"],
    ...     {"pcx": 1e-4, "tilt": 0.01})
    >>> s.shape, jg.shape, jr.shape
    ((2, 1600), (2, 1600, 2), (2, 1600, 3))
    """
    simulated, j_rot, j_pc, chain, _ = _intensity_chain(
        geometry, points, rotations, arrays, names, steps
    )
    # (N, P, 6) @ (N, 6, K), all columns at once: column by column and
    # stacked on the last axis, the strided copy took longer than the
    # products
    j_geo = j_rot @ chain[:, :3] + j_pc @ chain[:, 3:]
    return simulated, j_geo, j_rot


def lattice_derivative(
    j_rot: np.ndarray, directions: np.ndarray, quaternions: np.ndarray
) -> np.ndarray:
    """Return the derivative of simulated patterns by a stretch of the
    crystal's c axis (its z axis), the relative change ``e`` of c/a.

    A lattice direction ``r`` of the crystal is ``F r`` in a crystal
    stretched by ``F = I + e c c^T``, so the pattern shows at the crystal
    direction ``u`` what the master pattern holds at ``F^-1 u``: the
    intensity changes by ``grad . t`` with ``t = -(u . c) (c - (u . c) u)``,
    the tangential move. The tangential gradient is ``j_rot x u`` (the
    rotation derivative is ``u x grad``), all in the sample frame; being
    normal to ``u``, its product with ``t`` is ``-(u . c) j_rot . (u x c)``. First
    order in ``e``, as HR-EBSD's shifts are; the bands' widths, which
    change with the d-spacings by as little, are not modelled.

    Parameters
    ----------
    j_rot
        (N, P, 3) rotation derivatives of
        :func:`~kikuchipy_geomdic.indexing.orientation.project_derivatives`.
    directions
        (N, P, 3) unit directions of the pixels, sample frame.
    quaternions
        (N, 4) orientations (sample to crystal, orix's).

    Returns
    -------
    j_lattice
        (N, P): intensity per unit ``e``.

    Examples
    --------
    Against a finite difference of a master pattern of a stretched lattice
    is what the tests do; here the shapes:

    >>> import numpy as np
    >>> lattice_derivative(np.zeros((2, 5, 3)), np.ones((2, 5, 3)) / 3**0.5,
    ...                    np.tile([1.0, 0, 0, 0], (2, 1))).shape
    (2, 5)
    """
    from orix.quaternion import Rotation

    # The c axis in the sample frame: the crystal's z under the inverse
    c = (~Rotation(np.asarray(quaternions).reshape(-1, 4))).to_matrix()[:, :, 2]
    u = np.asarray(directions, dtype=np.float64)
    j = np.asarray(j_rot, dtype=np.float64)
    c0, c1, c2 = (c[:, None, i] for i in range(3))
    u0, u1, u2 = u[..., 0], u[..., 1], u[..., 2]
    # Component by component: np.cross and einsum copied the stacks
    along = j[..., 0] * (u1 * c2 - u2 * c1)
    along += j[..., 1] * (u2 * c0 - u0 * c2)
    along += j[..., 2] * (u0 * c1 - u1 * c0)
    return -(u0 * c0 + u1 * c1 + u2 * c2) * along


def _directions(pcs: np.ndarray, shape: tuple[int, int], om: np.ndarray) -> np.ndarray:
    """Unit directions (N, P, 3), sample frame, of the pixels of detectors
    with Bruker PCs *pcs* (N, 3), *shape* and detector matrix *om*."""
    from kikuchipy_geomdic.indexing._lambert import _direction_cosines

    om = np.ascontiguousarray(om, dtype=np.float64)
    return np.stack(
        [_direction_cosines(np.asarray(pc, np.float64), shape[0], shape[1], om) for pc in pcs]
    )


def _intensity_chain(geometry, points, rotations, arrays, names, steps, lattice=False):
    """The parts of :func:`intensity_jacobian`: the simulated patterns
    (N, P), their derivatives by rotation (N, P, 3) and by the pattern's
    own PC (N, P, 3), and the chain matrices (N, 6, K) that make the
    geometry's columns of them, ``[j_rot, j_pc] @ chain``. The full field
    processes the six columns and applies the chain after: the processing
    is linear in the columns, and six are fewer than K + 3. With
    *lattice*, also the derivative by the c axis' stretch (N, P, 1) of
    :func:`lattice_derivative` (else None)."""
    from orix.quaternion import Rotation

    from kikuchipy_geomdic.indexing.orientation import detector_matrix, project_derivatives

    pts = np.asarray(points)
    q = np.asarray(
        rotations.data if isinstance(rotations, Rotation) else rotations, dtype=np.float64
    ).reshape(-1, 4)
    det = geometry.detector(pts)
    pcs = det.pc.reshape(-1, 3).astype(np.float64)
    if pcs.shape[0] == 1:
        pcs = np.repeat(pcs, len(q), axis=0)
    om = detector_matrix(det)
    simulated, j_rot, j_pc = project_derivatives(q, pcs, om, arrays, det.shape)

    def column(name, step):
        rot, dpc = parameter_derivatives(geometry, pts, name, step)
        return np.concatenate(np.broadcast_arrays(rot, dpc), axis=-1)

    chain = _assemble(names, steps, column, axis=-1)
    if not lattice:
        return simulated, j_rot, j_pc, chain, None
    j_lat = lattice_derivative(j_rot, _directions(pcs, det.shape, om), q)
    return simulated, j_rot, j_pc, chain, j_lat[..., None]
