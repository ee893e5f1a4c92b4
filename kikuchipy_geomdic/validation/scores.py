"""How a calibration is scored against the truth: displacements and errors.

Displacements
-------------
The paper's x axis is the mean displacement magnitude between the
starting and the true pattern sets. Two versions are reported, both from
the geometry model
(:meth:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry.displacement`), so free
of DIC tracking errors and defined also where DIC would no longer find
the features: :func:`mean_displacement` averages the model field over
every pixel of every calibration pattern per ROI, then takes the mean
magnitude over ROIs divided by the detector width;
:func:`eq2_displacement` samples it where DIC finds vectors and averages
as the paper's Eq. 2 does (an ROI without vectors in a pattern adds
zero), which is the paper's measure and comes out smaller. The
DIC-measured values of the refinement are kept beside them.

Tilt and sample tilt
--------------------
In kikuchipy's projection only ``tilt - sample_tilt`` is observable (see
:mod:`~kikuchipy_geomdic.geometry`); the refinement splits a change of it
equally between the two. Their individual errors are therefore reported
but the meaningful one is ``err_tilt_difference``, the error of
``tilt - sample_tilt``.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence

import numpy as np
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration.solve import coupling_matrix
from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, DEFAULT_STEPS, MapGeometry
from kikuchipy_geomdic.patterns.displacement import measure_displacements
from kikuchipy_geomdic.patterns.roi import roi_index
from kikuchipy_geomdic.patterns.simulation import simulate_patterns

__all__ = ["mean_displacement", "eq2_displacement", "sensitivities"]

_PC = ("pcx", "pcy", "pcz")


def _all_points(navigation_shape: tuple[int, int]) -> np.ndarray:
    """Every (row, col) point of a map, row-major."""
    return np.stack([a.ravel() for a in np.indices(navigation_shape)], axis=1)


def _pixel_grid(shape: tuple[int, int], max_side: int = 60):
    step = max(1, int(np.ceil(max(shape) / max_side)))
    y, x = np.mgrid[0 : shape[0] : step, 0 : shape[1] : step]
    return x.ravel().astype(float), y.ravel().astype(float)


def _average_field(
    geometry_a: MapGeometry, geometry_b: MapGeometry, points: np.ndarray, rois
) -> np.ndarray:
    """ROI-averaged model displacement (R, 2) from A to B, over *points*."""
    x, y = _pixel_grid(geometry_a.shape)
    uv = geometry_a.displacement(geometry_b, points, x, y)  # (n, m, 2)
    idx = roi_index(x, y, geometry_a.shape, rois)
    n_rois = rois[0] * rois[1]
    out = np.zeros((n_rois, 2))
    valid = np.isfinite(uv).all(axis=-1)  # (n, m)
    for c in range(2):
        vals = np.where(valid, uv[..., c], 0.0)
        s = np.zeros(n_rois)
        cnt = np.zeros(n_rois)
        np.add.at(s, idx, vals.sum(axis=0))
        np.add.at(cnt, idx, valid.sum(axis=0))
        out[:, c] = s / np.maximum(cnt, 1)
    return out


def mean_displacement(
    geometry_a: MapGeometry,
    geometry_b: MapGeometry,
    points: np.ndarray | None = None,
    rois: tuple[int, int] = (8, 8),
) -> float:
    """Return the paper's mean displacement magnitude between geometries.

    The forward displacement from geometry A to B is evaluated at every
    pixel of the pattern at every calibration point (every fourth pixel
    or so for patterns larger than 60 px), averaged per ROI and over the
    points (Eq. 2), and the mean magnitude over ROIs is divided by the
    detector width.

    Parameters
    ----------
    geometry_a, geometry_b
        :class:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry` of one map and
        detector shape.
    points
        Calibration points (N, 2) (row, column); default the whole map.
    rois
        ROI grid (rows, columns).

    Returns
    -------
    displacement
        Fraction of the detector width.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.validation.scores import mean_displacement
    >>> geo = synthetic.default_geometry((5, 5), (60, 60))
    >>> d = mean_displacement(geo, geo.updated({"pcx": 0.02}))
    >>> round(d, 4)  # pcx moves the whole pattern by 2 % of its width
    0.02
    """
    if points is None:
        points = _all_points(geometry_a.navigation_shape)
    f = _average_field(geometry_a, geometry_b, np.asarray(points), tuple(rois))
    return float(np.linalg.norm(f, axis=1).mean() / geometry_a.shape[1])


def eq2_displacement(
    master_pattern: EBSDMasterPattern,
    rotations: Rotation,
    geometry_a: MapGeometry,
    geometry_b: MapGeometry,
    points: np.ndarray,
    energy: float = 20.0,
    rois: tuple[int, int] = (8, 8),
    seed: int = 0,
    **dic_kwargs,
) -> tuple[float, float]:
    r"""Return the mean displacement as the paper measured it (Eq. 2).

    Patterns are simulated at the calibration points with *rotations*
    under geometry A (the paper's :math:`\mathbf{A}^0`) and B (the
    "experimental" :math:`\mathbf{B}`), and DIC is run between them. The
    model displacement from A to B is then evaluated where DIC measured
    (the vectors' positions) and averaged as Eq. 2 averages: an ROI without
    vectors in a pattern adds zero and the sum is divided by N. This is
    what the paper's displacement axis is, without the tracking errors that
    make DIC fail at large displacements; it is smaller than
    :func:`mean_displacement` because of the zeros.

    Parameters
    ----------
    master_pattern
        Lambert master pattern.
    rotations
        Orientations at *points* (N,).
    geometry_a, geometry_b
        Starting and true geometry.
    points
        Calibration points (N, 2).
    energy
        Beam energy in kV.
    rois
        ROI grid.
    seed
        Seed of the DIC.
    **dic_kwargs
        Further options of
        :func:`~kikuchipy_geomdic.patterns.displacement.measure_displacements`.

    Returns
    -------
    model, measured
        Mean magnitude over ROIs with vectors, fraction of the detector
        width: the model field at the measured positions, and the field
        DIC measured.
    """
    points = np.asarray(points)
    a = simulate_patterns(master_pattern, rotations, geometry_a.detector(points), energy)
    b = simulate_patterns(master_pattern, rotations, geometry_b.detector(points), energy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = measure_displacements(a, b, rois=tuple(rois), seed=seed, **dic_kwargs)
    pos = f.positions  # (N, R, 2)
    uv = geometry_a.displacement(geometry_b, points, pos[..., 0], pos[..., 1])
    uv = np.where((f.counts > 0)[..., None] & np.isfinite(uv), uv, 0.0)
    mean = uv.sum(axis=0) / len(points)
    has = f.total_counts > 0
    if not has.any():
        return float("nan"), float("nan")
    model = float(np.linalg.norm(mean[has], axis=1).mean() / geometry_a.shape[1])
    return model, f.mean_displacement


def sensitivities(
    geometry: MapGeometry,
    points: np.ndarray | None = None,
    parameters: Sequence[str] = DEFAULT_PARAMETERS,
    steps: Mapping[str, float] | None = None,
    rois: tuple[int, int] = (8, 8),
) -> tuple[dict[str, float], np.ndarray]:
    """Return the normalisation of the paper's Eq. 12 and the coupling.

    For each parameter ``k`` the model displacement field between
    ``p - delta_k`` and ``p + delta_k`` gives the mean magnitude
    ``d_N`` (fraction of the detector width); ``d_N / (2 delta_k)`` is the
    mean displacement per unit of the parameter, and a parameter error
    ``eps_k`` has the normalised error ``eps_k d_N / (2 delta_k)``
    (Eq. 12): the error expressed as a displacement.

    Parameters
    ----------
    geometry
        Geometry at which the sensitivities are taken.
    points
        Calibration points (N, 2); default the whole map.
    parameters
        Parameter names.
    steps
        ``delta_k``; default :data:`~kikuchipy_geomdic.geometry.parameters.DEFAULT_STEPS`.
    rois
        ROI grid.

    Returns
    -------
    scale
        ``{name: d_N / (2 delta_k)}`` (fraction of the width per unit).
    coupling
        Coupling matrix (K, K) of the ROI-averaged sensitivity fields
        (the paper's Fig. 3C).

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.validation.scores import sensitivities
    >>> geo = synthetic.default_geometry((5, 5), (60, 60))
    >>> scale, coupling = sensitivities(geo)
    >>> round(scale["pcx"], 3)  # a pcx change moves everything by itself
    1.0
    >>> round(float(coupling[3, 5]), 3)  # tilt and sample_tilt: opposite
    -1.0
    """
    if points is None:
        points = _all_points(geometry.navigation_shape)
    st = dict(DEFAULT_STEPS)
    st.update(steps or {})
    scale, cols_ = {}, []
    for k in parameters:
        d = st[k]
        f = _average_field(
            geometry.updated({k: -d}), geometry.updated({k: d}), np.asarray(points), rois
        )
        scale[k] = float(np.linalg.norm(f, axis=1).mean() / geometry.shape[1] / (2 * d))
        cols_.append(f.ravel() / (2 * d))
    return scale, coupling_matrix(np.stack(cols_, axis=1))


def _misorientation(a: Rotation, b: Rotation) -> np.ndarray:
    """Rotation angle (deg) between rotations, no crystal symmetry: the
    refined orientations start at (or near) the truth and move
    continuously, so a symmetry-equivalent jump would itself be a
    failure."""
    return np.rad2deg((a * ~b).angle)


def _disorientation_from_mean(rot: Rotation) -> float:
    """The paper's single-crystal metric: mean angle to the mean."""
    return float(_misorientation(rot, rot.mean()).mean())


def _geometry_errors(refined: MapGeometry, truth: MapGeometry) -> dict[str, float]:
    centre = np.array([truth.reference])
    pc_r = refined.pc_at(centre)[0]
    pc_t = truth.pc_at(centre)[0]
    err = {k: float(pc_r[i] - pc_t[i]) for i, k in enumerate(_PC)}
    for k in ("tilt", "azimuthal", "sample_tilt"):
        err[k] = float(getattr(refined, k) - getattr(truth, k))
    err["tilt_difference"] = err["tilt"] - err["sample_tilt"]
    return err
