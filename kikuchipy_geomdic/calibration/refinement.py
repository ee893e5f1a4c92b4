"""The refinement loop: global geometry from displacement fields.

Both solvers follow the paper's method (sections 2.2-2.4, Fig. 4):
simulate the calibration points at the current geometry, measure the
displacement fields (:mod:`~kikuchipy_geomdic.patterns.displacement`),
linearise (:mod:`~kikuchipy_geomdic.calibration.jacobian`), solve
(:mod:`~kikuchipy_geomdic.calibration.solve`) and update the geometry and its
PC field (:mod:`~kikuchipy_geomdic.geometry`).

The joint solver (default)
--------------------------
The unknowns are the geometry *and* one small rotation per calibration
pattern. Each pattern's own ROI field is modelled as
``J_geo,i dp + J_rot,i dw_i``; the rotations are eliminated exactly and
the orientations updated from the same fields, so no kikuchipy refinement
runs inside the loop. A step is accepted when the RMS of the per-pattern
displacements falls (else the damping grows tenfold, up to
:data:`MAX_TRIALS` times); the loop converges when every parameter's step
is below its standard error.

- *Gauge.* A rotation common to all orientations equals a change of the
  detector angles for every pattern. Without an ``orientation_prior``
  only the PC field across the map separates the two; with one, the
  starting orientations' mean pins it. Parameters the map determines
  poorly (standard error above :data:`DETERMINACY_LIMITS`) leave their
  start only by a significant step rather than follow the noise; such
  angles wait until the PC has settled, and a step in them, which the RMS
  cannot resolve, is accepted when no parameter would move significantly
  from where it lands.
- *Standard errors.* Cluster-robust over the patterns: DIC errors within
  a pattern are correlated, which a model of independent vectors misses.
- *Weights.* An ROI mean of ``c`` vectors weighs ``c`` times a vector, and
  each pattern has its own vector variance, estimated from its residuals
  (never below the median pattern's), so that a poor pattern (a grain
  boundary, a wrong variant) weighs little.
- *Degeneracy.* The ``sample_tilt`` column is ``-1`` times the ``tilt``
  column, exactly: with both refined, the solve has one column for their
  difference and splits its change equally.

The paper's solver
------------------
``solver="paper"``: the average field, Eqs. 8-11, kikuchipy's orientation
refinement inside the loop and NCC acceptance, with these departures:

- *Anchored orientations.* Orientation refinement at a wrong geometry
  absorbs the angle error into the orientations, so the orientations used
  to simulate are the refined ones with their mean rotation relative to
  the start removed: the angles are measured against the starting
  orientations, assumed free of a common error.
- *Acceptance.* A step is accepted when the mean displacement magnitude
  falls and the NCC after orientation refinement does not drop by more
  than ``ncc_tolerance``; the loop ends when the NCC gain is below
  ``ncc_tolerance`` and the displacement no longer falls by 10 %.
- *Jacobian.* ``"analytic"`` evaluates the forward displacement map at the
  measured feature positions instead of simulating at ``p +- delta``.

Layout
------
As kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation`:
:func:`refine_geometry_dic` checks its inputs (:func:`_check_options`,
:func:`_check_inputs`), selects the calibration points
(:func:`_select_points`), freezes everything that stays fixed into a
:class:`_Problem` (:func:`_prepare_problem`), runs one of the loops
(:func:`_joint_loop`, one :func:`_joint_step` per iteration, or
:func:`_paper_loop`) on frozen :class:`_State` s and builds the
:class:`GeometryRefinementResult` (:func:`_build_result`).
"""

from __future__ import annotations

import functools
import sys
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import hyperspy.api as hs
import numba as nb
import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation
from scipy import ndimage
from tqdm import tqdm

from kikuchipy_geomdic.calibration.jacobian import (
    INTENSITY_STEPS,
    analytic_jacobian,
    finite_difference_jacobian,
    intensity_jacobian,
    pattern_jacobian,
)
from kikuchipy_geomdic.calibration.solve import (
    JointUpdate,
    coupling_matrix,
    solve_joint,
    solve_update,
)
from kikuchipy_geomdic.geometry import (
    DEFAULT_PARAMETERS,
    DEFAULT_STEPS,
    EQUIVALENT_PARAMETERS,
    MapGeometry,
    check_parameters,
    rotation_vectors,
    rotations_from_vectors,
    solved_parameters,
)
from kikuchipy_geomdic.geometry.maps import check_signal_and_detector, flat_index, navigation_shape
from kikuchipy_geomdic.indexing import orientation as ori
from kikuchipy_geomdic.indexing.reindex import refine_orientations, usable_points
from kikuchipy_geomdic.patterns import displacement as dsp
from kikuchipy_geomdic.patterns.phases import check_phase
from kikuchipy_geomdic.patterns.simulation import check_master_pattern

