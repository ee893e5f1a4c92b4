"""The geometry calibration's public driver: :func:`refine_geometry_dic`
refines the global sample-detector geometry of a map by global DIC.

Both solvers follow the paper's method (sections 2.2-2.4, Fig. 4):
simulate the calibration points at the current geometry, measure the
displacement fields (:mod:`~kikuchipy_geomdic.patterns.displacement`),
linearise (:mod:`~kikuchipy_geomdic.calibration.jacobian`), solve
(:mod:`~kikuchipy_geomdic.calibration.solve`) and update the geometry and its
PC field (:mod:`~kikuchipy_geomdic.geometry`). By default a full-field
stage follows: Gauss-Newton on the pixel intensities from where the DIC
stage ended, checked against it.

Layout
------
As kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation`:
:func:`refine_geometry_dic` checks its options (``_check_options``) and
inputs (``_checks``), selects the calibration points (``_points``,
:func:`calibration_points`), freezes everything that stays fixed into a
``_Problem`` (``_problem``), runs the DIC stage (``_dic_stage``: the joint
solver's loop on the fits of ``_dic_fit``, or the paper's loop,
``_paper``) and the full field (``_full_field``, with its model of what
was done to the patterns, ``_processing``), and builds the
:class:`~kikuchipy_geomdic.calibration.result.GeometryRefinementResult`
(:mod:`~kikuchipy_geomdic.calibration.result`). Standard errors,
determinacy and adequacy are in
:mod:`~kikuchipy_geomdic.calibration.uncertainty`, the progress bar in
``_progress``.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._checks import _check_inputs, _step_sizes
from kikuchipy_geomdic.calibration._crystal import CRYSTAL_SCATTER, ORIENTATION_MODELS
from kikuchipy_geomdic.calibration._dic_stage import _check_matched, _dic_stage
from kikuchipy_geomdic.calibration._full_field import FULL_FIELD_BASIN, _full_field_stage
from kikuchipy_geomdic.calibration._points import calibration_points
from kikuchipy_geomdic.calibration._preparation import _prepare_problem
from kikuchipy_geomdic.calibration._problem import _binning, _State
from kikuchipy_geomdic.calibration._progress import _Progress, _show_progressbar
from kikuchipy_geomdic.calibration.result import (
    GeometryRefinementResult,
    _build_result,
    _final_orientations,
)
from kikuchipy_geomdic.calibration.uncertainty import _named_errors
from kikuchipy_geomdic.geometry import (
    DEFAULT_PARAMETERS,
    MapGeometry,
    check_parameters,
    solved_parameters,
)
from kikuchipy_geomdic.geometry.maps import navigation_shape
from kikuchipy_geomdic.indexing.phases_to_refine import check_energy, unrefined_phases

__all__ = [
    "refine_geometry_dic",
    "calibration_points",
    "SOLVERS",
]


#: Solvers of :func:`refine_geometry_dic`.
SOLVERS = ("joint", "paper")

#: Default standard deviation of a crystal's c/a about its CIF's, as a
#: fraction: a user's CIF is a room-temperature bulk reference, the crystal
#: in the microscope a film, a heated sample or another composition; a
#: cubic CIF for a slightly tetragonal phase (BaTiO3) is 1.1 % off.
LATTICE_TOLERANCE = 0.01

_JACOBIANS = ("finite-difference", "analytic")


#: What to do where the map's mean was divided out of one crystal's patterns
_DYNAMIC_ONLY = (
    "Calibrate on patterns with only the dynamic background removed "
    "(EBSD.remove_dynamic_background on the raw patterns): on BaTiO3 domain maps their PC "
    "ended 2.6e-4 off (median of 8), with the mean divided out 4.9e-4 with standard errors "
    "of about 1e-3"
)


def _check_options(
    parameters, solver, jacobian, orientation_prior, orientation_model="auto", lattice_tolerance=0
) -> tuple[str, ...]:
    """Check the options that need no data; return the parameters to
    refine in canonical order."""
    names = check_parameters(parameters)
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, not {solver!r}")
    if orientation_model not in ORIENTATION_MODELS:
        raise ValueError(
            f"orientation_model must be one of {ORIENTATION_MODELS}, not {orientation_model!r}"
        )
    if solver == "paper" and orientation_model == "crystal":
        raise ValueError(
            "orientation_model='crystal' needs the joint solver: the paper's refines every "
            "orientation on its own"
        )
    if jacobian not in _JACOBIANS:
        raise ValueError(f"jacobian must be one of {_JACOBIANS}, not {jacobian!r}")
    if orientation_prior is not None and not (
        np.isfinite(orientation_prior) and orientation_prior > 0
    ):
        raise ValueError(
            f"orientation_prior must be a positive RMS angle in degrees or None, "
            f"not {orientation_prior}"
        )
    if not (np.isscalar(lattice_tolerance) and lattice_tolerance >= 0):
        raise ValueError(
            f"lattice_tolerance must be a fraction >= 0 (0 holds the CIF's lattice), "
            f"not {lattice_tolerance!r}"
        )
    return names


def refine_geometry_dic(
    signal: EBSD,
    xmap: CrystalMap,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern | Sequence[EBSDMasterPattern],
    energy: float,
    *,
    parameters: Sequence[str] = DEFAULT_PARAMETERS,
    points: int | np.ndarray = 100,
    solver: str = "joint",
    orientation_prior: float | None = None,
    orientation_model: str = "auto",
    pseudo_symmetry_ops: Rotation | Sequence[Rotation | None] | None = None,
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
    lattice_tolerance: float = LATTICE_TOLERANCE,
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
        Lambert master pattern of the phase, or a list of them, one per
        phase of the map, each matched to the map's phase it is of
        (:func:`~kikuchipy_geomdic.indexing.phases_to_refine.phases_to_refine`:
        proper point group, then lattice or name). The points of every
        phase with a master pattern are chosen across the map and enter one
        joint solve (one geometry, a rotation per pattern, each pattern
        simulated from its phase's master pattern); points of a phase
        without one are left out, with a warning. The result's ``xmap``
        holds each point's phase
        (:attr:`GeometryRefinementResult.points_per_phase`).
    energy
        Beam energy in kV, one for every phase.
    parameters
        Parameters to refine, from
        :data:`~kikuchipy_geomdic.geometry.parameters.PARAMETERS`. Default the
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
        field across the map. With the crystal model: the RMS scatter of
        the orientations about their parent (default
        ``CRYSTAL_SCATTER``, 0.1 deg).
    orientation_model
        "free": a rotation per point, for any map. "crystal":
        the map is one crystal (a wafer, a domain map): every point is
        one parent orientation in one of its variants (the
        *pseudo_symmetry_ops*) with a small scatter (*orientation_prior*),
        the parent's three angles fitted with the geometry and each
        point's variant chosen by its pattern. The starting orientations
        only place the parent (their mode, modulo the crystal symmetry and
        the variants): a point's own start error, or a wrong variant, is
        not carried into the fit. Raises
        :class:`~kikuchipy_geomdic.calibration.NotOneCrystalError` (a ``ValueError``)
        if the starts are not one crystal. "auto" (default): "crystal"
        where at least 70 % of the starts lie within 5 deg of one parent
        (modulo *pseudo_symmetry_ops*) and their patterns agree, else
        "free" (on realistic single crystals the free model's standard
        errors missed errors by up to 23 of them, the crystal model's by
        at most 1.6; on 37 BaTiO3 domain maps across the envelope the free
        model's missed it on 7, by up to 14, the crystal model's on 1, a
        map both miss; a polycrystal is calibrated as before).
        The result says which was used
        (:attr:`GeometryRefinementResult.orientation_model`). Joint solver
        only.
    pseudo_symmetry_ops
        Pseudo-symmetry operators (orix ``Rotation``, crystal frame, left
        factors ``op * rotation``), e.g.
        ``variant_operators()[1:]`` for BaTiO3. The joint
        solver picks per point the variant whose simulated pattern
        correlates best, before the loop and at the refined geometry; the
        paper solver passes them to kikuchipy. With a list of master
        patterns, a list of operators, one per master pattern (None where a
        phase has none).
    steps
        Central-difference step per parameter; defaults in
        :data:`~kikuchipy_geomdic.geometry.parameters.DEFAULT_STEPS`.
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
        has several phases and one master pattern is given (with a list,
        each master pattern is matched to its phase).
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
        :data:`~kikuchipy_geomdic.calibration.uncertainty.ADEQUACY_LIMIT`
        combined standard errors). Default: True for the joint solver,
        False for the paper's. The DIC stage then ends once the RMS
        displacement is below 0.3 % of the width, the full field's basin.
        By default it is skipped, with a warning, when the DIC stage
        leaves a PC standard error above 3e-3 (``FULL_FIELD_GUARD``): the
        full field needs a start in its basin; True runs it anyway. False:
        the DIC stage alone, for patterns the model does not describe (see
        the method page).
    lattice_tolerance
        How far, as a fraction, the crystal's c/a may be from that of the
        master pattern's phase (its CIF): a prior's standard deviation.
        On one crystal (the crystal orientation model) with one unique
        axis (tetragonal, hexagonal, trigonal) the full field fits the c
        axis' stretch with the geometry, since a c/a the CIF does not have
        moves every band of every pattern alike and reads as a PC error
        (0.6 % of c/a: 2-3e-3 of PC). Where the map separates the two, the
        fit is the data's; where it cannot, the PC's standard errors carry
        this tolerance. Reported in :attr:`GeometryRefinementResult.lattice`.
        0 holds the lattice at the CIF's; cubic crystals have no such
        freedom, and on a polycrystal each pattern's rotation absorbs most
        of it (the lattice is held there). Default :data:`LATTICE_TOLERANCE`.
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
    exceeds :data:`~kikuchipy_geomdic.calibration.uncertainty.DETERMINACY_LIMITS`
    is moved by the joint solver only by a step of
    :data:`~kikuchipy_geomdic.calibration.uncertainty.SIGNIFICANCE` standard
    errors or more, so that noise cannot walk it around, and if its whole
    move still ends under that many standard errors, the DIC stage runs
    again with it fixed at its start (a single crystal with domains let the
    azimuthal angle walk 17 deg on a standard error of 6 deg); the result
    lists it in :attr:`~GeometryRefinementResult.undetermined`, with its
    standard error.

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
    names = _check_options(
        parameters, solver, jacobian, orientation_prior, orientation_model, lattice_tolerance
    )
    nav = navigation_shape(signal)
    phases = _check_inputs(
        signal, xmap, detector, master_pattern, phase, nav, pseudo_symmetry_ops, energy
    )
    _left_out_note(xmap, phases)
    energy = check_energy(energy)
    # Left at its default, the full field runs only where the DIC stage
    # has brought the geometry into its basin; True forces it
    guarded = full_field is None
    if full_field is None:
        full_field = solver == "joint"
    dic_kw = dict(rois=tuple(rois), binning=binning, dic=dic, seed=seed)
    dic_kw.update(dic_kwargs or {})
    if dic_kw["binning"] is None:
        dic_kw["binning"] = 1 if not full_field else _binning(signal.axes_manager.signal_shape)
    geometry0 = MapGeometry.from_detector(detector, _step_sizes(signal), nav)
    problem = _prepare_problem(
        signal, xmap, phases, energy, names, points, nav, steps, dic_kw, refine_kwargs,
        orientation_model if solver == "joint" else None, geometry0,
    )  # fmt: skip
    problem = replace(problem, lattice_tolerance=float(lattice_tolerance))
    if problem.crystal is not None and orientation_prior is None:
        orientation_prior = CRYSTAL_SCATTER
    dic_stage = functools.partial(
        _dic_stage,
        geometry0=geometry0,
        solver=solver,
        jacobian=jacobian,
        prior=orientation_prior,
        damping=damping,
        max_iterations=max_iterations,
        ncc_tolerance=ncc_tolerance,
    )
    header = (
        f"Refining the geometry ({solver} solver) with {len(problem.points)} calibration "
        f"points{_per_phase(problem)}: {', '.join(names)}"
        + (
            f"; one crystal ({100 * problem.crystal.fraction:.0f} % of the starts within "
            f"5 deg of its parent's variants), scatter prior {orientation_prior:g} deg"
            if problem.crystal is not None
            else ""
        )
        + (
            "; the map's mean pattern, bands and all, was divided out of the patterns: the DIC "
            "stage compares them with its bands put back"
            if problem.bands_put_back
            else ""
        )
    )
    with _Progress(show, max_iterations, header) as progress:
        outcome = dic_stage(problem, progress, FULL_FIELD_BASIN if full_field else 0.0)
        outcome, standard_errors, adequacy = _full_field_stage(
            problem, outcome, dic_stage, orientation_prior, full_field, guarded, binning, progress
        )
    outcome, matched = _check_matched(outcome, functools.partial(_mean_divided_note, problem))
    outcome, standard_errors, adequacy = _failures(
        problem, outcome, matched, standard_errors, adequacy, geometry0
    )
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


def _left_out_note(xmap, phases) -> None:
    """Warn about the map's indexed phases without a master pattern (with
    several given): their points are left out of the calibration."""
    left = unrefined_phases(xmap, phases)
    if len(phases) > 1 and left:
        listed = ", ".join(f"{name!r} ({n} points)" for name, n in left.items())
        warnings.warn(
            f"No master pattern of the phases {listed}: their points are left out of the "
            "calibration",
            UserWarning,
            stacklevel=3,
        )


def _per_phase(problem) -> str:
    """The points per phase for the header, with several phases."""
    if not problem.multi_phase:
        return ""
    counts = np.bincount(problem.point_phase, minlength=len(problem.phases))
    return " (" + ", ".join(f"{p.name} {n}" for p, n in zip(problem.phases, counts)) + ")"


def _failures(problem, outcome, matched, standard_errors, adequacy, geometry0):
    """The outcome, standard errors and adequacy, with infinite standard
    errors where the patterns did not determine the geometry: features
    that did not match, or a start no step could leave; and a note of the
    ROIs without vectors."""
    names = problem.parameters
    if matched and problem.bands_put_back and not adequacy:
        # DIC on what dividing by the map's mean left matches the noise as
        # readily as the variants' bands; only the full field models the
        # division (a BaTiO3 domain map whose DIC stage alone moved pcz
        # from 1.8e-2 to -1.8e-2 off, at 4.2 of its standard errors)
        warnings.warn(
            "The DIC stage did not bring the geometry within reach of the full field, the "
            "stage that models the division by the map's mean. The result is the start, marked "
            "not converged, with infinite standard errors. " + _mean_divided_note(problem),
            UserWarning,
            stacklevel=3,
        )
        outcome, matched = replace(outcome, converged=False), False
    if not matched and not adequacy:
        # Steps on fields of unmatched features follow the noise's matches,
        # so the result is the start, whose own uncertainty applies (Si,
        # one crystal, 30 counts/px with the map's mean divided out: one
        # such step took pcy from 1.2e-2 to 3.7e-2 off). Standard errors
        # from such fields measure the noise's matches, not the geometry
        # (BaTiO3 domain map at 30 counts/px, users' start kept: pcz 1.8e-2
        # off at 4.0 of them)
        outcome = replace(
            outcome, state=_State.measure(problem, geometry0, problem.start_rotations)
        )
        solved, _ = solved_parameters(names)
        standard_errors = _named_errors(names, np.full(len(solved), np.inf))
    if matched and _unmoved(outcome.state.geometry, geometry0, names):
        # Standard errors at a start no step could leave describe the
        # start's linearisation, not the geometry (a BaTiO3 domain map from
        # users' starts: pcy and pcz reported at 3-4e-4, 1.5e-2 off). A
        # loop "converges" there too when every parameter is poorly
        # determined and none would move significantly (a Si crystal whose
        # patterns matched in a third of the ROIs)
        outcome = replace(outcome, converged=False)
        warnings.warn(
            "The calibration did not move from its start: no step lowered the DIC "
            "displacement, so these patterns and starting orientations do not determine the "
            "geometry from there. The result is the start, marked not converged, with infinite "
            "standard errors. Try a start closer to the truth, more or better patterns, or "
            "orientation_model='crystal' for one crystal",
            UserWarning,
            stacklevel=3,
        )
        solved, _ = solved_parameters(names)
        standard_errors = _named_errors(names, np.full(len(solved), np.inf))
        adequacy = {}
    if not adequacy.get("lattice", {}).get("variants_apart", True):
        # A lattice fitted to the parent's cubic one makes the variants
        # alike, and wrong ones can pull it there: a domain map whose c/a
        # is 0.6 % below the CIF's fitted 1.0002 +- 0.0007, its variants
        # 20 % right and its PC 1.8e-3 off at 4.8 standard errors
        outcome = replace(outcome, converged=False)
        warnings.warn(
            "The c/a fitted is within 3 standard errors of 1, where the variants look alike: "
            "they and the geometry fitted with them cannot be trusted; marked not converged. A "
            "crystal this near cubic has no variants to tell apart (calibrate without "
            "pseudo_symmetry_ops); a tetragonal one needs starts with more variants right",
            UserWarning,
            stacklevel=3,
        )
    _empty_rois_note(outcome.state.field)
    return outcome, standard_errors, adequacy


def _empty_rois_note(field) -> None:
    """Warn once about the ROIs the last DIC comparison left without a
    vector (the measurements of every step do not: :func:`_problem._measure`)."""
    empty = np.flatnonzero(field.total_counts == 0)
    if empty.size:
        warnings.warn(
            f"{empty.size} of {field.total_counts.size} ROIs got no displacement vector in the "
            f"calibration's last DIC comparison (ROIs {empty.tolist()}): too few trackable "
            "features there (a dark corner, a shadow); their weight is zero",
            UserWarning,
            stacklevel=4,
        )


def _unmoved(geometry: MapGeometry, geometry0: MapGeometry, names) -> bool:
    """Whether no parameter among *names* left its start."""
    return bool(np.array_equal(geometry.values(names), geometry0.values(names)))


def _mean_divided_note(problem) -> str:
    """Why the geometry may be out of the patterns' reach, if the map's
    mean pattern was divided out of them (:attr:`_Problem.mean_divided`),
    and what to do; else an empty string."""
    if not problem.mean_divided:
        return ""
    return (
        "The signal's static background holds these patterns' Kikuchi bands, and the map's "
        "mean pattern was divided out of them: on a map of one crystal (or of few grains) "
        "that leaves little more than the noise and the variants' differences. "
        + _DYNAMIC_ONLY
        + (
            "; on one crystal, orientation_model='crystal' puts the static background's bands "
            "back for the DIC stage"
            if problem.crystal is None
            else ""
        )
    )
