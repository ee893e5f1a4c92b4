"""The refinement loop: global geometry from averaged displacement fields.

This is the paper's algorithm (sections 2.2-2.4, Fig. 4): simulate the
calibration points at the current geometry, measure the average
displacement field ``b`` (:mod:`~kikuchipy_geomdic.displacement`), build
the Jacobian, solve the weighted, column-normalised, damped least squares
(:mod:`~kikuchipy_geomdic.solve`), update the geometry and its PC field
(:mod:`~kikuchipy_geomdic.geometry`), refine the orientations with
kikuchipy, and accept or reject the step.

Where it departs from the paper, and why
----------------------------------------
- *Anchored orientations.* A rotation common to all orientations (right
  factor, sample frame) is exactly a change of the detector angles in
  kikuchipy's projection. Orientation refinement at a wrong geometry
  therefore absorbs the angle error into the orientations, and the next
  displacement field no longer shows it. The orientations used to
  simulate are the refined ones with their mean rotation relative to the
  starting orientations removed: each may move, their mean may not. The
  angles are thus measured against the starting orientations, assumed
  free of a common bias (true of the paper's perturbation study, and of
  any start whose errors are random).
- *Acceptance.* NCC after orientation refinement barely tells a right
  geometry from one whose error was absorbed (field notes), so a step is
  accepted when the mean displacement magnitude falls (measured first,
  cheaply, with the current orientations) and then the NCC after
  orientation refinement does not drop by more than ``ncc_tolerance``;
  the loop ends when the NCC gain is below ``ncc_tolerance`` *and* the
  displacement no longer falls by 10 %. A rejected step is retried with
  ten times the damping, twice, before the loop ends; steps rejected on
  their displacement cost no orientation refinement.
- *Jacobian.* ``"analytic"`` evaluates the forward displacement map at the
  measured feature positions instead of simulating at ``p +- delta``.
- *Degeneracy.* The ``sample_tilt`` column is ``-1`` times the ``tilt``
  column, exactly, and is not simulated; the solve handles the resulting
  null direction by a minimum-norm split (:mod:`~kikuchipy_geomdic.solve`).
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic import displacement as dsp
from kikuchipy_geomdic.geometry import (
    DEFAULT_PARAMETERS,
    DEFAULT_STEPS,
    EQUIVALENT_PARAMETERS,
    MapGeometry,
    check_parameters,
    copy_detector,
)
from kikuchipy_geomdic.jacobian import analytic_jacobian, finite_difference_jacobian
from kikuchipy_geomdic.reindex import usable_points
from kikuchipy_geomdic.simulation import check_master_pattern, simulate_patterns
from kikuchipy_geomdic.solve import coupling_matrix, solve_update

__all__ = ["GeometryRefinementResult", "refine_geometry_dic", "calibration_points"]

_JACOBIANS = ("finite-difference", "analytic")


# --------------------------------------------------------------------- #
# The result
# --------------------------------------------------------------------- #


@dataclass(frozen=True)
class GeometryRefinementResult:
    """What :func:`refine_geometry_dic` returns.

    Attributes
    ----------
    detector
        New :class:`~kikuchipy.detectors.EBSDDetector` for the whole map:
        refined angles and the PC field following from them, navigation
        shape equal to the signal's.
    geometry
        The refined :class:`~kikuchipy_geomdic.geometry.MapGeometry`.
    start_geometry
        The starting geometry.
    xmap
        :class:`~orix.crystal_map.CrystalMap` of the calibration points
        (1D, in the order of *points*) with orientations refined at the
        refined geometry and properties ``scores`` (NCC), ``row``, ``col``
        and ``pseudo_symmetry_index``: which of
        ``refine_kwargs["pseudo_symmetry_ops"]`` (1-based; 0 for none)
        relates the input orientation to the refined one.
    points
        Calibration points (N, 2) as (row, column).
    parameter_names
        The refined parameters, in canonical order.
    parameters
        ``{name: refined value}`` for the refined parameters.
    history
        One dict per trial step: ``parameters`` (values after the step),
        ``ncc_before``, ``ncc_after`` (mean NCC after orientation
        refinement, on the binned patterns of the loop for patterns of
        120 px or more; NaN for a step rejected on its displacement alone),
        ``displacement_before``, ``displacement_after`` (mean displacement
        magnitude as a fraction of the detector width, both measured with
        the orientations of the state the step starts from), ``damping``
        and ``accepted``.
    jacobian
        Jacobian (2R, K) at the last accepted geometry, pixels per
        parameter unit, columns in *parameter_names* order.
    coupling
        Normalised coupling matrix (K, K), the paper's Fig. 3C.
    singular_values
        Singular values of the weighted, column-normalised Jacobian.
    degenerate
        Parameter combinations the data cannot constrain, as
        ``{name: coefficient}`` dicts (e.g. tilt and sample_tilt).
    field_before, field_after
        :class:`~kikuchipy_geomdic.displacement.DisplacementField` at the
        start and at the refined geometry.
    converged
        Whether the loop ended by its tolerances (NCC gain below
        ``ncc_tolerance`` and the displacement no longer falling, or no
        step able to lower it further) rather than by *max_iterations*
        or by rejections before the NCC had settled.
    """

    detector: EBSDDetector
    geometry: MapGeometry
    start_geometry: MapGeometry
    xmap: CrystalMap
    points: np.ndarray
    parameter_names: tuple[str, ...]
    parameters: dict[str, float]
    history: list[dict[str, Any]]
    jacobian: np.ndarray
    coupling: np.ndarray
    singular_values: np.ndarray
    degenerate: list[dict[str, float]]
    field_before: dsp.DisplacementField
    field_after: dsp.DisplacementField
    converged: bool
    steps: dict[str, float] = field(default_factory=dict)

    def __repr__(self) -> str:
        lines = [f"{type(self).__name__} ({len(self.points)} points, "
                 f"{len(self.history)} iterations, converged={self.converged})"]
        start = self.start_geometry.as_dict()
        for name in self.parameter_names:
            lines.append(
                f"  {name:<12} {start[name]:>10.5f} -> {self.parameters[name]:>10.5f}"
            )
        return "\n".join(lines)

    def plot_displacement(self, **kwargs):
        """Plot the average displacement field before and after (quiver).

        See :func:`kikuchipy_geomdic.plotting.plot_displacement_fields`.
        """
        from kikuchipy_geomdic import plotting

        return plotting.plot_displacement_fields(
            [self.field_before, self.field_after], ["before", "after"], **kwargs
        )

    def plot_sensitivity(self, **kwargs):
        """Plot each parameter's sensitivity field (a Jacobian column).

        See :func:`kikuchipy_geomdic.plotting.plot_sensitivity`.
        """
        from kikuchipy_geomdic import plotting

        return plotting.plot_sensitivity(
            self.jacobian, self.parameter_names, self.field_after, self.steps, **kwargs
        )

    def plot_coupling(self, **kwargs):
        """Plot the coupling matrix. See :func:`kikuchipy_geomdic.plotting.plot_coupling`."""
        from kikuchipy_geomdic import plotting

        return plotting.plot_coupling(self.coupling, self.parameter_names, **kwargs)

    def plot_convergence(self, **kwargs):
        """Plot NCC and displacement per iteration.

        See :func:`kikuchipy_geomdic.plotting.plot_convergence`.
        """
        from kikuchipy_geomdic import plotting

        return plotting.plot_convergence(self.history, **kwargs)


# --------------------------------------------------------------------- #
# Input checks and calibration points
# --------------------------------------------------------------------- #


def calibration_points(
    navigation_shape: tuple[int, int], n: int, usable: np.ndarray | None = None
) -> np.ndarray:
    """Return about *n* map points spread evenly over the map.

    Parameters
    ----------
    navigation_shape
        Map shape (rows, columns).
    n
        Number of points wanted.
    usable
        Boolean mask of the map (rows, columns); unusable points
        (non-indexed, NaN patterns) are replaced by the nearest usable
        point not already chosen.

    Returns
    -------
    points
        Integer array (m, 2) of (row, column), ``m <= n``, row-major.

    Examples
    --------
    >>> from kikuchipy_geomdic.refinement import calibration_points
    >>> calibration_points((10, 20), 8).tolist()
    [[0, 0], [0, 6], [0, 13], [0, 19], [9, 0], [9, 6], [9, 13], [9, 19]]
    """
    ny, nx = navigation_shape
    if usable is None:
        usable = np.ones((ny, nx), dtype=bool)
    n = int(min(n, usable.sum()))
    if n <= 0:
        return np.zeros((0, 2), dtype=int)
    # A grid with the map's aspect ratio and about n nodes
    nr = int(np.clip(round(np.sqrt(n * ny / nx)), 1, ny))
    nc = int(np.clip(int(np.ceil(n / nr)), 1, nx))
    while nr * nc < n:
        nr, nc = min(nr + 1, ny), min(nc + (nr >= ny), nx)
    rows = np.round(np.linspace(0, ny - 1, nr)).astype(int)
    cols = np.round(np.linspace(0, nx - 1, nc)).astype(int)
    grid = np.stack(np.meshgrid(rows, cols, indexing="ij"), -1).reshape(-1, 2)
    # Thin to n nodes evenly along the row-major order
    grid = grid[np.round(np.linspace(0, len(grid) - 1, n)).astype(int)]
    free = usable.copy()
    out = []
    for r, c in grid:
        if not free[r, c]:
            cand = np.argwhere(free)
            if len(cand) == 0:
                break
            r, c = cand[np.argmin(np.hypot(cand[:, 0] - r, cand[:, 1] - c))]
        free[r, c] = False
        out.append((r, c))
    return np.array(sorted(out), dtype=int).reshape(-1, 2)


def _navigation_shape(signal: EBSD) -> tuple[int, int]:
    nav = signal.axes_manager.navigation_shape[::-1]
    if len(nav) == 1:
        return (1, nav[0])
    if len(nav) != 2:
        raise ValueError(
            f"The signal must have a 1D or 2D navigation shape, not {nav}"
        )
    return tuple(nav)


def _step_sizes(signal: EBSD) -> tuple[float, float]:
    axes = signal.axes_manager.navigation_axes
    if len(axes) == 2:
        dx, dy = axes[0].scale, axes[1].scale
    else:
        dx = axes[0].scale
        dy = dx
    return float(dy), float(dx)


def _check_inputs(signal, xmap, detector, master_pattern, phase, nav):
    if not isinstance(signal, EBSD):
        raise TypeError(f"signal must be a kikuchipy EBSD signal, not {type(signal).__name__}")
    if not isinstance(xmap, CrystalMap):
        raise TypeError(f"xmap must be an orix CrystalMap, not {type(xmap).__name__}")
    if not isinstance(detector, EBSDDetector):
        raise TypeError(f"detector must be a kikuchipy EBSDDetector, not {type(detector).__name__}")
    check_master_pattern(master_pattern)
    xshape = xmap.shape if len(xmap.shape) == 2 else (1,) + tuple(xmap.shape)
    if tuple(xshape) != nav or xmap.size != nav[0] * nav[1]:
        raise ValueError(
            f"xmap shape {xmap.shape} (with {xmap.size} points) does not match the "
            f"signal's navigation shape {nav}"
        )
    if tuple(detector.shape) != tuple(signal.axes_manager.signal_shape[::-1]):
        raise ValueError(
            f"detector shape {detector.shape} differs from the pattern shape "
            f"{signal.axes_manager.signal_shape[::-1]}"
        )
    n_pc = detector.pc.reshape(-1, 3).shape[0]
    if n_pc not in (1, nav[0] * nav[1]):
        raise ValueError(
            f"The detector has {n_pc} PCs, which fits neither one PC nor the "
            f"signal's {nav[0] * nav[1]} map points"
        )
    ids = [i for i in xmap.phases_in_data.ids if i >= 0]
    if phase is None:
        if len(ids) > 1:
            names = [xmap.phases[i].name for i in ids]
            raise ValueError(
                f"xmap has several phases {names}: choose one with phase=<name>"
            )
        if not ids:
            raise ValueError("xmap has no indexed points")
        phase_id = ids[0]
    else:
        try:
            phase_id = xmap.phases.id_from_name(phase) if isinstance(phase, str) else int(phase)
        except (KeyError, ValueError, AttributeError):
            raise ValueError(f"Phase {phase!r} is not in xmap's phases") from None
    mp_pg = master_pattern.phase.point_group
    x_pg = xmap.phases[phase_id].point_group
    if mp_pg is not None and x_pg is not None and mp_pg.name != x_pg.name:
        raise ValueError(
            f"The master pattern's point group {mp_pg.name} differs from the "
            f"phase's {x_pg.name} in xmap"
        )
    return phase_id


# --------------------------------------------------------------------- #
# The loop
# --------------------------------------------------------------------- #


@dataclass
class _Problem:
    """Everything that stays fixed during a refinement."""

    experimental: np.ndarray
    points: np.ndarray
    start_rotations: Rotation
    master_pattern: EBSDMasterPattern
    energy: float
    phase: Any
    parameters: tuple[str, ...]
    steps: dict[str, float]
    dic_kwargs: dict
    refine_kwargs: dict

    def simulate(self, geometry: MapGeometry, rotations: Rotation) -> np.ndarray:
        det = geometry.detector(self.points)
        return simulate_patterns(self.master_pattern, rotations, det, self.energy)

    def measure(self, geometry: MapGeometry, rotations: Rotation) -> dsp.DisplacementField:
        sim = self.simulate(geometry, rotations)
        return dsp.measure_displacements(sim, self.experimental, **self.dic_kwargs)

    def refine_orientations(
        self, geometry: MapGeometry, rotations: Rotation, binning: int | None = None
    ) -> tuple[Rotation, np.ndarray]:
        """Refine orientations with kikuchipy, on patterns binned by
        *binning* (default :attr:`loop_binning`)."""
        b = self.loop_binning if binning is None else binning
        n = len(self.points)
        exp = self.experimental
        det = geometry.detector(self.points)
        if b > 1:
            # Bruker PC fractions do not change with binning
            exp = exp.reshape(n, exp.shape[1] // b, b, exp.shape[2] // b, b).mean(axis=(2, 4))
            det = copy_detector(det, shape=exp.shape[1:], binning=det.binning * b)
        signal = EBSD(exp)
        signal.axes_manager.navigation_axes[0].name = "x"
        xmap = CrystalMap(
            rotations=rotations, x=np.arange(n, dtype=float), phase_list=PhaseList(self.phase)
        )
        # kikuchipy prints a summary and a dask progress bar per call
        with contextlib.redirect_stdout(io.StringIO()):
            ref = signal.refine_orientation(
                xmap, det, self.master_pattern, self.energy, **self.refine_kwargs
            )
        return ref.rotations, ref.scores

    @property
    def loop_binning(self) -> int:
        """Binning of the orientation refinements inside the loop: the
        largest factor dividing the pattern shape that keeps at least
        60 px a side. Orientations refined from 60 px patterns were as
        precise (0.0025 deg) as from 120 px ones (0.0022 deg) at a quarter
        of the cost; the final orientations use full resolution."""
        ny, nx = self.experimental.shape[1:]
        b = 1
        for f in range(2, min(ny, nx) // 60 + 1):
            if ny % f == 0 and nx % f == 0:
                b = f
        return b

    def variants(self, rotations: Rotation) -> tuple[np.ndarray, Rotation]:
        """Return, per point, the pseudo-symmetry operator (0: none) that
        brings the start closest to *rotations*, and the remaining
        deviation ``~(op * start) * rotation`` (a sample-frame rotation)."""
        ops = self.refine_kwargs.get("pseudo_symmetry_ops")
        ops_all = Rotation.identity(1)
        if ops is not None:
            ops_all = Rotation(np.concatenate([ops_all.data, ops.flatten().data]))
        angles = np.stack(
            [(~(op * self.start_rotations) * rotations).angle for op in ops_all], axis=1
        )
        k = np.argmin(angles, axis=1)
        return k, ~(ops_all[k] * self.start_rotations) * rotations

    def anchor(self, rotations: Rotation) -> Rotation:
        """Remove the mean deviation from the start (see module notes)."""
        _, dq = self.variants(rotations)
        # Far-off points (another variant not among the operators, or a
        # failed refinement) are not small deviations
        small = dq.angle < np.deg2rad(5)
        if not small.any():
            return rotations
        mean = (dq.axis.data * dq.angle[:, None])[small].mean(axis=0)
        a = np.linalg.norm(mean)
        if a == 0:
            return rotations
        return rotations * ~Rotation.from_axes_angles(mean / a, a)

    def jacobian(
        self, geometry: MapGeometry, rotations: Rotation, field0: dsp.DisplacementField, kind: str
    ) -> np.ndarray:
        if kind == "finite-difference":
            return finite_difference_jacobian(
                lambda g: self.measure(g, rotations).residual, geometry, self.parameters, self.steps
            )
        return analytic_jacobian(
            geometry, self.points, field0.positions, field0.counts, self.parameters, self.steps
        )


def _mean_displacement(f: dsp.DisplacementField) -> float:
    """Mean magnitude of the average field over ROIs with vectors, as a
    fraction of the detector width."""
    has = f.total_counts > 0
    if not has.any():
        return float("nan")
    return float(np.linalg.norm(f.mean[has], axis=1).mean() / f.shape[1])


def refine_geometry_dic(
    signal: EBSD,
    xmap: CrystalMap,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern,
    energy: float,
    parameters: Sequence[str] = DEFAULT_PARAMETERS,
    points: int | np.ndarray = 100,
    steps: Mapping[str, float] | None = None,
    rois: tuple[int, int] = (8, 8),
    binning: int = 1,
    dic: str = "auto",
    jacobian: str = "analytic",
    damping: float = 1e-3,
    max_iterations: int = 10,
    ncc_tolerance: float = 0.005,
    refine_kwargs: Mapping[str, Any] | None = None,
    dic_kwargs: Mapping[str, Any] | None = None,
    phase: str | int | None = None,
    seed: int | None = 0,
    show_progressbar: bool | None = None,
) -> GeometryRefinementResult:
    """Refine the global sample-detector geometry of a map by global DIC.

    Parameters
    ----------
    signal
        EBSD map (``EBSD`` or ``LazyEBSD``), 1D or 2D navigation shape,
        navigation axes scaled by the step sizes in micrometres.
    xmap
        Starting orientations for the map (e.g. Hough indexing), of the
        signal's navigation shape. Points not indexed (phase -1, zero or
        NaN rotations) are not used.
    detector
        Starting geometry: one PC (taken at the map centre) or one PC per
        map point (its mean is taken at the mean position).
    master_pattern
        Lambert master pattern of the phase.
    energy
        Beam energy in kV.
    parameters
        Parameters to refine, from
        :data:`~kikuchipy_geomdic.geometry.PARAMETERS`. Default the
        paper's six. Both ``tilt`` and ``sample_tilt`` may be given: only
        their difference is determined and the change is split equally
        (see :mod:`~kikuchipy_geomdic.solve`); leave one out to keep it
        fixed.
    points
        Number of calibration points spread evenly over the map, or an
        explicit (N, 2) integer array of (row, column).
    steps
        Central-difference step per parameter; defaults in
        :data:`~kikuchipy_geomdic.geometry.DEFAULT_STEPS`.
    rois
        ROI grid (rows, columns) of the displacement field.
    binning
        Pixel binning before feature detection and tracking.
    dic
        "auto" (OpenCV if importable, else scikit-image), "opencv" or
        "skimage".
    jacobian
        "analytic" (default: the forward displacement map evaluated at
        the measured feature positions, no simulation) or
        "finite-difference" (the paper's Eqs. 4-5: a simulation and DIC
        pass per +-delta). Both reach the same geometry (the fixed point
        is b = 0 either way); the analytic one is free of DIC noise and
        about four times faster.
    damping
        lambda of Eq. 10.
    max_iterations
        Upper bound on geometry updates.
    ncc_tolerance
        NCC gain below which the loop may stop, and NCC loss above which
        a step is rejected.
    refine_kwargs
        Passed to kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation`
        (``method``, ``method_kwargs``, ``trust_region``,
        ``pseudo_symmetry_ops``, ...).
    dic_kwargs
        Further options of
        :func:`~kikuchipy_geomdic.displacement.measure_displacements`
        (``noise``, ``max_roi_crossings``, ...).
    phase
        Phase name or id in *xmap* to calibrate with; required when *xmap*
        has several phases.
    seed
        Seed of the DIC noise.
    show_progressbar
        Print one line per step. Default: on.

    Returns
    -------
    result
        :class:`GeometryRefinementResult`. The inputs are not modified.

    Examples
    --------
    >>> from kikuchipy_geomdic import synthetic, refine_geometry_dic
    >>> sm = synthetic.synthetic_map("Si", (5, 5), shape=(60, 60), seed=0)
    >>> res = refine_geometry_dic(
    ...     sm.signal, sm.start_xmap, sm.start_detector, sm.master_pattern, 20,
    ...     parameters=["pcx", "pcy", "pcz"], points=25, jacobian="analytic",
    ...     max_iterations=3, show_progressbar=False,
    ... )
    >>> res.detector.navigation_shape
    (5, 5)
    """
    if show_progressbar is None:
        show_progressbar = True
    names = check_parameters(parameters)
    if jacobian not in _JACOBIANS:
        raise ValueError(f"jacobian must be one of {_JACOBIANS}, not {jacobian!r}")
    nav = _navigation_shape(signal)
    phase_id = _check_inputs(signal, xmap, detector, master_pattern, phase, nav)
    step_all = dict(DEFAULT_STEPS)
    if steps:
        check_parameters(list(steps))
        step_all.update({k: float(v) for k, v in steps.items()})
    if any(step_all[n] <= 0 for n in names):
        raise ValueError("Finite-difference steps must be positive")

    usable = usable_points(xmap, phase_id).reshape(nav)
    if np.ndim(points) == 0:
        pts = calibration_points(nav, int(points), usable)
    else:
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] != 2 or not np.issubdtype(pts.dtype, np.integer):
            raise ValueError("points must be an int or an (N, 2) integer array of (row, col)")
        outside = (pts < 0).any(axis=1) | (pts[:, 0] >= nav[0]) | (pts[:, 1] >= nav[1])
        if outside.any():
            raise ValueError(
                f"{outside.sum()} point(s) lie outside the map of shape {nav}, e.g. "
                f"{pts[outside][0].tolist()}"
            )
        bad = ~usable[pts[:, 0], pts[:, 1]]
        if bad.any():
            raise ValueError(
                f"{bad.sum()} point(s) are not indexed with the chosen phase, e.g. "
                f"{pts[bad][0].tolist()}"
            )
    n_free = len(names) - sum(
        1 for n in names if n in EQUIVALENT_PARAMETERS and EQUIVALENT_PARAMETERS[n][0] in names
    )
    if len(pts) < max(n_free, 2):
        raise ValueError(
            f"{len(pts)} usable calibration point(s) for {n_free} independent "
            "parameter(s): at least as many points as parameters (and 2) are needed"
        )

    exp = _experimental(signal, pts, nav)
    geometry0 = MapGeometry.from_detector(detector, _step_sizes(signal), nav)
    flat = pts[:, 0] * nav[1] + pts[:, 1]
    lookup = np.full(nav[0] * nav[1], -1)
    lookup[xmap.id] = np.arange(xmap.size)
    start_rot = Rotation(xmap.rotations.data[lookup[flat]])

    dic_kw = dict(rois=tuple(rois), binning=binning, dic=dic, seed=seed)
    dic_kw.update(dic_kwargs or {})
    ref_kw = dict(refine_kwargs or {})
    problem = _Problem(
        experimental=exp,
        points=pts,
        start_rotations=start_rot,
        master_pattern=master_pattern,
        energy=float(energy),
        # The master pattern's phase, checked above to have xmap's point
        # group: kikuchipy refuses phases whose atom lists differ in order
        # (as after a round trip through an h5ebsd file)
        phase=master_pattern.phase.deepcopy(),
        parameters=names,
        steps={n: step_all[n] for n in names},
        dic_kwargs=dic_kw,
        refine_kwargs=ref_kw,
    )
    say = print if show_progressbar else (lambda *a, **k: None)

    # The starting state, judged after orientation refinement like every
    # later state
    say(f"Refining the geometry with {len(pts)} calibration points: {', '.join(names)}")
    rot_ref, scores = problem.refine_orientations(geometry0, start_rot)
    state = dict(
        geometry=geometry0,
        # The first field uses the starting orientations themselves, as the
        # paper does: orientations refined at a far-off start absorb much of
        # a large geometry error (measured: a 6 % start read as 1.4 %), and
        # the loop then converges to a wrong geometry
        rotations=start_rot,
        refined=rot_ref,
        scores=scores,
        ncc=float(np.mean(scores)),
    )
    state["field"] = problem.measure(geometry0, state["rotations"])
    field_before = state["field"]
    state["disp"] = _mean_displacement(state["field"])
    history = []
    converged = False
    jac = None
    update = None
    gain = np.inf
    for it in range(max_iterations):
        jac = problem.jacobian(state["geometry"], state["rotations"], state["field"], jacobian)
        lam = damping
        step_taken = False
        for attempt in range(3):
            update = solve_update(jac, state["field"].residual, state["field"].weights, lam)
            geo = state["geometry"].updated(dict(zip(names, update.delta)))
            # Judge the step first by the displacement with the current
            # orientations (a simulation and a DIC pass); only a step that
            # lowers it pays for orientation refinement
            disp = _mean_displacement(problem.measure(geo, state["rotations"]))
            ncc = float("nan")
            accepted = bool(disp < state["disp"])
            if accepted:
                rot_ref, scores = problem.refine_orientations(geo, state["rotations"])
                ncc = float(np.mean(scores))
                accepted = bool(ncc > state["ncc"] - ncc_tolerance)
            history.append(
                dict(
                    iteration=it,
                    parameters=dict(zip(names, map(float, geo.values(names)))),
                    ncc_before=state["ncc"],
                    ncc_after=ncc,
                    displacement_before=state["disp"],
                    displacement_after=disp,
                    damping=lam,
                    accepted=accepted,
                )
            )
            say(
                f"  iteration {it}: NCC {state['ncc']:.4f} -> {ncc:.4f}, displacement "
                f"{100 * state['disp']:.3f} -> {100 * disp:.3f} % of width, "
                f"{'accepted' if accepted else 'rejected'}"
            )
            if accepted:
                rot = problem.anchor(rot_ref)
                fld = problem.measure(geo, rot)
                gain = ncc - state["ncc"]
                fall = 1 - disp / state["disp"]
                state = dict(
                    geometry=geo, rotations=rot, refined=rot_ref, scores=scores,
                    ncc=ncc, field=fld, disp=_mean_displacement(fld),
                )
                step_taken = True
                break
            lam *= 10
        if not step_taken:
            # No step lowers the displacement any more: converged if the
            # NCC had stopped gaining too (the paper's criterion)
            converged = bool(history) and any(h["accepted"] for h in history) and gain < ncc_tolerance
            break
        if gain < ncc_tolerance and fall < 0.1:
            converged = True
            break

    geometry = state["geometry"]
    # Orientations refined at the final geometry, not anchored: the best
    # estimate of each orientation given the calibrated geometry
    final_rot, final_scores = state["refined"], state["scores"]
    if problem.loop_binning > 1:
        final_rot, final_scores = problem.refine_orientations(geometry, final_rot, binning=1)
    xmap_out = CrystalMap(
        rotations=final_rot,
        x=np.arange(len(pts), dtype=float),
        phase_list=PhaseList(problem.phase),
        prop={
            "scores": np.asarray(final_scores),
            "row": pts[:, 0],
            "col": pts[:, 1],
            "pseudo_symmetry_index": problem.variants(final_rot)[0],
        },
    )
    det = geometry.detector()
    if len(detector.navigation_shape) == 2 or nav[0] > 1:
        det.pc = det.pc.reshape(
            signal.axes_manager.navigation_shape[::-1] + (3,)
        )
    degenerate = [
        {n: float(c) for n, c in zip(names, v) if abs(c) > 1e-6}
        for v in update.null_space.T
    ] if update is not None else []
    return GeometryRefinementResult(
        detector=det,
        geometry=geometry,
        start_geometry=geometry0,
        xmap=xmap_out,
        points=pts,
        parameter_names=names,
        parameters=dict(zip(names, map(float, geometry.values(names)))),
        history=history,
        jacobian=jac,
        coupling=coupling_matrix(jac, state["field"].weights),
        singular_values=update.singular_values if update is not None else np.array([]),
        degenerate=degenerate,
        field_before=field_before,
        field_after=state["field"],
        converged=converged,
        steps=problem.steps,
    )


def _experimental(signal: EBSD, pts: np.ndarray, nav: tuple[int, int]) -> np.ndarray:
    data = signal.data
    if len(signal.axes_manager.navigation_shape) == 1:
        sel = data[pts[:, 1]]
    else:
        # Sorted, unique row-major indices read a lazy signal chunk-wise
        data = data.reshape((nav[0] * nav[1],) + data.shape[-2:])
        sel = data[pts[:, 0] * nav[1] + pts[:, 1]]
    if hasattr(sel, "compute"):
        sel = sel.compute()
    sel = np.asarray(sel, dtype=np.float32)
    bad = ~np.isfinite(sel).all(axis=(1, 2))
    if bad.any():
        raise ValueError(
            f"{bad.sum()} calibration pattern(s) contain NaN or infinite values, e.g. "
            f"at (row, col) {pts[bad][0].tolist()}: remove them from xmap or pass "
            "explicit points"
        )
    return sel