__all__ = [
    "GeometryRefinementResult",
    "refine_geometry_dic",
    "calibration_points",
    "SOLVERS",
    "DETERMINACY_LIMITS",
    "ADEQUACY_LIMIT",
]

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
        ``pseudo_symmetry_index`` (which of the pseudo-symmetry operators,
        1-based, 0 for none, relates the input orientation to the refined
        one) and ``dic_rms``: the RMS displacement in pixels left in each
        pattern's field at the refined state (one far above the rest marks
        a pattern the calibration could not use, e.g. a failed start).
    points
        Calibration points (N, 2) as (row, column).
    parameter_names
        The refined parameters, in canonical order.
    parameters
        ``{name: refined value}`` for the refined parameters.
    standard_errors
        ``{name: sigma}`` for every refined parameter, in its unit, plus
        ``"tilt-sample_tilt"`` when either tilt is refined: from the
        joint normal matrix at the refined geometry (rotations
        eliminated, ``orientation_prior`` included) and the measured
        residual scatter. ``inf`` for tilt and sample_tilt when both are
        refined: only their difference is determined.
    undetermined
        Parameters the map determines only poorly (standard error above
        :data:`DETERMINACY_LIMITS`; for tilt and sample_tilt, that of
        their difference). The joint solver moved them only by
        significant steps; unmoved, they keep their start value.
    solver
        "joint" or "paper".
    history
        One dict per trial step: ``parameters`` (values after the step),
        ``ncc_before``, ``ncc_after`` (mean NCC; NaN for a rejected step),
        ``displacement_before``, ``displacement_after`` (the solver's
        objective as a fraction of the detector width: RMS of the
        per-pattern ROI displacements for the joint solver, mean
        magnitude of the average field for the paper's), ``damping``,
        ``accepted`` and, joint solver, ``standard_errors`` of the step.
        Paper solver: the NCC is after orientation refinement, on the
        binned patterns of the loop for patterns of 120 px or more.
    jacobian
        Jacobian (2R, K) of the average field at the refined geometry,
        pixels per parameter unit, columns in *parameter_names* order.
    coupling
        Normalised coupling matrix (K, K), the paper's Fig. 3C.
    singular_values
        Singular values of the weighted, column-normalised Jacobian of
        the average field.
    degenerate
        Parameter combinations the data cannot constrain, as
        ``{name: coefficient}`` dicts (e.g. tilt and sample_tilt).
    field_before, field_after
        :class:`~kikuchipy_geomdic.patterns.displacement.DisplacementField` at the
        start and at the refined geometry.
    converged
        Whether the loop ended by its tolerances (joint: every step below
        its standard error; paper: NCC gain below ``ncc_tolerance`` and
        the displacement no longer falling) rather than by
        *max_iterations* or by rejected steps.
    adequacy
        The check of the full-field stage against the DIC stage
        (:data:`ADEQUACY_LIMIT`): the step the DIC stage would take
        from the full field's solution per parameter (``"dic_step"``) and
        in units of their combined standard errors (``"z"``), whether it passed
        (``"consistent"``; if not, the standard errors are inflated to
        cover the disagreement) and a sentence saying so
        (``"verdict"``). Empty when no full field ran.
    """

    detector: EBSDDetector
    geometry: MapGeometry
    start_geometry: MapGeometry
    xmap: CrystalMap
    points: np.ndarray
    parameter_names: tuple[str, ...]
    parameters: dict[str, float]
    standard_errors: dict[str, float]
    undetermined: tuple[str, ...]
    solver: str
    history: list[dict[str, Any]]
    jacobian: np.ndarray
    coupling: np.ndarray
    singular_values: np.ndarray
    degenerate: list[dict[str, float]]
    field_before: dsp.DisplacementField
    field_after: dsp.DisplacementField
    converged: bool
    steps: dict[str, float] = field(default_factory=dict)
    adequacy: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        return self.table()

    def table(self, truth: MapGeometry | None = None) -> str:
        """Return start and refined values with standard errors as text.

        Parameters
        ----------
        truth
            Known geometry (synthetic data) to add true values and errors.
        """
        head = (
            f"{type(self).__name__} ({self.solver} solver, {len(self.points)} points, "
            f"{len(self.history)} steps, converged={self.converged}, DIC "
            f"{self.field_after.backend})"
        )
        cols = f"{'parameter':<17}{'start':>10}{'refined':>11}{'sigma':>10}"
        if truth is not None:
            cols += f"{'true':>11}{'error':>11}"
        lines = [head, cols + "  unit"]
        start, true = self.start_geometry.as_dict(), None
        if truth is not None:
            true = truth.as_dict()
        rows = [(n, start[n], self.parameters[n]) for n in self.parameter_names]
        if TILT_DIFFERENCE in self.standard_errors:
            ref = {**start, **self.parameters}
            rows.append(
                (
                    TILT_DIFFERENCE,
                    start["tilt"] - start["sample_tilt"],
                    ref["tilt"] - ref["sample_tilt"],
                )
            )
            if true is not None:
                true[TILT_DIFFERENCE] = true["tilt"] - true["sample_tilt"]
        notes = []
        for name, a, b in rows:
            pc = name.startswith("pc")
            f = "{:>10.6f}" if pc else "{:>10.4f}"
            se = self.standard_errors.get(name, float("nan"))
            line = f"{name:<17}" + f.format(a) + " " + f.format(b)
            line += f"{se:>10.1e}" if np.isfinite(se) else f"{'-':>10}"
            if true is not None:
                line += (
                    " "
                    + f.format(true[name])
                    + " "
                    + ("{:>+10.6f}" if pc else "{:>+10.4f}").format(b - true[name])
                )
            line += "  " + ("PC" if pc else "deg")
            if name in self.undetermined or (
                name == TILT_DIFFERENCE and "tilt" in self.undetermined
            ):
                line += "  poorly determined" + (", kept" if a == b else "")
            lines.append(line)
        if any(not np.isfinite(self.standard_errors.get(n, 0)) for n in self.parameter_names):
            notes.append("tilt and sample_tilt: only their difference is determined")
        if self.adequacy:
            notes.append(self.adequacy["verdict"])
        return "\n".join(lines + notes)

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

    def compare_bound(self, bound) -> str:
        """Return the standard errors next to a Cramer-Rao bound, with
        their ratio (1: the data's information limit is reached).

        Parameters
        ----------
        bound
            :class:`~kikuchipy_geomdic.calibration.bound.CramerRaoBound` of the same
            map, e.g. from :func:`~kikuchipy_geomdic.calibration.bound.cramer_rao_bound`
            at :attr:`geometry` with :attr:`xmap` and ``points=``
            :attr:`points`.

        Returns
        -------
        table
        """
        return bound.table(self.standard_errors)


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
    >>> from kikuchipy_geomdic.calibration.refinement import calibration_points
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


def _step_sizes(signal: EBSD) -> tuple[float, float]:
    axes = signal.axes_manager.navigation_axes
    if len(axes) == 2:
        dx, dy = axes[0].scale, axes[1].scale
    else:
        dx = axes[0].scale
        dy = dx
    return float(dy), float(dx)


def _check_inputs(signal, xmap, detector, master_pattern, phase, nav):
    check_signal_and_detector(signal, detector)
    if not isinstance(xmap, CrystalMap):
        raise TypeError(f"xmap must be an orix CrystalMap, not {type(xmap).__name__}")
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
    return check_phase(xmap, master_pattern, phase)


def _check_options(parameters, solver, jacobian, orientation_prior) -> tuple[str, ...]:
    """Check the options that need no data; return the parameters to
    refine in canonical order."""
    names = check_parameters(parameters)
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, not {solver!r}")
    if jacobian not in _JACOBIANS:
        raise ValueError(f"jacobian must be one of {_JACOBIANS}, not {jacobian!r}")
    if orientation_prior is not None and not (
        np.isfinite(orientation_prior) and orientation_prior > 0
    ):
        raise ValueError(
            f"orientation_prior must be a positive RMS angle in degrees or None, "
            f"not {orientation_prior}"
        )
    return names


def _check_steps(names: Sequence[str], steps: Mapping[str, float] | None) -> dict[str, float]:
    """Central-difference steps of the refined parameters: the defaults
    updated by *steps*, all positive."""
    step_all = dict(DEFAULT_STEPS)
    if steps:
        check_parameters(list(steps))
        step_all.update({k: float(v) for k, v in steps.items()})
    if any(step_all[n] <= 0 for n in names):
        raise ValueError("Finite-difference steps must be positive")
    return {n: step_all[n] for n in names}


def _select_points(
    points, xmap: CrystalMap, phase_id: int, nav: tuple[int, int], names: Sequence[str]
) -> np.ndarray:
    """The calibration points (N, 2): *points* spread over the usable map
    points, or the explicit array checked; enough for the parameters."""
    pts = _points(points, usable_points(xmap, phase_id).reshape(nav), nav)
    n_free = len(solved_parameters(names)[0])
    if len(pts) < max(n_free, 2):
        raise ValueError(
            f"{len(pts)} usable calibration point(s) for {n_free} independent "
            "parameter(s): at least as many points as parameters (and 2) are needed"
        )
    return pts


def _points(points, usable: np.ndarray, nav: tuple[int, int]) -> np.ndarray:
    if np.ndim(points) == 0:
        return calibration_points(nav, int(points), usable)
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
    return pts


def _experimental(signal: EBSD, pts: np.ndarray, nav: tuple[int, int]) -> np.ndarray:
    data = signal.data
    if len(signal.axes_manager.navigation_shape) == 1:
        sel = data[pts[:, 1]]
    else:
        # Sorted, unique row-major indices read a lazy signal chunk-wise
        data = data.reshape((nav[0] * nav[1],) + data.shape[-2:])
        sel = data[flat_index(pts, nav)]
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


def _prepare_problem(
    signal: EBSD,
    xmap: CrystalMap,
    master_pattern: EBSDMasterPattern,
    energy: float,
    names: tuple[str, ...],
    points,
    phase_id: int,
    nav: tuple[int, int],
    steps: Mapping[str, float] | None,
    dic_kwargs: dict,
    refine_kwargs: Mapping[str, Any] | None,
    pseudo_symmetry_ops: Rotation | None,
) -> _Problem:
    """Check the steps, select the points, read their patterns and
    starting orientations: the :class:`_Problem` the loops solve."""
    steps = _check_steps(names, steps)
    ref_kw = dict(refine_kwargs or {})
    ops = ref_kw.pop("pseudo_symmetry_ops", None)
    if pseudo_symmetry_ops is not None:
        ops = pseudo_symmetry_ops
    pts = _select_points(points, xmap, phase_id, nav, names)
    exp = _experimental(signal, pts, nav)
    lookup = np.full(nav[0] * nav[1], -1)
    lookup[xmap.id] = np.arange(xmap.size)
    return _Problem(
        experimental=exp,
        points=pts,
        start_rotations=Rotation(xmap.rotations.data[lookup[flat_index(pts, nav)]]),
        master_pattern=master_pattern,
        energy=float(energy),
        # The master pattern's phase, checked to match xmap's: kikuchipy
        # refuses phases whose atom lists differ in order (as after a
        # round trip through an h5ebsd file)
        phase=master_pattern.phase.deepcopy(),
        parameters=names,
        steps=steps,
        dic_kwargs=dic_kwargs,
        refine_kwargs=ref_kw,
        pseudo_symmetry_ops=None if ops is None else Rotation(ops).flatten(),
        lobe=_lobe(signal),
    )


def _lobe(signal: EBSD) -> np.ndarray | None:
    """The background lobe, mean 1: a Gaussian fitted to the signal's
    static background (kikuchipy's ``EBSD.static_background``; its
    logarithm, quadratic in x and y, by least squares); None without one.
    A map-mean background holds faint bands, which the fit averages out
    where smoothing kept a part (a Gaussian smoothing of an eighth of the
    width left pcz 0.45e-4 off at 20,000 counts/px, the fit 0.24e-4)."""
    bg = getattr(signal, "static_background", None)
    shape = tuple(signal.axes_manager.signal_shape[::-1])
    if bg is None or tuple(np.shape(bg)) != shape:
        return None
    bg = np.asarray(bg.compute() if hasattr(bg, "compute") else bg, dtype=np.float64)
    if not np.isfinite(bg).all() or bg.min() <= 0:
        return None
    y, x = (np.indices(shape).reshape(2, -1) + 0.5) / shape[1]
    basis = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    coef, *_ = np.linalg.lstsq(basis, np.log(bg.ravel()), rcond=None)
    lobe = np.exp(basis @ coef).reshape(shape)
    return lobe / lobe.mean()


# --------------------------------------------------------------------- #
# The problem: everything that stays fixed during a refinement
# --------------------------------------------------------------------- #

#: Solvers of :func:`refine_geometry_dic`.
SOLVERS = ("joint", "paper")

#: A parameter whose standard error exceeds this (its unit) is poorly
#: determined by the map: the joint solver moves it only by significant
#: steps (:data:`SIGNIFICANCE`), so noise cannot. PC: 1e-3 is what pattern-wise
#: refinement reaches on single patterns; angles: 0.1 deg is the accuracy
#: of a goniometer or detector-installation readout.
DETERMINACY_LIMITS = {
    "pcx": 1e-3,
    "pcy": 1e-3,
    "pcz": 1e-3,
    "tilt": 0.1,
    "azimuthal": 0.1,
    "sample_tilt": 0.1,
    "twist": 0.1,
}

#: A poorly determined parameter (standard error above its limit) leaves
#: its start value only by a step of at least this many standard errors.
SIGNIFICANCE = 3.0

_PC = ("pcx", "pcy", "pcz")

#: Name of the determined combination of the two equivalent tilts.
TILT_DIFFERENCE = "tilt-sample_tilt"

#: Smallest vector variance (px^2) assumed: DIC is not more precise than
#: 1e-4 px, and a start at the exact truth must not give infinite weights.
MIN_VARIANCE = 1e-8

#: A step that lowers the displacement by less than this fraction ends
#: the joint loop: the measurement's noise floor is reached.
MIN_FALL = 0.1

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

#: Paper solver: an accepted step that gains less NCC than
#: ``ncc_tolerance`` and lowers the mean displacement by less than this
#: fraction ends the loop: the displacement no longer falls by 10 %.
PAPER_MIN_FALL = 0.1

#: Paper solver: a point whose refined orientation lies further than this
#: (degrees) from its start is no small deviation (another variant not
#: among the operators, or a failed refinement) and is left out of the
#: mean rotation removed by the anchoring.
ANCHOR_MAX_ANGLE = 5.0

#: Paper solver: smallest side (px) the patterns are binned down to for
#: the orientation refinements inside the loop. Orientations refined from
#: 60 px patterns were as precise (0.0025 deg) as from 120 px ones
#: (0.0022 deg) at a quarter of the cost.
LOOP_MIN_SIZE = 60

#: Unknowns per pattern besides the geometry (its small rotation): the
#: degrees of freedom its residuals lose when its variance is estimated.
ROTATION_UNKNOWNS = 3

#: Vector variance (px^2) assumed for every pattern when none has enough
#: vectors (more than :data:`ROTATION_UNKNOWNS` components) to estimate
#: its own: all patterns then weigh the same, one square pixel each.
FALLBACK_VARIANCE = 1.0

#: Components of a null-space vector below this are SVD round-off, not
#: part of the reported degenerate combination (the columns are
#: normalised, so a real component is of order one).
NULL_SPACE_TOLERANCE = 1e-6

#: Gauss-Newton steps of the full-field stage at most; it stops earlier
#: when no parameter moves by more than :data:`FULL_FIELD_STOP` of its
#: standard error.
FULL_FIELD_ITERATIONS = 5
FULL_FIELD_STOP = 0.25
#: ... and no orientation moves by more than this (deg).
FULL_FIELD_ROTATION_STOP = 0.01
#: The full field builds its Jacobians again after a step that lowered
#: chi2 by more than this fraction.
JACOBIAN_REFRESH = 0.1

#: RMS displacement (fraction of the width) below which the DIC stage
#: hands over to the full field: well inside its basin (measured: from
#: the state after one DIC step, 0.09 % RMS with the angles 0.5-0.7 deg
#: off, the full field reached the same geometry as after five).
FULL_FIELD_BASIN = 0.003

#: Smallest pixel noise variance of the full field, as a fraction of its
#: pattern's mean.
MIN_PIXEL_VARIANCE = 0.3

#: Range and grid (px) of the search for the detector's point spread.
PSF_MAX = 3.0
PSF_STEP = 0.25

#: A Gaussian blur narrower than this (px) is left out: its weight on a
#: neighbouring pixel is below 3e-4.
PSF_NEGLIGIBLE = 0.25


@dataclass(frozen=True)
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
    pseudo_symmetry_ops: Rotation | None = None
    #: The smoothed static background (mean 1), if the signal has one
    lobe: np.ndarray | None = None

    @cached_property
    def arrays(self) -> ori.MasterPatternArrays:
        """The master pattern's hemispheres at the energy, for projection."""
        return ori.master_pattern_arrays(self.master_pattern, self.energy)

    def simulate(self, geometry: MapGeometry, rotations: Rotation) -> np.ndarray:
        """Patterns (N, rows, columns), float64, as kikuchipy's
        ``get_patterns`` projects them, by this package's compiled
        kernel (a quarter of kikuchipy's time on 100 patterns)."""
        return ori.project_patterns(rotations, geometry.detector(self.points), self.arrays)

    def compare(
        self, geometry: MapGeometry, rotations: Rotation
    ) -> tuple[dsp.DisplacementField, np.ndarray]:
        """Displacement field and NCC (N,) of the patterns simulated at
        *geometry* against the experimental ones, from one simulation."""
        sim = self.simulate(geometry, rotations).astype(np.float32)
        field = dsp.measure_displacements(sim, self.experimental, **self.dic_kwargs)
        return field, _ncc(sim, self.experimental)

    def measure(self, geometry: MapGeometry, rotations: Rotation) -> dsp.DisplacementField:
        return self.compare(geometry, rotations)[0]

    def ncc(self, geometry: MapGeometry, rotations: Rotation) -> np.ndarray:
        """NCC (N,) of the patterns simulated at *geometry* with the
        experimental ones, full resolution."""
        return _ncc(self.simulate(geometry, rotations).astype(np.float32), self.experimental)

    def refine_orientations(
        self, geometry: MapGeometry, rotations: Rotation, binning: int | None = None
    ) -> tuple[Rotation, np.ndarray]:
        """Refine orientations with kikuchipy, on patterns binned by
        *binning* (default :attr:`loop_binning`)."""
        kw = dict(self.refine_kwargs)
        if self.pseudo_symmetry_ops is not None:
            kw["pseudo_symmetry_ops"] = self.pseudo_symmetry_ops
        ref = refine_orientations(
            self.experimental,
            rotations,
            geometry.detector(self.points),
            self.master_pattern,
            self.energy,
            self.phase,
            self.loop_binning if binning is None else binning,
            **kw,
        )
        return ref.rotations, ref.scores

    @property
    def loop_binning(self) -> int:
        """Binning of the orientation refinements inside the paper's loop
        (:func:`_binning`); the final orientations use full resolution."""
        return _binning(self.experimental.shape[1:])

    def operators(self) -> Rotation:
        """Identity followed by the pseudo-symmetry operators."""
        ops = Rotation.identity(1)
        if self.pseudo_symmetry_ops is not None:
            ops = Rotation(np.concatenate([ops.data, self.pseudo_symmetry_ops.flatten().data]))
        return ops

    def variants(self, rotations: Rotation) -> tuple[np.ndarray, Rotation]:
        """Return, per point, the pseudo-symmetry operator (0: none) that
        brings the start closest to *rotations*, and the remaining
        deviation ``~(op * start) * rotation`` (a sample-frame rotation)."""
        ops_all = self.operators()
        angles = np.stack(
            [(~(op * self.start_rotations) * rotations).angle for op in ops_all], axis=1
        )
        k = np.argmin(angles, axis=1)
        return k, ~(ops_all[k] * self.start_rotations) * rotations

    def rotation_offsets(self, rotations: Rotation) -> np.ndarray:
        """Rotation vectors (N, 3) of *rotations* away from the start (its
        closest variant): the offsets of the orientation prior."""
        return rotation_vectors(self.variants(rotations)[1])

    def best_variants(self, geometry: MapGeometry, rotations: Rotation) -> Rotation:
        """Return per point the variant ``op * rotation`` its pattern shows.

        Each candidate is first refined at *geometry* (Gauss-Newton on the
        intensities, :mod:`~kikuchipy_geomdic.indexing.orientation`), then compared
        by :func:`~kikuchipy_geomdic.indexing.orientation.compare_variants`:
        unrefined, a right variant a few tenths of a degree off lost to a
        wrong one refined by the loop (measured with the de-ebsd BaTiO3
        master pattern: 6 of 36 points kept a wrong variant)."""
        ops = self.operators()
        if ops.size == 1:
            return rotations
        m, n = ops.size, rotations.size
        det = geometry.detector(self.points)
        pcs = det.pc.reshape(-1, 3)
        pcs = np.repeat(pcs, n, axis=0) if pcs.shape[0] == 1 else pcs
        om = ori.detector_matrix(det)
        arrays = self.arrays
        candidates = np.stack([(op * rotations).data.reshape(-1, 4) for op in ops], axis=1)
        refined = ori.refine_arrays(
            np.repeat(self.experimental, m, axis=0),
            candidates.reshape(-1, 4),
            np.repeat(pcs, m, axis=0),
            om,
            arrays,
            levels=(1,),
        )
        rq = refined.rotations.data.reshape(n, m, 4)
        k = ori.compare_variants(self.experimental, rq, pcs, om, arrays).variant
        return ops[k] * rotations

    def jacobian(
        self, geometry: MapGeometry, rotations: Rotation, field0: dsp.DisplacementField, kind: str
    ) -> np.ndarray:
        if kind == "finite-difference":
            return finite_difference_jacobian(
                lambda g: self.measure(g, rotations).residual,
                geometry,
                self.parameters,
                self.steps,
            )
        return analytic_jacobian(
            geometry, self.points, field0.positions, field0.counts, self.parameters, self.steps
        )


def _binning(shape: tuple[int, int]) -> int:
    """The largest factor dividing the pattern *shape* that keeps at least
    :data:`LOOP_MIN_SIZE` px a side."""
    ny, nx = shape
    b = 1
    for f in range(2, min(ny, nx) // LOOP_MIN_SIZE + 1):
        if ny % f == 0 and nx % f == 0:
            b = f
    return b


# --------------------------------------------------------------------- #
# The state: where a refinement stands
# --------------------------------------------------------------------- #


@dataclass(frozen=True)
class _State:
    """A geometry and orientations, with the displacement field and the
    NCC (N,) of the patterns simulated there against the experimental ones."""

    geometry: MapGeometry
    rotations: Rotation
    field: dsp.DisplacementField
    scores: np.ndarray

    @classmethod
    def measure(cls, problem: _Problem, geometry: MapGeometry, rotations: Rotation) -> _State:
        """The state at *geometry* and *rotations*, from one simulation."""
        fld, scores = problem.compare(geometry, rotations)
        return cls(geometry=geometry, rotations=rotations, field=fld, scores=scores)


@dataclass(frozen=True)
class _PaperState(_State):
    """The paper solver's state: *rotations* are the anchored ones the
    field is measured with, *refined* those kikuchipy refined at
    *geometry* (their mean NCC *ncc*); *disp* is the objective."""

    refined: Rotation
    ncc: float
    disp: float


@dataclass(frozen=True)
class _LoopOutcome:
    """What a loop returns: the final state, one history record per trial
    step, whether it converged and the field at the start."""

    state: _State
    history: list[dict[str, Any]]
    converged: bool
    field_before: dsp.DisplacementField


def _ncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64).reshape(len(a), -1)
    b = np.asarray(b, dtype=np.float64).reshape(len(b), -1)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    return (a * b).sum(axis=1) / np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))


