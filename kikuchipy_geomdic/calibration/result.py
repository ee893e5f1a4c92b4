"""What :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`
returns (:class:`GeometryRefinementResult`), and how it is built from the
refinement's final state.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._problem import _LoopOutcome, _Problem, _State
from kikuchipy_geomdic.calibration.jacobian import analytic_jacobian
from kikuchipy_geomdic.calibration.solve import coupling_matrix, solve_update
from kikuchipy_geomdic.calibration.uncertainty import DETERMINACY_LIMITS, TILT_DIFFERENCE
from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.patterns import displacement as dsp

__all__ = ["GeometryRefinementResult"]

#: Components of a null-space vector below this are SVD round-off, not
#: part of the reported degenerate combination (the columns are
#: normalised, so a real component is of order one).
NULL_SPACE_TOLERANCE = 1e-6


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
        The refined :class:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry`.
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
        Calibrated from several master patterns, its phases are those of
        the input map with their ids, and each point has its own.
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
        refined: only their difference is determined; ``inf`` for an
        angle kept at its start (see *undetermined*); ``inf`` for every
        parameter when the DIC stage's features did not match (an RMS
        displacement above 4 px at the end) and no full field ran: the
        patterns do not determine the geometry.
    undetermined
        Parameters the map determines only poorly (standard error above
        :data:`~kikuchipy_geomdic.calibration.uncertainty.DETERMINACY_LIMITS`;
        for tilt and sample_tilt, that of their difference). The joint solver moved them only by
        significant steps; unmoved, they keep their start value and an
        infinite standard error (the start's own uncertainty applies).
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
        start and at the last geometry the DIC measured: the refined one,
        or, after the full-field stage, the DIC stage's last (the full
        field's start, a few tenths of a percent of the width from the
        solution).
    converged
        Whether the loop ended by its tolerances (joint: every step below
        its standard error; paper: NCC gain below ``ncc_tolerance`` and
        the displacement no longer falling) rather than by
        *max_iterations* or by rejected steps.
    adequacy
        The check of the full-field stage against the DIC stage
        (:data:`~kikuchipy_geomdic.calibration.uncertainty.ADEQUACY_LIMIT`):
        the DIC stage's solution (where it ended plus its last step) minus
        the full field's, per parameter (``"dic_step"``) and
        in units of their combined standard errors (``"z"``), whether it passed
        (``"consistent"``; if not, the standard errors are inflated to
        cover the disagreement), a sentence saying so (``"verdict"``) and
        ``"systematic"``: the part of each standard error that a misfit
        the patterns share adds, from the spread of the full field's
        solutions on the detector's quadrants (crystal model) or over the
        grains left out in turn (free model), included in
        :attr:`standard_errors`; ``"lattice"`` where the full field fitted
        the lattice (:attr:`lattice`). Empty when no full field ran.
    orientation_model
        The orientation model used: "free" (a rotation per point) or
        "crystal" (one parent orientation in each point's variant with a
        small scatter, see ``orientation_model`` of
        :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`).
    crystal
        With the crystal model: ``parent`` (the fitted parent
        orientation, an orix ``Rotation``), ``scatter`` (RMS angle in deg
        of the orientations about it in their variants, fitted),
        ``prior`` (the scatter the fit assumed, deg) and ``fraction`` (of
        the starting orientations within 5 deg of the parent's
        variants); else empty. The points' variants are in
        ``xmap.prop["variant"]``.
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
    orientation_model: str = "free"
    crystal: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        return self.table()

    @property
    def points_per_phase(self) -> dict[str, int]:
        """The calibration points of each phase, by the phase's name."""
        ids, counts = np.unique(self.xmap.phase_id, return_counts=True)
        return {self.xmap.phases[int(i)].name: int(c) for i, c in zip(ids, counts)}

    @property
    def lattice(self) -> dict[str, Any]:
        """The crystal's lattice as the full field fitted it (``lattice_tolerance``
        of :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`):
        ``"stretch"`` of the c axis against the CIF's (a fraction) and its
        ``"stretch_se"``, the ``"c_over_a"`` it makes with its
        ``"c_over_a_se"`` and the CIF's ``"phase_c_over_a"``, the prior's
        ``"tolerance"``, and whether the map ``"determined"`` it (its
        standard error below half the tolerance; if not, the PC's
        standard errors carry the tolerance). Empty where it was not
        fitted: a cubic crystal, a polycrystal, patterns with the map's mean
        divided out, ``lattice_tolerance=0`` or no full field.
        """
        return dict(self.adequacy.get("lattice", {}))

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
            f"{self.field_after.backend}"
            + (f", {self.orientation_model} orientation model" if self.crystal else "")
            + ")"
        )
        cols = f"{'parameter':<17}{'start':>10}{'refined':>11}{'sigma':>10}"
        start, true = self.start_geometry.as_dict(), None
        if truth is not None:
            cols += f"{'true':>11}{'error':>11}"
            true = truth.as_dict()
        lines = [head, cols + "  unit"]
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
                own = TILT_DIFFERENCE if name in ("tilt", "sample_tilt") else name
                none = np.isinf(self.standard_errors.get(own, 0))
                line += "  not determined" if none else "  poorly determined"
                # Kept: back at the start to round-off (a held difference
                # of tilt and sample_tilt is split in two again)
                line += ", kept" if _at_start(b, a) else ""
            lines.append(line)
        pcs = [n for n in self.parameter_names if n.startswith("pc")]
        if pcs and all(np.isinf(self.standard_errors.get(n, 0)) for n in pcs):
            notes.append("not determined by these patterns: the start's own uncertainty applies")
        elif any(not np.isfinite(self.standard_errors.get(n, 0)) for n in self.parameter_names):
            notes.append("tilt and sample_tilt: only their difference is determined")
        if self.adequacy:
            notes.append(self.adequacy["verdict"])
        # Both tilts refined: each is infinite, their difference carries it
        sys = {n: v for n, v in self.adequacy.get("systematic", {}).items() if 0 < v < np.inf}
        if sys:
            notes.append(
                "sigma includes a systematic part (spread of the "
                + ("detector's quadrants" if self.crystal else "grains")
                + "): "
                + ", ".join(f"{n} {v:.1e}" for n, v in sys.items())
            )
        lattice = self.lattice
        if lattice:
            notes.append(
                f"c/a {lattice['c_over_a']:.5f} +- {lattice['c_over_a_se']:.5f} (the CIF's "
                f"{lattice['phase_c_over_a']:.5f}, stretch {lattice['stretch']:+.2%}), "
                + (
                    "fitted with the geometry"
                    if lattice["determined"]
                    else f"not determined by this map: the PC's sigma carries its "
                    f"{lattice['tolerance']:.1%} tolerance"
                )
            )
        return "\n".join(lines + notes)

    def plot_displacement(self, **kwargs):
        """Plot the average displacement field before and after (quiver).

        See :func:`kikuchipy_geomdic.plotting.calibration.plot_displacement_fields`.
        """
        from kikuchipy_geomdic import plotting

        return plotting.plot_displacement_fields(
            [self.field_before, self.field_after], ["before", "after"], **kwargs
        )

    def plot_sensitivity(self, **kwargs):
        """Plot each parameter's sensitivity field (a Jacobian column).

        See :func:`kikuchipy_geomdic.plotting.calibration.plot_sensitivity`.
        """
        from kikuchipy_geomdic import plotting

        return plotting.plot_sensitivity(
            self.jacobian, self.parameter_names, self.field_after, self.steps, **kwargs
        )

    def plot_coupling(self, **kwargs):
        """Plot the coupling matrix. See
        :func:`kikuchipy_geomdic.plotting.calibration.plot_coupling`."""
        from kikuchipy_geomdic import plotting

        return plotting.plot_coupling(self.coupling, self.parameter_names, **kwargs)

    def plot_convergence(self, **kwargs):
        """Plot NCC and displacement per iteration.

        See :func:`kikuchipy_geomdic.plotting.calibration.plot_convergence`.
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


def _phases_of_points(problem: _Problem) -> dict[str, Any]:
    """The phase list and the phase ids of the calibration points' map."""
    if not problem.multi_phase:
        return {"phase_list": PhaseList(problem.phase)}
    phases = PhaseList({p.phase_id: p.phase.deepcopy() for p in problem.phases})
    ids = np.array([p.phase_id for p in problem.phases])[problem.point_phase]
    return {"phase_list": phases, "phase_id": ids}


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