def _rms_displacement(f: dsp.DisplacementField, variances: np.ndarray | None = None) -> float:
    """Weighted RMS of the per-pattern ROI displacements, as a fraction of
    the detector width: the joint solver's objective. Weights are vector
    counts, divided by each pattern's vector variance if given."""
    c = f.counts.astype(np.float64)
    if variances is not None:
        c = c / np.asarray(variances)[:, None]
    if c.sum() == 0:
        return float("nan")
    return float(np.sqrt((c * (f.u**2).sum(axis=-1)).sum() / c.sum()) / f.shape[1])


# --------------------------------------------------------------------- #
# The joint solver
# --------------------------------------------------------------------- #


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
) -> tuple[JointUpdate, np.ndarray]:
    """One joint solve with the geometry *columns* of *linear*; also
    returns the per-pattern variances it weighted with."""
    jg, jr, b = linear
    jg = jg[..., list(columns)]
    # First without the prior, to learn each pattern's noise; then with
    # the weights in inverse pixels squared, the units of the prior
    first = solve_joint(jg, jr, b, _pattern_weights(field, None), damping=damping)
    var = _pattern_variances(field, jg, jr, first)
    w = _pattern_weights(field, var)
    return solve_joint(jg, jr, b, w, prior=prior, offsets=offsets, damping=damping), var


def _step_record(
    it, names, geometry, ncc_before, ncc_after, before, after, damping, accepted, **extra
) -> dict[str, Any]:
    """One entry of :attr:`GeometryRefinementResult.history`."""
    return dict(
        iteration=it,
        parameters=dict(zip(names, map(float, geometry.values(names)))),
        ncc_before=ncc_before,
        ncc_after=ncc_after,
        displacement_before=before,
        displacement_after=after,
        damping=damping,
        accepted=accepted,
        **extra,
    )


def _prior_per_axis(prior: float | None) -> float | None:
    """The RMS orientation error *prior* (degrees, of the rotation angle)
    as an RMS per rotation-vector axis in radians, the solve's unit."""
    return None if prior is None else np.deg2rad(prior) / np.sqrt(3)


@dataclass(frozen=True)
class _JointCarry:
    """What the joint loop carries from one iteration to the next.

    Attributes
    ----------
    state
        The current state.
    damping
        The Levenberg-Marquardt damping the next trial starts with.
    hold
        Whether poorly determined angles still wait for the PC to
        settle: far from the solution the standard
        errors of a small map are not to be trusted (measured: a 4 x 4
        map moved the azimuthal angle by 3.9 deg "at 3.2 sigma", away
        from the truth).
    settled
        Whether the last step was within its standard errors or lowered
        the displacement by less than :data:`MIN_FALL`.
    kept
        Parameters kept at their value in the last iteration (None
        before the first).
    moved
        Parameters that have left their start value. The significance
        rule guards only the start: once a poorly determined parameter
        has taken a significant step, it is refined like any other
        (measured: a tilt that overshot from 0.9 to -0.6 deg off at a
        standard error of 0.24 deg could not come back by a step under
        three standard errors).
    """

    state: _State
    damping: float
    hold: bool = True
    settled: bool = False
    kept: tuple[str, ...] | None = None
    moved: tuple[str, ...] = ()


@dataclass(frozen=True)
class _JointStep:
    """The outcome of one iteration of the joint loop: the carry for the
    next, the history records of its trial steps and why the loop ends, if
    it does: "converged" (settled, nothing left to free), "stalled" (no
    trial step lowered the displacement) or "basin" (the state is in the
    full field's basin)."""

    carry: _JointCarry
    records: tuple[dict[str, Any], ...]
    end: str | None = None


def _choose_free(
    solved: Sequence[str], update: JointUpdate, carry: _JointCarry
) -> tuple[bool, tuple[str, ...], tuple[str, ...], bool]:
    """Split the *solved* parameters, from a solve with all of them, into
    those kept at their value and those free to move; also return whether
    poorly determined parameters are still held and whether one leaves
    its start now.

    A parameter the map determines only poorly leaves its start only by
    a significant step, so that noise cannot walk it around. Far from the
    solution the standard errors of a small map are not to be trusted
    (measured: a 4 x 4 map moved the azimuthal angle by 3.9 deg "at 3.2
    sigma", away from the truth), so poorly determined angles are held
    until the PC has settled. The PC moves from the start however poorly
    it is determined: the RMS judges its steps, and a start 2 % off must
    not be kept because its sigma there is large."""
    se = dict(zip(solved, update.standard_errors))
    step = dict(zip(solved, update.delta))
    poor = [n for n in solved if se[n] > DETERMINACY_LIMITS[n] and n not in carry.moved]
    hold = carry.hold and not carry.settled
    weak = [n for n in poor if n not in _PC] if hold else []
    if not hold or len(weak) == len(solved):
        # Nothing else to settle first: significance alone decides
        hold = False
        weak = [n for n in poor if abs(step[n]) < SIGNIFICANCE * se[n]]
    free = tuple(n for n in solved if n not in weak)
    return hold, tuple(weak), free, any(n in poor for n in free)


def _joint_step(
    problem: _Problem,
    carry: _JointCarry,
    iteration: int,
    prior: float | None,
    report: Callable[[str], None],
    basin: float = 0.0,
) -> _JointStep:
    """One iteration of the joint loop: linearise at the current state,
    choose the free parameters, then up to :data:`MAX_TRIALS` trial
    solves with growing damping until one lowers the displacement; none
    if the state's own RMS displacement is already below *basin*."""
    names = problem.parameters
    solved, split = solved_parameters(names)
    prior_rad = _prior_per_axis(prior)
    state, lam = carry.state, carry.damping
    # Linearise and solve with every parameter: standard errors and steps
    offsets = problem.rotation_offsets(state.rotations)
    linear = _linearise(problem, state.geometry, state.field, solved)
    update, var = _joint_solve(state.field, linear, range(len(solved)), offsets, prior_rad, 0.0)
    hold, weak, free, released = _choose_free(solved, update, carry)
    carry = replace(carry, hold=hold)
    # Settled, and no parameter has become determinable since
    if (carry.settled and weak == carry.kept) or not free:
        # Variants are told apart only near the solution: a wrong one
        # is then re-fitted from its correct variant
        changed = _best_variant_state(problem, state) if free else None
        if changed is None:
            return _JointStep(carry, (), "converged")
        state = changed
        offsets = problem.rotation_offsets(state.rotations)
        linear = _linearise(problem, state.geometry, state.field, solved)
    columns = [solved.index(n) for n in free]
    # Trial solves. Steps are judged by the objective of the solve: each
    # pattern weighted by its own precision, so one failed pattern cannot
    # veto a step
    before = _rms_displacement(state.field, var)
    if before < basin:
        # Weighted with this state's own fit, the last step's result is
        # in the basin already (measured: 0.40 % of the width with the
        # weights before the step, 0.23 % with its own; one more DIC step
        # and measurement moved it to 0.22 %)
        return _JointStep(carry, (), "basin")
    ncc_before = float(np.mean(state.scores))
    records = []
    for _ in range(MAX_TRIALS):
        update, _ = _joint_solve(state.field, linear, columns, offsets, prior_rad, lam)
        delta = _expand(dict(zip(free, update.delta)), split)
        trial = _State.measure(
            problem,
            state.geometry.updated(delta),
            state.rotations * rotations_from_vectors(update.rotations),
        )
        after = _rms_displacement(trial.field, var)
        accepted = bool(after < before) or (
            after < (1 + MIN_FALL) * before
            and _consistent(
                problem,
                trial.geometry,
                trial.field,
                free,
                problem.rotation_offsets(trial.rotations),
                prior_rad,
            )
        )
        ncc = float(np.mean(trial.scores)) if accepted else float("nan")
        records.append(
            _step_record(
                iteration,
                names,
                trial.geometry,
                ncc_before,
                ncc,
                before,
                after,
                lam,
                accepted,
                standard_errors=dict(zip(free, map(float, update.standard_errors))),
                kept=weak,
            )
        )
        report(
            f"  iteration {iteration}: RMS displacement {100 * before:.4f} -> "
            f"{100 * after:.4f} % of width, NCC {ncc_before:.4f} -> {ncc:.4f}, "
            f"{'accepted' if accepted else 'rejected'}"
            + (f" (kept: {', '.join(weak)})" if weak else "")
        )
        if accepted:
            # A step that takes a poorly determined parameter off its
            # start is followed by at least one more, which may correct it
            settled = not released and (_within_errors(update) or 1 - after / before < MIN_FALL)
            moved = tuple(n for n in solved if n in carry.moved or n in free)
            return _JointStep(
                _JointCarry(trial, lam / DAMPING_FACTOR, hold, settled, weak, moved),
                tuple(records),
            )
        lam = max(DAMPING_FACTOR * lam, MIN_RETRY_DAMPING)
    return _JointStep(
        _JointCarry(state, lam, hold, False, weak, carry.moved), tuple(records), "stalled"
    )


def _joint_loop(
    problem: _Problem,
    geometry0: MapGeometry,
    prior: float | None,
    damping: float,
    max_iterations: int,
    progress: _Progress,
    basin: float = 0.0,
) -> _LoopOutcome:
    """The joint refinement from *geometry0* and the starting orientations:
    :func:`_joint_step` until it converges or stalls, or for
    *max_iterations*, or until the RMS displacement after a step is below
    *basin* (a fraction of the width)."""
    start = _State.measure(problem, geometry0, problem.start_rotations)
    carry = _JointCarry(start, damping)
    history: list[dict[str, Any]] = []
    converged = False
    for it in range(max_iterations):
        step = _joint_step(problem, carry, it, prior, progress.write, basin)
        carry = step.carry
        history.extend(step.records)
        progress.advance(history[-1] if step.records else None)
        if step.end == "converged":
            converged = True
            break
        last = step.records[-1] if step.records else {}
        if step.end == "basin" or (last.get("accepted") and last["displacement_after"] < basin):
            # In the full field's basin; the variants, told apart only
            # this close, are chosen before it takes over
            changed = _best_variant_state(problem, carry.state)
            if changed is None:
                converged = True
                break
            carry = replace(carry, state=changed)
        if step.end == "stalled":
            # Nothing lowers the displacement any more: the measurement's
            # floor, if an earlier step got there
            converged = any(h["accepted"] for h in history)
            break
    else:
        converged = carry.settled
    return _LoopOutcome(carry.state, history, converged, start.field)


def _best_variant_state(problem: _Problem, state: _State) -> _State | None:
    """The state measured again with each point's best variant
    (:meth:`_Problem.best_variants`), or None if no point changes."""
    rot = problem.best_variants(state.geometry, state.rotations)
    if np.array_equal(rot.data, state.rotations.data):
        return None
    return _State.measure(problem, state.geometry, rot)


def _consistent(problem, geometry, field, free, offsets, prior) -> bool:
    """Whether, from *geometry*, no parameter in *free* would move by a
    significant step.

    Near the solution a step in a poorly determined parameter changes the
    RMS displacement by less than re-measuring it does (other features
    are found in each simulation; measured on a 10 x 10 map: a step of
    five standard errors that brought both angles to the truth raised the
    RMS by 0.3 %), so such a step is judged by where it lands instead.
    """
    linear = _linearise(problem, geometry, field, free)
    update, _ = _joint_solve(field, linear, range(len(free)), offsets, prior, 0.0)
    se = np.where(np.isfinite(update.standard_errors), update.standard_errors, np.inf)
    return bool(np.all(np.abs(update.delta) < SIGNIFICANCE * se))


def _within_errors(update: JointUpdate) -> bool:
    se = update.standard_errors
    return bool(np.all(np.abs(update.delta) <= np.where(np.isfinite(se), se, np.inf)))


# --------------------------------------------------------------------- #
# The paper's solver
# --------------------------------------------------------------------- #


def _anchor(problem: _Problem, rotations: Rotation) -> Rotation:
    """Remove the mean deviation of *rotations* from the start: the paper
    solver measures the angles against the starting orientations."""
    _, dq = problem.variants(rotations)
    # Far-off points (another variant not among the operators, or a
    # failed refinement) are not small deviations
    small = dq.angle < np.deg2rad(ANCHOR_MAX_ANGLE)
    if not small.any():
        return rotations
    mean = rotation_vectors(dq)[small].mean(axis=0)
    return rotations * ~rotations_from_vectors(mean)


def _paper_state(problem: _Problem, geometry, rotations, refined, scores) -> _PaperState:
    """The paper solver's state at *geometry*: the field measured with
    *rotations*, the NCC of the kikuchipy-*refined* orientations."""
    fld = problem.measure(geometry, rotations)
    return _PaperState(
        geometry=geometry,
        rotations=rotations,
        field=fld,
        scores=scores,
        refined=refined,
        ncc=float(np.mean(scores)),
        disp=fld.mean_displacement,
    )


def _paper_loop(
    problem: _Problem,
    geometry0: MapGeometry,
    jacobian: str,
    damping: float,
    max_iterations: int,
    ncc_tolerance: float,
    progress: _Progress,
) -> _LoopOutcome:
    """The paper's loop (Fig. 4): average field, Eqs. 8-11, kikuchipy
    orientation refinement and NCC acceptance; see the module notes."""
    names = problem.parameters
    rotations0 = problem.start_rotations
    rot_ref, scores = problem.refine_orientations(geometry0, rotations0)
    # The first field uses the starting orientations themselves, as the
    # paper does: orientations refined at a far-off start absorb much of
    # a large geometry error (measured: a 6 % start read as 1.4 %), and
    # the loop then converges to a wrong geometry
    state = _paper_state(problem, geometry0, rotations0, rot_ref, scores)
    field_before = state.field
    history, converged, gain = [], False, np.inf
    for it in range(max_iterations):
        jac = problem.jacobian(state.geometry, state.rotations, state.field, jacobian)
        lam = damping
        step_taken = False
        for _ in range(MAX_TRIALS):
            update = solve_update(jac, state.field.residual, state.field.weights, lam)
            geo = state.geometry.updated(dict(zip(names, update.delta)))
            # Judge the step first by the displacement with the current
            # orientations (a simulation and a DIC pass); only a step that
            # lowers it pays for orientation refinement
            disp = problem.measure(geo, state.rotations).mean_displacement
            ncc = float("nan")
            accepted = bool(disp < state.disp)
            if accepted:
                rot_ref, scores = problem.refine_orientations(geo, state.rotations)
                ncc = float(np.mean(scores))
                accepted = bool(ncc > state.ncc - ncc_tolerance)
            history.append(
                _step_record(it, names, geo, state.ncc, ncc, state.disp, disp, lam, accepted)
            )
            progress.write(
                f"  iteration {it}: NCC {state.ncc:.4f} -> {ncc:.4f}, displacement "
                f"{100 * state.disp:.3f} -> {100 * disp:.3f} % of width, "
                f"{'accepted' if accepted else 'rejected'}"
            )
            if accepted:
                gain = ncc - state.ncc
                fall = 1 - disp / state.disp
                state = _paper_state(problem, geo, _anchor(problem, rot_ref), rot_ref, scores)
                step_taken = True
                break
            lam *= DAMPING_FACTOR
        progress.advance(history[-1])
        if not step_taken:
            # No step lowers the displacement any more: converged if the
            # NCC had stopped gaining too (the paper's criterion)
            converged = any(h["accepted"] for h in history) and gain < ncc_tolerance
            break
        if gain < ncc_tolerance and fall < PAPER_MIN_FALL:
            converged = True
            break
    # The orientations refined at the final geometry, not anchored: the
    # best estimate of each orientation given the calibrated geometry
    state = replace(state, rotations=state.refined)
    return _LoopOutcome(state, history, converged, field_before)