def _at_start(value: float, start: float) -> bool:
    """Whether *value* is *start* to round-off (a held tilt difference is
    split in two again)."""
    return abs(value - start) <= 1e-9 * max(1.0, abs(start))


def _kept(se: dict[str, float], geometry: MapGeometry, geometry0: MapGeometry) -> dict:
    """*se* with an infinite standard error for every poorly determined
    angle the calibration kept at its start: the start is then the answer,
    and only the start's own uncertainty applies (with the estimate's
    standard error kept, a Ni single crystal's azimuthal read 0.75 deg off
    at 0.19 deg)."""
    se, now, then = dict(se), geometry.as_dict(), geometry0.as_dict()
    for name in list(se):
        own = TILT_DIFFERENCE if name in ("tilt", "sample_tilt") else name
        if (
            name in now
            and not name.startswith("pc")
            and se.get(own, 0) > DETERMINACY_LIMITS[name]
            and _at_start(now[name], then[name])
        ):
            se[name] = float("inf")
            if own == TILT_DIFFERENCE:
                se[TILT_DIFFERENCE] = float("inf")
    return se


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
    standard_errors: dict[str, float],
    adequacy: dict[str, Any] | None = None,
) -> GeometryRefinementResult:
    """The :class:`GeometryRefinementResult` of a loop's *outcome*, with
    the final orientations *rotations* and their NCC *scores* and the
    *standard_errors* of the stage that ended it."""
    names, pts = problem.parameters, problem.points
    state = outcome.state
    geometry, field_after = state.geometry, state.field
    crystal, extra = {}, {}
    if problem.crystal is not None:
        scatter = problem.crystal.deviations(rotations)[1]
        crystal = {
            "parent": problem.crystal.fitted_parent(rotations),
            "scatter": float(np.rad2deg(np.sqrt((scatter**2).sum(axis=1).mean()))),
            "prior": float(prior),
            "fraction": problem.crystal.fraction,
        }
        extra["variant"] = problem.crystal.labels(rotations)
    xmap_out = CrystalMap(
        rotations=rotations,
        x=np.arange(len(pts), dtype=float),
        **_phases_of_points(problem),
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
            **extra,
        },
    )
    det = geometry.detector()
    if len(detector.navigation_shape) == 2 or nav[0] > 1:
        det.pc = det.pc.reshape(signal.axes_manager.navigation_shape[::-1] + (3,))
    se = _kept(standard_errors, geometry, geometry0)
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
        orientation_model="free" if problem.crystal is None else "crystal",
        crystal=crystal,
    )