# --------------------------------------------------------------------- #
# Progress
# --------------------------------------------------------------------- #


def _show_progressbar(show_progressbar: bool | None) -> bool:
    """*show_progressbar*, or HyperSpy's preference if None (kikuchipy's
    convention)."""
    if show_progressbar is None:
        return bool(hs.preferences.General.show_progressbar)
    return bool(show_progressbar)


class _Progress:
    """What the user sees while a loop runs, if *show*: *header* and one
    line per trial step printed to stdout, and a tqdm bar over the
    iterations on stderr with the current RMS displacement and NCC.

    The lines are printed as kikuchipy prints its refinement information
    next to its progress bars (:meth:`~kikuchipy.signals.EBSD.refine_orientation`
    prints; kikuchipy logs only debug messages); ``tqdm.write`` keeps them
    above the bar.
    """

    def __init__(self, show: bool, total: int, header: str):
        self.show = show
        self._bar = None
        if show:
            print(header)
            self._bar = tqdm(total=total, desc="Geometry refinement", unit="iteration")

    def write(self, line: str) -> None:
        if self.show:
            tqdm.write(line, file=sys.stdout)

    def advance(self, record: Mapping[str, Any] | None = None) -> None:
        """One iteration done; *record* is the history record of its last
        trial step."""
        if self._bar is None:
            return
        if record is not None:
            self._bar.set_postfix(
                rms=f"{100 * record['displacement_after']:.4f} %",
                ncc=f"{record['ncc_after']:.4f}",
                refresh=False,
            )
        self._bar.update()

    def __enter__(self) -> _Progress:
        return self

    def __exit__(self, exc_type, *exc) -> bool:
        if self._bar is not None:
            if exc_type is None:
                # Converged before max_iterations: a full bar
                self._bar.total = self._bar.n
            self._bar.close()
        return False


# The function
# --------------------------------------------------------------------- #


def refine_geometry_dic(
    signal: EBSD,
    xmap: CrystalMap,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern,
    energy: float,
    *,
    parameters: Sequence[str] = DEFAULT_PARAMETERS,
    points: int | np.ndarray = 100,
    solver: str = "joint",
    orientation_prior: float | None = None,
    pseudo_symmetry_ops: Rotation | None = None,
    steps: Mapping[str, float] | None = None,
    rois: tuple[int, int] = (8, 8),
    binning: int | None = None,
    dic: str = "auto",
    jacobian: str = "analytic",
    damping: float | None = None,
    max_iterations: int = 10,
    ncc_tolerance: float = 0.005,
    refine_kwargs: Mapping[str, Any] | None = None,
    dic_kwargs: Mapping[str, Any] | None = None,
    phase: str | int | None = None,
    seed: int | None = 0,
    full_field: bool | None = None,
    show_progressbar: bool | None = None,
) -> GeometryRefinementResult:
    """Refine the global sample-detector geometry of a map by global DIC.

    Parameters
    ----------
    signal
        EBSD map (``EBSD`` or ``LazyEBSD``), 1D or 2D navigation shape,
        navigation axes scaled by the step sizes in micrometres.
    xmap
        Starting orientations for the map (e.g. Hough or dictionary
        indexing at the nominal geometry), of the signal's navigation
        shape. Points not indexed (phase -1, zero or NaN rotations) are
        not used.
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
        their difference is determined and its change is split equally
        (reported in :attr:`GeometryRefinementResult.degenerate`); leave
        one out to keep it fixed.
    points
        Number of calibration points spread evenly over the map, or an
        explicit (N, 2) integer array of (row, column).
    solver
        "joint" (default): every pattern's displacement field is fitted
        with the geometry and one small rotation per pattern, the
        rotations eliminated exactly (Schur complement, see
        :func:`~kikuchipy_geomdic.calibration.solve.solve_joint`), orientations
        updated from the same fields: right whatever common error the
        starting orientations share, as orientations indexed at a wrong
        geometry do. "paper": the paper's algorithm (average field,
        Eqs. 8-11, kikuchipy orientation refinement and NCC acceptance
        in the loop), accurate when the starting orientation errors are
        random and cancel in the average.
    orientation_prior
        Joint solver: RMS error in degrees of the starting orientations,
        believed independent and zero-mean over the points (the paper's
        perturbation study). It adds ``|w_i|^2 / s^2`` per orientation
        (``w_i`` its rotation away from the start, ``s`` the RMS per
        axis) to the fit, which pins the rotation common to all
        orientations, and with it the detector angles, to the start's.
        None (default): the starting orientations say nothing about their
        common rotation, and the angles are seen only through the PC
        field across the map.
    pseudo_symmetry_ops
        Pseudo-symmetry operators (orix ``Rotation``, crystal frame, left
        factors ``op * rotation``), e.g.
        ``variant_operators()[1:]`` for BaTiO3. The joint
        solver picks per point the variant whose simulated pattern
        correlates best, before the loop and at the refined geometry; the
        paper solver passes them to kikuchipy.
    steps
        Central-difference step per parameter; defaults in
        :data:`~kikuchipy_geomdic.geometry.DEFAULT_STEPS`.
    rois
        ROI grid (rows, columns) of the displacement field.
    binning
        Pixel binning before feature detection and tracking. Default 1,
        or, when the full-field stage follows, the largest factor that
        keeps patterns of at least :data:`LOOP_MIN_SIZE` px a side: the
        DIC stage then only has to bring the geometry into the full
        field's basin.
    dic
        "auto" (OpenCV if importable, else scikit-image), "opencv" or
        "skimage".
    jacobian
        Paper solver: "analytic" (default: the forward displacement map
        evaluated at the measured feature positions, no simulation) or
        "finite-difference" (the paper's Eqs. 4-5). The joint solver is
        always analytic.
    damping
        Paper solver: lambda of Eq. 10 (default 1e-3). Joint solver: the
        starting Levenberg-Marquardt damping (default 0, Gauss-Newton),
        raised tenfold after a step that does not lower the displacement.
    max_iterations
        Upper bound on geometry updates.
    ncc_tolerance
        Paper solver: NCC gain below which the loop may stop, and NCC
        loss above which a step is rejected.
    refine_kwargs
        Options of kikuchipy's
        :meth:`~kikuchipy.signals.EBSD.refine_orientation` (``method``,
        ``method_kwargs``, ``trust_region``, ...). Joint solver: None
        (default) keeps the orientations of the joint solve, which are
        measured from the same displacement fields as the geometry and
        cost nothing more; a dict (``{}`` for kikuchipy's defaults)
        refines them once more with kikuchipy at full resolution at the
        refined geometry. Paper solver: used in the loop.
    dic_kwargs
        Further options of
        :func:`~kikuchipy_geomdic.patterns.displacement.measure_displacements`
        (``noise``, ``blur``, ``max_roi_crossings``, ...).
    phase
        Phase name or id in *xmap* to calibrate with; required when *xmap*
        has several phases.
    seed
        Seed of the DIC noise.
    full_field
        After the DIC stage, refine the geometry and orientations once
        more by Gauss-Newton on the pixel intensities, every pixel used
        where DIC uses a few hundred features, with a model of what the
        camera and the user did to the patterns (background lobe from the
        signal's ``static_background``, point spread, static and dynamic
        background removal, chosen from the patterns); rotations
        eliminated by the same Schur complement; standard errors
        cluster-robust over the patterns, checked against the DIC stage
        (:attr:`GeometryRefinementResult.adequacy`: raised, with a
        warning, where the two disagree by more than
        :data:`ADEQUACY_LIMIT` combined standard errors). Default: True
        for the joint solver, False for the paper's. The DIC stage then
        ends once the RMS displacement is below :data:`FULL_FIELD_BASIN`.
        By default it is skipped, with a warning, when the DIC stage
        leaves a PC parameter undetermined (standard error above
        :data:`DETERMINACY_LIMITS`): the full field needs a start in its
        basin; True runs it anyway. False: the DIC stage alone, for
        patterns the model does not describe (see the method page).
    show_progressbar
        Whether to show a progress bar over the iterations (tqdm, on
        stderr) and print a header and one line per trial step (stdout).
        If not given, the value of
        :obj:`hyperspy.api.preferences.General.show_progressbar` is used.

    Returns
    -------
    result
        :class:`GeometryRefinementResult` with the geometry, its
        :attr:`~GeometryRefinementResult.standard_errors`, and the
        orientations of the calibration points. The inputs are not
        modified.

    Notes
    -----
    A rotation common to all orientations is exactly a change of the
    detector angles for every single pattern; only the PC field's
    dependence on the angles across the map (weak: it grows with the
    field of view) and a belief about the starting orientations
    (*orientation_prior*) separate them. A parameter whose standard error
    exceeds :data:`DETERMINACY_LIMITS` is moved by the joint solver only
    by a step of :data:`SIGNIFICANCE` standard errors or more, so that
    noise cannot walk it around; the result lists it in
    :attr:`~GeometryRefinementResult.undetermined`, with its standard
    error.

    Examples
    --------
    >>> from kikuchipy_geomdic import refine_geometry_dic
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> sm = synthetic.synthetic_map("Si", (5, 5), shape=(60, 60), seed=0)
    >>> res = refine_geometry_dic(
    ...     sm.signal, sm.start_xmap, sm.start_detector, sm.master_pattern, 20,
    ...     parameters=["pcx", "pcy", "pcz"], points=25, show_progressbar=False,
    ... )
    >>> res.detector.navigation_shape
    (5, 5)
    >>> abs(res.parameters["pcx"] - sm.geometry.pc[0]) < 3e-4
    True
    """
    show = _show_progressbar(show_progressbar)
    names = _check_options(parameters, solver, jacobian, orientation_prior)
    nav = navigation_shape(signal)
    phase_id = _check_inputs(signal, xmap, detector, master_pattern, phase, nav)
    # Left at its default, the full field runs only where the DIC stage
    # has brought the geometry into its basin; True forces it
    guarded = full_field is None
    if full_field is None:
        full_field = solver == "joint"
    dic_kw = dict(rois=tuple(rois), binning=binning, dic=dic, seed=seed)
    dic_kw.update(dic_kwargs or {})
    if dic_kw["binning"] is None:
        dic_kw["binning"] = 1 if not full_field else _binning(signal.axes_manager.signal_shape)
    problem = _prepare_problem(
        signal,
        xmap,
        master_pattern,
        energy,
        names,
        points,
        phase_id,
        nav,
        steps,
        dic_kw,
        refine_kwargs,
        pseudo_symmetry_ops,
    )
    geometry0 = MapGeometry.from_detector(detector, _step_sizes(signal), nav)
    header = (
        f"Refining the geometry ({solver} solver) with {len(problem.points)} calibration "
        f"points: {', '.join(names)}"
    )

    def dic_stage(problem, progress, basin):
        if solver == "joint":
            return _joint_loop(
                problem,
                geometry0,
                orientation_prior,
                0.0 if damping is None else damping,
                max_iterations,
                progress,
                basin,
            )
        return _paper_loop(
            problem,
            geometry0,
            jacobian,
            PAPER_DAMPING if damping is None else damping,
            max_iterations,
            ncc_tolerance,
            progress,
        )

    with _Progress(show, max_iterations, header) as progress:
        outcome = dic_stage(problem, progress, FULL_FIELD_BASIN if full_field else 0.0)
        standard_errors = _standard_errors(problem, outcome.state, orientation_prior)
        loose = [n for n in _PC if standard_errors.get(n, 0) > DETERMINACY_LIMITS[n]]
        if guarded and full_field and loose:
            # The full field needs a start in its basin, which a PC the
            # DIC stage leaves undetermined is not (measured: at 0.3
            # counts/px it converged 2.9e-3 off at 9.7 of its standard
            # errors, where the DIC stage's own errors covered its error)
            warnings.warn(
                f"The full-field stage was skipped: the DIC stage left {', '.join(loose)} "
                f"undetermined (standard errors above {DETERMINACY_LIMITS[loose[0]]:g}); "
                "the patterns are too noisy or too few for the geometry",
                UserWarning,
                stacklevel=2,
            )
            full_field = False
            if binning is None and problem.dic_kwargs["binning"] > 1:
                # The DIC stage alone, as full_field=False runs it: at full
                # resolution (binned, at 0.3 counts/px, it ended 9.6e-3
                # off at 4.8 standard errors)
                problem = replace(problem, dic_kwargs={**problem.dic_kwargs, "binning": 1})
                outcome = dic_stage(problem, progress, 0.0)
                standard_errors = None
        adequacy = {}
        if full_field:
            ff = _full_field(
                problem,
                outcome.state,
                orientation_prior,
                1 + max((h["iteration"] for h in outcome.history), default=-1),
                progress.write,
            )
            state = _State.measure(problem, ff.geometry, ff.rotations)
            adequacy = _adequacy(problem, ff, _dic_update(problem, state, orientation_prior))
            progress.write(f"  {adequacy['verdict']}")
            if not adequacy["consistent"]:
                warnings.warn(adequacy["verdict"], UserWarning, stacklevel=2)
            outcome = replace(outcome, state=state, history=outcome.history + ff.history)
            standard_errors = _inflated(ff.standard_errors, adequacy)
    rotations, scores = _final_orientations(problem, outcome.state, solver, refine_kwargs)
    return _build_result(
        problem,
        outcome,
        rotations,
        scores,
        detector,
        signal,
        nav,
        geometry0,
        orientation_prior,
        solver,
        standard_errors,
        adequacy,
    )


# --------------------------------------------------------------------- #
# The full-field stage
# --------------------------------------------------------------------- #


@dataclass(frozen=True)
class _FullField:
    """What the full-field stage returns: the geometry and orientations it
    reached, its standard errors, one record per step and the (solved)
    parameters it held."""

    geometry: MapGeometry
    rotations: Rotation
    standard_errors: dict[str, float]
    history: list[dict[str, Any]]
    held: tuple[str, ...] = ()


def _gaussian_matrix(n: int, sigma: float) -> np.ndarray:
    """The (n, n) matrix of a 1D Gaussian filter of *sigma* px with
    edge-replicating borders (scipy's ``mode="nearest"``)."""
    if sigma <= 0:
        return np.eye(n)
    return ndimage.gaussian_filter1d(np.eye(n), sigma, axis=0, mode="nearest")


@functools.lru_cache(maxsize=16)
def _lowpass_factors(n: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Low-rank factors ``A @ B`` of the (n, n) Gaussian low-pass matrix:
    at a sigma of an eighth of the width, 13 of 96 singular values are
    above 1e-4, so thin products replace square ones."""
    u, sv, vt = np.linalg.svd(_gaussian_matrix(n, sigma))
    k = int((sv > LOWPASS_RANK_TOLERANCE * sv[0]).sum())
    return u[:, :k], sv[:k, None] * vt[:k]


@dataclass(frozen=True)
class _Processing:
    """The full field's model of how the compared patterns were made from
    the simulation ``S``, as a camera records and a user processes them:

    1. ``x = L * (1 + contrast * K)``: ``K`` the pattern standardised, a
       Kikuchi *contrast* on the background *lobe* ``L`` (the smoothed
       static background; flat when unknown);
    2. the detector's point spread, a Gaussian of *psf* px, acting on the
       product: blurring a pattern on a sloping background moves its
       features down the slope, a magnification about the lobe's peak
       that pcz absorbs (measured: 1e-4 on 96 px Ni patterns with a blur
       of 0.6 px);
    3. static background removal: divided by the blurred lobe, and with
       *ghost* by the map's mean pattern, bands and all (kikuchipy's
       static background removal with the map's own mean holds bands on a
       map of few grains);
    4. dynamic background removal: divided by its Gaussian low-pass of
       *highpass* px (0: none).

    A *contrast* of 0 is the limit of a faint pattern, where the
    divisions become subtractions. Every step is differentiable, so
    Jacobian columns go through it with the pattern. Fitted as
    ``a * S + b`` instead (the model family of
    ``degrade_patterns``), processed Ni patterns moved pcz by 5
    standard errors."""

    shape: tuple[int, int]
    psf: float = 0.0
    highpass: float = 0.0
    contrast: float = 0.0
    ghost: bool = False
    lobe: np.ndarray | None = field(default=None, compare=False, repr=False)

    @cached_property
    def _lowpass_factors(self) -> tuple[np.ndarray, ...]:
        (ar, br), (ac, bc) = (_lowpass_factors(n, self.highpass) for n in self.shape)
        # Columns act from the right, transposed; all contiguous (BLAS was
        # 40x slower with a transposed view)
        return tuple(np.ascontiguousarray(m) for m in (ar, br, bc.T, ac.T))

    def _planes(self, a: np.ndarray, dtype=np.float64) -> np.ndarray:
        # (N, P, K) -> contiguous pattern planes (N, K, rows, columns):
        # matmul over strided ones was 100x slower
        n, k = a.shape[0], int(np.prod(a.shape[2:], dtype=int))
        planes = np.moveaxis(a.reshape((n,) + self.shape + (k,)), 3, 1)
        return np.ascontiguousarray(planes, dtype=dtype)

    def _flat(self, planes: np.ndarray, shape) -> np.ndarray:
        return np.ascontiguousarray(np.moveaxis(planes, 1, 3), dtype=np.float64).reshape(shape)

    def _lowpass(self, planes: np.ndarray) -> np.ndarray:
        ar, br, bct, act = (m.astype(planes.dtype, copy=False) for m in self._lowpass_factors)
        return ar @ (br @ planes @ bct) @ act

    def _blur(self, planes: np.ndarray) -> np.ndarray:
        if self.psf < PSF_NEGLIGIBLE:
            return planes
        return ndimage.gaussian_filter(planes, (0, 0, self.psf, self.psf), mode="nearest")

    def __call__(
        self, s0: np.ndarray, columns: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The model patterns (N, P) of simulated ones *s0*, and their
        derivatives (N, P, K) from those of *s0*, *columns* (processed in
        float32: a dozen passes over them were the full field's largest
        cost; the patterns stay float64)."""
        n, p = s0.shape
        x = self._planes(s0[..., None])
        d = None if columns is None else self._planes(columns, np.float32)
        axes = (2, 3)
        x = x - x.mean(axis=axes, keepdims=True)
        sd = np.sqrt((x**2).mean(axis=axes, keepdims=True))
        x = x / sd

        def f32(a):
            return np.asarray(a, dtype=np.float32)

        if d is not None:
            d = d - d.mean(axis=axes, keepdims=True)
            d = (d - f32(x) * (f32(x) * d).mean(axis=axes, keepdims=True)) / f32(sd)
        lobe = 1.0 if self.lobe is None else self.lobe
        c = self.contrast
        if c:
            # Step 1 and 2 in counts; 3: the static background divided out
            raw = lobe * (1 + c * x)
            den = raw.mean(axis=0, keepdims=True) if self.ghost else lobe
            den = self._blur(den * np.ones((1, 1) + self.shape))
            x = self._blur(raw) / den
            if d is not None:
                d = self._blur(f32(c * lobe) * d) / f32(den)
            if self.highpass:
                low = self._lowpass(x)
                x = x / low
                if d is not None:
                    d = (d - f32(x) * self._lowpass(d)) / f32(low)
        else:
            # The faint-pattern limit of the same: the background's blur
            # divided out of the blurred modulation, the ghost subtracted
            blurred_lobe = self._blur(lobe * np.ones((1, 1) + self.shape))
            x = self._blur(lobe * x) / blurred_lobe
            if d is not None:
                d = self._blur(f32(lobe) * d) / f32(blurred_lobe)
            if self.ghost:
                x = x - x.mean(axis=0, keepdims=True)
            if self.highpass:
                x = x - self._lowpass(x)
                if d is not None:
                    d = d - self._lowpass(d)
        return self._flat(x, (n, p)), None if d is None else self._flat(d, columns.shape)


#: Singular values of the low-pass matrices kept, relative to the largest.
LOWPASS_RANK_TOLERANCE = 1e-4

#: High-passes (fractions of the pattern width) the full field tries as
#: the model of the user's dynamic background removal (kikuchipy's
#: default: a width / 8), keeping the one whose model correlates best
#: with the patterns; 0: none.
HIGHPASS_GRID = (0.0, 1 / 12, 1 / 8, 1 / 6)

#: Patterns (at most) on which the full field chooses its high-pass and
#: point spread.
ESTIMATION_PATTERNS = 40

#: Kikuchi contrasts (relative to the background) the full field tries.
CONTRAST_GRID = (0.0, 0.05, 0.1, 0.15, 0.2, 0.3)


def _processed_ncc(e, s0, processing):
    return float((ori.standardise(processing(s0)[0]) * e).mean())


def _estimate_processing(problem, arrays, geometry, rotations) -> _Processing:
    """The model of what was done to the patterns (:class:`_Processing`)
    that correlates best with them, one property after the other: the
    high-pass (:data:`HIGHPASS_GRID`), the point spread (px; unmodelled,
    a blur of 0.6 px moved pcz by 11 standard errors, band widths being
    what pcz scales), whether the map's mean was divided out, the
    contrast (:data:`CONTRAST_GRID`)."""
    n = len(problem.points)
    shape = tuple(problem.experimental.shape[1:])
    e = ori.standardise(problem.experimental.reshape(n, -1).astype(np.float64))
    s0 = ori.project_patterns(rotations, geometry.detector(problem.points), arrays).reshape(n, -1)
    # The high-pass and the point spread, properties of each pattern, on
    # every k-th pattern; the ghost and the contrast on all of them (on 50
    # of 121 the map's mean pattern was not found)
    few = np.unique(np.linspace(0, n - 1, min(n, ESTIMATION_PATTERNS)).astype(int))

    def best(candidates, pick=slice(None)):
        return max(candidates, key=lambda proc: _processed_ncc(e[pick], s0[pick], proc))

    proc = best(
        (_Processing(shape, 2 * PSF_STEP, h * shape[1], lobe=problem.lobe) for h in HIGHPASS_GRID),
        few,
    )
    sigmas = np.arange(0.0, PSF_MAX + 1e-9, PSF_STEP)
    ncc = []
    for sg in sigmas:
        ncc.append(_processed_ncc(e[few], s0[few], replace(proc, psf=sg)))
        # Past the peak twice in a row: the rest of the grid cannot win
        if len(ncc) > 2 and ncc[-1] < ncc[-2] < max(ncc):
            break
    sigmas = sigmas[: len(ncc)]
    k = int(np.argmax(ncc))
    psf = float(sigmas[k])
    if 0 < k < len(sigmas) - 1:
        # Vertex of the parabola through the best and its neighbours
        a, b, c = ncc[k - 1], ncc[k], ncc[k + 1]
        den = a - 2 * b + c
        if den < 0:
            psf = float(sigmas[k] + PSF_STEP * 0.5 * (a - c) / den)
    proc = replace(proc, psf=psf)
    proc = best(replace(proc, ghost=g) for g in (False, True))
    return best(replace(proc, contrast=c) for c in CONTRAST_GRID)


@nb.njit(cache=True, nogil=True)
def _project_out(a, unit):
    """*a* (N, P, K) with each pattern's constant and *unit* (N, P)
    direction removed from every column, in two passes over the pixels
    (numpy's broadcasting made five and was the full field's largest
    cost)."""
    n, p, k = a.shape
    out = np.empty_like(a)
    for i in range(n):
        mean = np.zeros(k)
        along = np.zeros(k)
        for j in range(p):
            for c in range(k):
                mean[c] += a[i, j, c]
                along[c] += unit[i, j] * a[i, j, c]
        mean /= p
        # unit sums to zero, so the dot product needs no centring
        for j in range(p):
            for c in range(k):
                out[i, j, c] = a[i, j, c] - mean[c] - unit[i, j] * along[c]
    return out


def _intensity_system(problem, arrays, geometry, rotations, solved, processing, jacobians=True):
    """Residuals (N, P), geometry and rotation Jacobians with each
    pattern's gain and offset eliminated, and the pixel noise variances
    (N, P); the model made by *processing*. Without *jacobians*, only the
    residuals (the Jacobians None)."""
    n = len(problem.points)
    e = problem.experimental.reshape(n, -1).astype(np.float64)
    if jacobians:
        s0, jg, jr = intensity_jacobian(
            geometry, problem.points, rotations, arrays, solved, INTENSITY_STEPS
        )
        k = jg.shape[2]
        s0, cols = processing(s0, np.concatenate([jg, jr], axis=2))
        jg, jr = cols[..., :k], cols[..., k:]
    else:
        s0 = processing(problem.simulate(geometry, rotations).reshape(n, -1))[0]
    # Gain and offset of each pattern, then projected out of every column:
    # exactly their elimination (variable projection). The two basis
    # vectors, the constant and the centred model, are orthogonal: the
    # projection is a centring and one dot product per column
    sc = s0 - s0.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(sc, axis=1)
    unit = sc / norm[:, None]
    ec = e - e.mean(axis=1, keepdims=True)
    gain = (unit * ec).sum(axis=1) / norm

    def reduce(a):
        flat = np.ascontiguousarray(a.reshape(n, a.shape[1], -1))
        return _project_out(flat, unit).reshape(a.shape)

    residual = -reduce(e[..., None])[..., 0]  # model minus data, fitted gain and offset
    if jacobians:
        jg = reduce(gain[:, None, None] * jg)
        jr = reduce(gain[:, None, None] * jr)
    else:
        jg = jr = None
    return residual, jg, jr, _pixel_variances(residual, e + residual)


def _pixel_variances(residual: np.ndarray, model: np.ndarray) -> np.ndarray:
    """Noise variances (N, P) of the pixels, ``c0 + c1 * model`` fitted
    per pattern to the squared residuals: shot noise grows with the
    intensity, so bright bands are noisier than the background between
    them (measured at real-Ni noise: with one variance per pattern the
    errors were 1.3-1.6x the white-noise bound). Each pixel weighs at
    most 1 / :data:`MIN_PIXEL_VARIANCE` times its pattern's mean: at 0.1 one
    pattern's pcz score inflated the cluster-robust error twofold."""
    r2 = residual**2
    m = model - model.mean(axis=1, keepdims=True)
    slope = (m * r2).sum(axis=1) / (m**2).sum(axis=1)
    var = r2.mean(axis=1, keepdims=True) + np.clip(slope, 0, None)[:, None] * m
    # A variance model is no licence for a pixel to weigh without bound
    return np.maximum(var, MIN_PIXEL_VARIANCE * r2.mean(axis=1, keepdims=True))


def _full_field(problem, state, prior, first_it, report) -> _FullField:
    """Gauss-Newton on the pixel intensities from where the DIC stage
    converged: the geometry and one rotation per pattern, the rotations
    eliminated by the Schur complement of :func:`solve_joint`, each
    pattern's gain and offset projected out, each pixel weighted by the
    inverse of its noise variance (:func:`_pixel_variances`), the model
    made as the patterns were (:class:`_Processing`, estimated from them).

    Parameters the full field determines poorly (standard error above
    :data:`DETERMINACY_LIMITS`) follow the DIC stage's rule: they keep
    their value unless the full field moved them by :data:`SIGNIFICANCE`
    standard errors or more; if not, they are put back (:func:`_hold`)
    (measured on processed Ni maps: free, the tilt moved 1.3 deg away from
    the truth on a standard error of 0.5 deg). The move is judged after
    convergence: a first step fell short of three standard errors where
    the whole move did not (a tilt 0.4 deg off, 0.29 +- 0.10 deg). The
    result is checked against the DIC stage afterwards (:func:`_adequacy`).
    """
    names = problem.parameters
    solved, split = solved_parameters(names)
    start = state.geometry
    processing = _estimate_processing(problem, problem.arrays, start, state.rotations)
    history = []
    geometry, rotations, cov, system = _gauss_newton(
        problem,
        state,
        solved,
        split,
        (),
        processing,
        prior,
        first_it,
        history,
        report,
    )
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    moved = _solved_values(geometry, solved, split) - _solved_values(start, solved, split)
    held = tuple(
        nm
        for nm, sg, d in zip(solved, se, moved)
        if nm not in _PC and sg > DETERMINACY_LIMITS[nm] and abs(d) < SIGNIFICANCE * sg
    )
    if held and system is not None:
        geometry, rotations, cov = _hold(system, held, start, solved, split, prior, cov)
    se = dict(zip(solved, map(float, np.sqrt(np.clip(np.diag(cov), 0, None)))))
    if "tilt" in names or "sample_tilt" in names:
        se[TILT_DIFFERENCE] = se["tilt" if "tilt" in solved else "sample_tilt"]
    for name, base in split.items():
        se[name] = se[base] = float("inf")
    se = {k: se[k] for k in (*names, TILT_DIFFERENCE) if k in se}
    return _FullField(geometry, rotations, se, history, held)


@dataclass(frozen=True)
class _System:
    """The full field's linear system at a geometry and orientations:
    residuals (model minus data), geometry and rotation Jacobians with the
    nuisances eliminated, pixel weights and the rotation offsets."""

    geometry: MapGeometry
    rotations: Rotation
    residual: np.ndarray
    jg: np.ndarray
    jr: np.ndarray
    weights: np.ndarray
    offsets: Any


def _hold(system: _System, held, start: MapGeometry, solved, split, prior, cov):
    """The geometry, orientations and covariance with the *held*
    parameters put back to their values in *start*: the constrained
    least-squares step of the converged linear *system*, the orientations
    taking back what they had absorbed of the held parameters' moves. No
    new simulation: a second Gauss-Newton pass from the DIC stage's state
    with them held reached the same PC within 1.1e-5 (an eighth of a
    standard error) on two processed Ni maps."""
    idx = [i for i, nm in enumerate(solved) if nm in held]
    free = [i for i, nm in enumerate(solved) if nm not in held]
    back = (
        _solved_values(start, solved, split)[idx]
        - _solved_values(system.geometry, solved, split)[idx]
    )
    # The residual the linear model predicts once they are put back
    residual = system.residual + system.jg[..., idx] @ back
    upd = solve_joint(
        system.jg[..., free],
        system.jr,
        residual,
        system.weights,
        prior=_prior_per_axis(prior),
        offsets=system.offsets,
    )
    delta = {solved[i]: float(d) for i, d in zip(free, upd.delta)}
    delta.update({solved[i]: float(b) for i, b in zip(idx, back)})
    geometry = system.geometry.updated(_expand(delta, split))
    rotations = system.rotations * rotations_from_vectors(upd.rotations)
    out = cov.copy()
    out[np.ix_(free, free)] = upd.covariance
    out[np.ix_(free, idx)] = out[np.ix_(idx, free)] = 0.0
    return geometry, rotations, out


def _gauss_newton(
    problem, state, solved, split, held, processing, prior, first_it, history, report
):
    """The full field's iterations from *state* with the parameters *held*
    fixed; returns the geometry, the rotations and the covariance of all
    *solved* parameters (cluster-robust over the patterns) at the end,
    and the last linear :class:`_System`."""
    arrays = problem.arrays
    prior_rad = _prior_per_axis(prior)
    geometry, rotations = state.geometry, state.rotations
    free = [i for i, nm in enumerate(solved) if nm not in held]
    chi2_prev, weights, last, cov, system = np.inf, None, None, None, None
    chi2_before = np.inf
    for it in range(FULL_FIELD_ITERATIONS):
        # The Jacobians of the first step serve the next steps (in the
        # basin they hardly change; building them is most of the cost):
        # those simulate the patterns only, unless the last step lowered
        # chi2 by a large fraction (far from the solution, as after a
        # change of variants, the first Jacobians converged slowly)
        refresh = it == 0 or chi2_before - chi2_prev > JACOBIAN_REFRESH * chi2_before
        residual, j_geo, j_rot, var = _intensity_system(
            problem, arrays, geometry, rotations, solved, processing, jacobians=refresh
        )
        if refresh:
            jg, jr = j_geo, j_rot
        if weights is None:
            # Weights fixed at the first step, so that chi2 compares steps
            weights = 1 / var
        offsets = problem.rotation_offsets(rotations)
        full = solve_joint(jg, jr, residual, weights, prior=prior_rad, offsets=offsets)
        if full.chi2 > chi2_prev:
            # The last step went uphill: undo it and stop
            history[-1]["accepted"] = False
            geometry, rotations = last
            break
        system = _System(geometry, rotations, residual, jg, jr, weights, offsets)
        # Cluster-robust over the patterns, as the DIC stage's: pixels of
        # a pattern share its misfit (blur, interpolation), which the
        # white-noise model the bound is made of misses (measured: 2-3 %
        # larger on 121 Ni patterns, and one azimuthal error at 3.0 model
        # standard errors over nine maps)
        cov = full.covariance
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        if not free:
            break
        upd = full
        if len(free) < len(solved):
            upd = solve_joint(
                jg[..., free], jr, residual, weights, prior=prior_rad, offsets=offsets
            )
        delta = dict(zip([solved[i] for i in free], map(float, upd.delta)))
        chi2_before, chi2_prev, last = chi2_prev, full.chi2, (geometry, rotations)
        geometry = geometry.updated(_expand(delta, split))
        rotations = rotations * rotations_from_vectors(upd.rotations)
        history.append(
            _step_record(
                first_it + it,
                problem.parameters,
                geometry,
                np.nan,
                np.nan,
                np.nan,
                np.nan,
                0.0,
                True,
                stage="full-field",
                chi2=float(full.chi2),
            )  # fmt: skip
        )
        report(
            f"  iteration {first_it + it} (full field): chi2 {full.chi2:.6g}, "
            f"point spread {processing.psf:.2f} px, high-pass {processing.highpass:.1f} px, "
            f"contrast {processing.contrast:g}, ghost {processing.ghost}"
            + (f", held {', '.join(held)}" if held else "")
        )
        # Steps this small leave the covariance as it was; the
        # orientations, refined here too, must have settled as well (with
        # the first step's Jacobians they converge more slowly: a
        # noise-free BaTiO3 map ended 0.052 deg off on average, at 0.05)
        rotation_step = np.rad2deg(np.sqrt((upd.rotations**2).sum(axis=-1)).max())
        if rotation_step <= FULL_FIELD_ROTATION_STOP and all(
            abs(delta[solved[i]]) <= FULL_FIELD_STOP * se[i] for i in free
        ):
            break
    return geometry, rotations, cov, system


# --------------------------------------------------------------------- #
# The result builder
# --------------------------------------------------------------------- #


def _final_orientations(
    problem: _Problem, state: _State, solver: str, refine_kwargs: Mapping[str, Any] | None
) -> tuple[Rotation, np.ndarray]:
    """The final orientations and their NCC: the loop's, refined once more
    by kikuchipy at the refined geometry at full resolution if the joint
    solver was given *refine_kwargs* or the paper's loop binned."""
    if solver == "joint":
        again = refine_kwargs is not None
    else:
        again = problem.loop_binning > 1
    if not again:
        return state.rotations, state.scores
    return problem.refine_orientations(state.geometry, state.rotations, binning=1)


def _dic_update(problem: _Problem, state: _State, prior) -> JointUpdate:
    """The DIC stage's joint solve with every parameter free at *state*:
    the step it would take from there and its standard errors."""
    solved, _ = solved_parameters(problem.parameters)
    linear = _linearise(problem, state.geometry, state.field, solved)
    update, _ = _joint_solve(
        state.field,
        linear,
        range(len(solved)),
        problem.rotation_offsets(state.rotations),
        _prior_per_axis(prior),
        0.0,
    )
    return update


def _standard_errors(
    problem: _Problem, state: _State, prior, update: JointUpdate | None = None
) -> dict[str, float]:
    """Standard errors of every refined parameter at the final state, and
    of the determined tilt difference, from one joint solve."""
    names = problem.parameters
    solved, split = solved_parameters(names)
    if update is None:
        update = _dic_update(problem, state, prior)
    se = dict(zip(solved, map(float, update.standard_errors)))
    if "tilt" in names or "sample_tilt" in names:
        base = "tilt" if "tilt" in solved else "sample_tilt"
        se[TILT_DIFFERENCE] = se[base]
    for name, base in split.items():
        # Only their difference is determined
        se[name] = se[base] = float("inf")
    return {k: se[k] for k in (*names, TILT_DIFFERENCE) if k in se}


#: The full field passes its adequacy check when the step the DIC stage
#: would take from the full field's solution is below this many of their
#: combined standard errors for every parameter either determines.
ADEQUACY_LIMIT = 3.0


def _adequacy(problem: _Problem, ff: _FullField, update: JointUpdate) -> dict[str, Any]:
    """Whether the full field's solution agrees with the DIC evidence.

    A misfit every pattern shares (ghost bands, band profiles changed by
    the processing, another simulator's master pattern) biases the full
    field, which compares intensities, more than the DIC stage, which
    tracks where features are; no variance over the patterns can see it.
    The DIC stage's step from the full field's solution, *update*, can:
    it is noise of the DIC's standard errors where both are right. Each
    parameter that neither stage leaves undetermined enters, in units of
    the two standard errors combined."""
    solved, _ = solved_parameters(problem.parameters)
    z, dic_step = {}, {}
    for name, step, se_dic in zip(solved, update.delta, update.standard_errors):
        key = TILT_DIFFERENCE if name in ("tilt", "sample_tilt") else name
        se_ff = ff.standard_errors.get(key, np.inf)
        if name in ff.held or max(se_dic, se_ff) > DETERMINACY_LIMITS[name]:
            continue
        z[key] = float(step / np.hypot(se_dic, se_ff))
        dic_step[key] = float(step)
    worst = max(z, key=lambda k: abs(z[k]), default=None)
    consistent = worst is None or abs(z[worst]) <= ADEQUACY_LIMIT
    if worst is None:
        # Nothing to compare (e.g. one pattern): say so, pass nothing off
        verdict = (
            "full field not checked: the DIC stage determines none of the parameters "
            "(its standard errors are above DETERMINACY_LIMITS)"
        )
    elif consistent:
        verdict = (
            "full field consistent with the DIC stage (largest step "
            f"{abs(z[worst]):.1f} combined standard errors, {worst})"
        )
    else:
        verdict = (
            f"full field and DIC stage disagree ({worst} {abs(z[worst]):.1f} combined "
            "standard errors apart): a misfit all patterns share; the full field's "
            "standard errors are raised to cover the disagreement"
        )
    return {"z": z, "dic_step": dic_step, "consistent": consistent, "verdict": verdict}


def _inflated(standard_errors: dict[str, float], adequacy: dict[str, Any]) -> dict[str, float]:
    """The full field's standard errors, each at least a third of the DIC
    stage's step from the full field's solution when the two disagree:
    either may be the biased one, and where it is the full field, its
    error is about that step. Falling back to the DIC stage instead was
    worse in every case measured: the DIC stage, blind to the blur and
    the processing, was itself biased where the two disagreed (pcy 3.4e-4
    off on processed Ni at 20,000 counts/px, where the full field was
    0.3e-4 off)."""
    if adequacy["consistent"]:
        return standard_errors
    out = dict(standard_errors)
    for key, step in adequacy["dic_step"].items():
        for name in ("tilt", "sample_tilt", key) if key == TILT_DIFFERENCE else (key,):
            if np.isfinite(out.get(name, np.inf)):
                out[name] = max(out[name], abs(step) / ADEQUACY_LIMIT)
    return out


def _build_result(
    problem: _Problem,
    outcome: _LoopOutcome,
    rotations: Rotation,
    scores: np.ndarray,
    detector: EBSDDetector,
    signal: EBSD,
    nav: tuple[int, int],
    geometry0: MapGeometry,
    prior: float | None,
    solver: str,
    standard_errors: dict[str, float] | None = None,
    adequacy: dict[str, Any] | None = None,
) -> GeometryRefinementResult:
    """The :class:`GeometryRefinementResult` of a loop's *outcome*, with
    the final orientations *rotations* and their NCC *scores*; the
    standard errors of the DIC field unless *standard_errors* are given."""
    names, pts = problem.parameters, problem.points
    state = outcome.state
    geometry, field_after = state.geometry, state.field
    xmap_out = CrystalMap(
        rotations=rotations,
        x=np.arange(len(pts), dtype=float),
        phase_list=PhaseList(problem.phase),
        prop={
            "scores": np.asarray(scores),
            "row": pts[:, 0],
            "col": pts[:, 1],
            "pseudo_symmetry_index": problem.variants(rotations)[0],
            # A pattern far above the others failed (e.g. a wrong start)
            "dic_rms": np.sqrt(
                (field_after.counts * (field_after.u**2).sum(axis=-1)).sum(axis=1)
                / np.maximum(field_after.counts.sum(axis=1), 1)
            ),
        },
    )
    det = geometry.detector()
    if len(detector.navigation_shape) == 2 or nav[0] > 1:
        det.pc = det.pc.reshape(signal.axes_manager.navigation_shape[::-1] + (3,))
    se = standard_errors or _standard_errors(problem, state, prior)
    # Diagnostics of the average field, the paper's view of the map
    jac = analytic_jacobian(
        geometry, pts, field_after.positions, field_after.counts, names, problem.steps
    )
    update = solve_update(jac, field_after.residual, field_after.weights, 0.0)
    degenerate = [
        {n: float(c) for n, c in zip(names, v) if abs(c) > NULL_SPACE_TOLERANCE}
        for v in update.null_space.T
    ]
    return GeometryRefinementResult(
        detector=det,
        geometry=geometry,
        start_geometry=geometry0,
        xmap=xmap_out,
        points=pts,
        parameter_names=names,
        parameters=dict(zip(names, map(float, geometry.values(names)))),
        standard_errors=se,
        undetermined=tuple(
            n
            for n in names
            if se.get(TILT_DIFFERENCE if n in ("tilt", "sample_tilt") else n, 0)
            > DETERMINACY_LIMITS[n]
        ),
        solver=solver,
        history=outcome.history,
        jacobian=jac,
        coupling=coupling_matrix(jac, field_after.weights),
        singular_values=update.singular_values,
        degenerate=degenerate,
        field_before=outcome.field_before,
        field_after=field_after,
        converged=outcome.converged,
        steps=problem.steps,
        adequacy=adequacy or {},
    )
