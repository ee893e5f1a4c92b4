"""The full-field stage: Gauss-Newton on the pixel intensities from where
the DIC stage ended (:func:`_full_field`), each pattern's gain and offset
projected out, each pixel weighted by its noise variance, the model made
as the patterns were (``_processing``), on one crystal both high-passed
alike before they are compared; and what runs it after the DIC stage
(:func:`_full_field_stage`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._dic_fit import _expand, _prior_per_axis, _solved_values
from kikuchipy_geomdic.calibration._intensity import _hold, _intensity_system, _System
from kikuchipy_geomdic.calibration._problem import _LoopOutcome, _Problem, _State, _step_record
from kikuchipy_geomdic.calibration._processing import PSF_NEGLIGIBLE, _estimate_processing
from kikuchipy_geomdic.calibration._progress import _Progress
from kikuchipy_geomdic.calibration._systematic import (
    CRYSTAL_PRIOR_PARTS,
    PRIOR_PARTS,
    REGIONS,
    _grain_errors,
    _quadrants,
    _region_errors,
    _with_prior,
)
from kikuchipy_geomdic.calibration.solve import JointSystem
from kikuchipy_geomdic.calibration.uncertainty import (
    _PC,
    DETERMINACY_LIMITS,
    TILT_DIFFERENCE,
    UNDETERMINED_RANGE,
    _adequacy,
    _dic_errors,
    _dic_step,
    _free_errors,
    _inflated,
    _insignificant_moves,
    _named_errors,
    _unkeepable,
)
from kikuchipy_geomdic.geometry import MapGeometry, rotations_from_vectors, solved_parameters

#: Gauss-Newton steps of the full-field stage at most; it stops earlier
#: when no parameter moves by more than :data:`FULL_FIELD_STOP` of its
#: standard error.
FULL_FIELD_ITERATIONS = 5
#: ... with the crystal model, whose steps move the parent, every pattern
#: at once, along a valley where a PC change is nearly the parent's
#: rotation: each went about 0.7 of the way (240 px domain map, the map's
#: mean divided out: pcx 1.8e-3 off at the DIC stage, 4.1e-4 after five
#: steps, 2.4e-4 after nine)
CRYSTAL_FULL_FIELD_ITERATIONS = 10
FULL_FIELD_STOP = 0.25
#: ... and no orientation moves by more than this (deg).
FULL_FIELD_ROTATION_STOP = 0.01
#: The full field builds its Jacobians again after a step that lowered
#: chi2 by more than this fraction.
JACOBIAN_REFRESH = 0.1

#: Longest step of the c axis' stretch (a fraction) in one full-field
#: iteration: its derivative holds to 6 % over 1e-3, to 25 % over 4e-3 (a
#: BaTiO3 master pattern); longer, a domain map's first step went to -3.2 %
#: for data 0.6 % off and the PC ended 1.8e-2 off
LATTICE_STEP = 2e-3
#: The c axis' stretch a master pattern resolves (a fraction): the
#: systematic floor of a fitted stretch, carried to the geometry along
#: their valley. Two simulators of one BaTiO3 CIF differ in c/a by about
#: this much: domain maps of the CIF's lattice fitted -0.02 to -0.03 %
#: at 0.01-0.02 %, maps 0.2-0.8 % off -0.12 to +0.05 % (RMS 0.06 %)
#: while the quadrants' spread said 0.01-0.05 % (7 of 18 covered)
LATTICE_RESOLUTION = 5e-4
#: A fitted stretch farther than this from the CIF's has the full field
#: choose the variants again at it and go on from there.
VARIANTS_AGAIN = 2e-3

#: RMS displacement (fraction of the width) below which the DIC stage
#: hands over to the full field: well inside its basin (measured: from
#: the state after one DIC step, 0.09 % RMS with the angles 0.5-0.7 deg
#: off, the full field reached the same geometry as after five).
FULL_FIELD_BASIN = 0.003

#: The DIC stage's PC standard error (statistical) above which the free
#: model's full field is skipped, its start outside its basin (about
#: 1e-2). Below, it beats the DIC stage (few-grain Ni maps, another
#: simulator: 1.1-9.0e-3 off at the DIC stage, 2.3e-4 to 1.6e-3 after,
#: z <= 1.0; benchmarks 8). Only after a DIC stage that moved: from a
#: start it could not leave (1.8e-2 off) one ended 5.9e-3 off at 2.7 of
#: its standard errors. The crystal model's full field needs a determined
#: PC (DETERMINACY_LIMITS): there the one parent moves every pattern
FULL_FIELD_GUARD = 3e-3


def _full_field_stage(
    problem: _Problem,
    outcome: _LoopOutcome,
    dic_stage: Callable[[_Problem, _Progress, float], _LoopOutcome],
    orientation_prior: float | None,
    full_field: bool,
    guarded: bool,
    binning: int | None,
    progress: _Progress,
) -> tuple[_LoopOutcome, dict[str, float] | None, dict[str, Any]]:
    """What follows the DIC stage's *outcome*: its standard errors, then,
    if *full_field*, the full field from where it ended, checked against
    it (:func:`_adequacy`). *guarded* (the default): the DIC stage run
    again unbinned (*dic_stage*) where it left a PC undetermined, unless
    the user chose the *binning*; the full field skipped, with a warning,
    where a PC stays so, or above :data:`FULL_FIELD_GUARD` (free model,
    the DIC stage moved). Returns the outcome, standard errors, adequacy."""

    def undetermined(statistical, limits=DETERMINACY_LIMITS):
        return [n for n in _PC if statistical.get(n, 0) > limits[n]]

    # Whether the full field's basin is reached is the statistics' say;
    # what is reported without it includes what the patterns share
    dic_update, statistical, standard_errors = _dic_errors(
        problem, outcome.state, orientation_prior
    )
    loose = undetermined(statistical)
    if guarded and full_field and loose and binning is None and problem.dic_kwargs["binning"] > 1:
        # The DIC stage again at full resolution, as full_field=False runs
        # it, and the full field from there if it determines the PC (a
        # domain map at pcz 0.5: binned, pcx and pcz undetermined; unbinned
        # determined, 5.4e-3 off at 13 of its standard errors, which the
        # full field took to 5.5e-4, within one of its own)
        progress.write(f"  {', '.join(loose)} undetermined binned: the DIC stage again unbinned")
        problem = replace(problem, dic_kwargs={**problem.dic_kwargs, "binning": 1})
        outcome = dic_stage(problem, progress, 0.0)
        dic_update, statistical, standard_errors = _dic_errors(
            problem, outcome.state, orientation_prior
        )
    moved = any(h["accepted"] for h in outcome.history)
    loose_start = problem.crystal is None and moved
    guard = dict.fromkeys(_PC, FULL_FIELD_GUARD) if loose_start else DETERMINACY_LIMITS
    loose = undetermined(statistical, guard)
    if guarded and full_field and loose:
        # The full field needs a start in its basin (measured: at 0.3
        # counts/px it converged 2.9e-3 off at 9.7 of its standard errors,
        # where the DIC stage's own errors covered its error)
        warnings.warn(
            f"The full-field stage was skipped: the DIC stage left {', '.join(loose)} "
            f"undetermined (standard errors above {guard[loose[0]]:g}); "
            "the patterns are too noisy or too few for the geometry",
            UserWarning,
            stacklevel=3,
        )
        full_field = False
    adequacy = {}
    if full_field:
        # What the DIC stage's patterns determine with a free rotation each:
        # the crystal model's standard errors are never below it
        free_se = None if problem.crystal is None else _free_errors(problem, outcome.state)
        ff = _full_field(
            problem,
            outcome.state,
            orientation_prior,
            1 + max((h["iteration"] for h in outcome.history), default=-1),
            progress.write,
            statistical,
            free_se,
            outcome.variants_best,
        )

        def checked_against(dic_problem, geometry, rotations):
            # The full field against the DIC stage's step from *geometry*,
            # measured again with *dic_problem*'s simulations
            state = _State.measure(dic_problem, geometry, rotations)
            update = _dic_step(dic_problem, state, orientation_prior)[0]
            return _adequacy(problem, ff.geometry, ff.standard_errors, ff.held, geometry, update)

        if ff.lattice is None:
            adequacy = _adequacy(
                problem, ff.geometry, ff.standard_errors, ff.held, outcome.state.geometry,
                dic_update,
            )  # fmt: skip
        else:
            # The DIC stage's solution at the lattice fitted: at the CIF's
            # it is biased by the difference the full field fitted
            at_fit = replace(problem, stretch=1 + ff.lattice["stretch"])
            adequacy = checked_against(at_fit, outcome.state.geometry, outcome.state.rotations)
        if not adequacy["consistent"] and free_se is None and ff.psf >= PSF_NEGLIGIBLE:
            # Before anything is raised, the DIC evidence again at the full
            # field's solution against simulations blurred as the full field
            # found the camera's: plain ones bias it by the blur (model
            # family, 10,000 counts/px from the truth: pcz -7e-5 at 4 of its
            # standard errors for 0.6 px; blurred alike within 1e-5), which
            # raised the model family's pcz 4-6x above the bound. Not on one
            # crystal, whose full field estimates the blur of high-passed
            # patterns: there the blurred DIC stage disagreed more (a single
            # Ni crystal's pcx step from 4.6e-3 to 7.2e-3, 3.5e-4 off)
            blurred = replace(problem, point_spread=ff.psf)
            adequacy = checked_against(blurred, ff.geometry, ff.rotations)
        adequacy["systematic"] = ff.systematic
        if ff.lattice is not None:
            adequacy["lattice"] = ff.lattice
        # The DIC field stays the last one measured, the DIC stage's:
        # measuring it again at the full field's solution, which is within
        # the basin of it, cost a sixth of the calibration
        state = replace(
            outcome.state,
            geometry=ff.geometry,
            rotations=ff.rotations,
            scores=problem.ncc(ff.geometry, ff.rotations),
        )
        progress.write(f"  {adequacy['verdict']}")
        if not adequacy["consistent"]:
            warnings.warn(adequacy["verdict"], UserWarning, stacklevel=3)
        outcome = replace(outcome, state=state, history=outcome.history + ff.history)
        # The spread over parts of the map (a polycrystal's grains, one
        # crystal's quadrants) with a prior (_with_prior): the DIC stage's
        # statistical variance, or with the crystal model what the DIC
        # stage's patterns determine with a free rotation each. The
        # crystal model's angles are never below the latter: the tie to one
        # parent, which a shared misfit can fit, determines them (a 2 mm
        # domain map: the tilt 0.90 deg off at 0.09 deg without)
        standard_errors = _inflated(ff.standard_errors, adequacy)
        if free_se is None:
            prior, parts = {k: v for k, v in statistical.items() if k in _PC}, ff.grains
            weight = PRIOR_PARTS
        else:
            prior, parts = _named_errors(problem.parameters, free_se), REGIONS[0] * REGIONS[1]
            weight = CRYSTAL_PRIOR_PARTS
        standard_errors = {
            k: _with_prior(v, prior[k], parts, weight) if k in _PC and k in prior
            else max(v, prior.get(k, 0.0))
            for k, v in standard_errors.items()
        }  # fmt: skip
    return outcome, standard_errors, adequacy


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
    #: The systematic part of *standard_errors* (:func:`_region_errors`)
    systematic: dict[str, float] | None = None
    #: The lattice fitted (:meth:`_Problem.lattice_result`), if it was
    lattice: dict[str, Any] | None = None
    #: The effective number of grains of a polycrystal's systematic part
    #: (:func:`_grain_errors`); infinite on one crystal
    grains: float = np.inf
    #: The detector's point spread it estimated (px, :class:`_Processing`)
    psf: float = 0.0


def _full_field(
    problem, state, prior, first_it, report, dic_errors=None, free_se=None, variants_best=False
) -> _FullField:
    """Gauss-Newton on the pixel intensities from where the DIC stage
    converged: the geometry and one rotation per pattern, the rotations
    eliminated by the Schur complement of :func:`solve_joint`, each
    pattern's gain and offset projected out, each pixel weighted by the
    inverse of its noise variance (:func:`_pixel_variances`), the model
    made as the patterns were (:class:`_Processing`, estimated from them),
    with the crystal model both compared high-passed (:func:`_compared`).

    Parameters the full field determines poorly (standard error above
    :data:`DETERMINACY_LIMITS`) follow the DIC stage's rule: they keep
    their value unless the full field moved them by :data:`SIGNIFICANCE`
    standard errors or more; if not, they are put back (:func:`_hold`)
    (measured on processed Ni maps: free, the tilt moved 1.3 deg away from
    the truth on a standard error of 0.5 deg). The move is judged after
    convergence: a first step fell short of three standard errors where
    the whole move did not (a tilt 0.4 deg off, 0.29 +- 0.10 deg). The
    result is checked against the DIC stage afterwards (:func:`_adequacy`).
    Angles whose DIC stage standard errors (*dic_errors*) exceed
    :data:`UNDETERMINED_RANGE` are held from the start: free,
    the first step took the azimuthal of a 65 um BaTiO3 map 20 deg away
    and ended the full field there. With the crystal model, a move is
    judged against at least the DIC stage's standard errors with a free
    rotation per pattern (*free_se*, solved order): the angles are then
    determined by the tie to one parent, which a misfit all patterns
    share can fit (a BaTiO3 domain map from another simulator's data,
    500 counts/px: the tilt moved from 0.9 to 2.8 deg off at 3.2 of the
    full field's standard errors; free rotations: 3.8 deg).
    """
    names = problem.parameters
    solved, split = solved_parameters(names)
    k = len(solved)
    start = state.geometry
    if problem.pseudo_symmetry_ops is not None and not variants_best:
        # Each pattern fitted with the variant it shows: the DIC stage
        # chooses them only once in the basin, so one that stopped short of
        # it left the starts' (on a BaTiO3 domain map from users' starts,
        # a random variant per point: the PC ended 4.7e-3 off at 18
        # standard errors; within two with the variants chosen here).
        # Where it ended on a choice that changed nothing, they are so
        # already
        state = replace(state, rotations=problem.best_variants(start, state.rotations))
    processing = _estimate_processing(problem, problem.arrays, start, state.rotations)
    history = []
    dic_errors = dic_errors or {}
    # With the crystal model, an angle judged against a free_se it cannot
    # move three of within UNDETERMINED_RANGE is held at the end whatever it
    # does: free until then, it drags the parent and the PC along the valley
    # they share, and holding it after a far move is a linear guess (240 px
    # domain map, the map's mean divided out, angles right at the start:
    # tilt and azimuthal 7 and 6 deg off in two steps, put back, pcx
    # 1.1e-3 off at 5.9 standard errors; held throughout 4.1e-4 at 0.9)
    unkeepable = () if free_se is None else _unkeepable(solved, free_se)
    unseen = tuple(
        n
        for n in solved
        if n not in _PC
        and (
            n in unkeepable
            or dic_errors.get(TILT_DIFFERENCE if n in ("tilt", "sample_tilt") else n, 0)
            > UNDETERMINED_RANGE
        )
    )
    gn = functools.partial(
        _gauss_newton,
        solved=solved, split=split, held=unseen, processing=processing, prior=prior,
        history=history, report=report,
    )  # fmt: skip
    geometry, rotations, cov, system, (stretch, stretch_se, slope) = gn(
        problem, state, first_it=first_it
    )
    if problem.pseudo_symmetry_ops is not None and abs(stretch - 1) > VARIANTS_AGAIN:
        # The variants chosen at the CIF's lattice, again at the one fitted:
        # a c/a nearer 1 than the CIF's makes 90 deg variants alike, and a
        # wrong one pulls the lattice on (a domain map of c/a 0.6 % below
        # the CIF's: the stretch walked to -2 %, PC 5.8e-3 off)
        at_fit = replace(problem, stretch=stretch)
        again = at_fit.best_variants(geometry, rotations)
        if not np.array_equal(again.data, rotations.data):
            report("  variants chosen again at the fitted lattice")
            geometry, rotations, cov, system, (stretch, stretch_se, slope) = gn(
                at_fit,
                replace(state, geometry=geometry, rotations=again),
                first_it=first_it + len(history),
            )
    # The systematic part first: an angle it leaves undetermined is held
    # at its start like one the statistics leave undetermined. One crystal:
    # the detector's quadrants. A polycrystal: its grains, each sharing a
    # bias; its quadrants, each with a rotation per pattern, are too weak
    # a fit for their spread to be believed (it raised pcz's error 4.7x)
    systematic, grains = np.zeros(len(solved)), np.inf
    if system is not None and not system.common:
        systematic, grains = _grain_errors(
            system.normal,
            system.residual,
            system.offsets,
            problem.grains(np.asarray(system.rotations.flatten().data)),
        )
    elif system is not None:
        systematic = _region_errors(
            system.residual,
            system.jg,
            system.jr,
            system.weights,
            system.offsets,
            _prior_per_axis(prior),
            system.common,
            _quadrants(problem.experimental.shape[1:]),
            system.geometry_prior,
            system.geometry_offsets,
            system.normal,
        )
    # The lattice's part (its stretch solved last) apart
    lattice_sys = float(systematic[k]) if len(systematic) > k else 0.0
    if problem.lattice_prior is not None:
        lattice_sys = float(np.hypot(lattice_sys, LATTICE_RESOLUTION))
    systematic = systematic[:k]
    se = np.sqrt(np.clip(np.diag(cov), 0, None) + systematic**2)
    moved = _solved_values(geometry, solved, split) - _solved_values(start, solved, split)
    judged = se if free_se is None else np.maximum(se, free_se)
    held = tuple(dict.fromkeys(unseen + _insignificant_moves(solved, judged, moved)))
    if held and system is not None:
        geometry, rotations, cov, lattice_hold = _hold(system, held, start, solved, split, cov)
        systematic[[solved.index(n) for n in held]] = 0.0
        if lattice_hold is not None:
            step, stretch_se, slope = lattice_hold
            stretch += step
    # The stretch's systematic part carries the geometry along their
    # valley: the quadrants scatter the stretch along it, not the PC (one
    # BaTiO3 crystal whose c/a is 0.6 % below the CIF's: the stretch
    # 0.37 % short at 0.13 %, pcz 2.1e-3 off at 1.3e-4 without it)
    stretch_se = float(np.hypot(stretch_se, lattice_sys))
    systematic = np.hypot(systematic, slope * lattice_sys)
    cov = cov + np.diag(systematic**2)
    se = _named_errors(names, np.sqrt(np.clip(np.diag(cov), 0, None)))
    lattice = None
    if problem.lattice_prior is not None:
        lattice = problem.lattice_result(stretch, stretch_se)
    return _FullField(
        geometry,
        rotations,
        se,
        history,
        held,
        _named_errors(names, systematic),
        lattice,
        grains,
        processing.psf,
    )


def _gauss_newton(
    problem, state, solved, split, held, processing, prior, first_it, history, report
):
    """The full field's iterations from *state* with the parameters *held*
    fixed; returns the geometry, the rotations and the covariance of all
    *solved* parameters (cluster-robust over the patterns) at the end,
    the last linear :class:`_System` and the lattice's stretch of the c
    axis with its standard error and the geometry's regression on it (1,
    0 and zeros where it is not fitted, :attr:`_Problem.lattice_prior`).

    With a lattice prior the stretch is one more column (after the
    geometry's), the patterns simulated from the master pattern at the
    current stretch, the prior holding it about the CIF's lattice."""
    lattice = problem.lattice_prior
    fit_lattice = lattice is not None
    k = len(solved)
    geo_prior = None if not fit_lattice else np.r_[np.full(k, np.inf), lattice]
    stretch = problem.stretch
    prior_rad = _prior_per_axis(prior)
    common = problem.crystal is not None
    geometry, rotations = state.geometry, state.rotations
    free = [i for i, nm in enumerate(solved) if nm not in held]
    # The stretch is solved with the free parameters
    cols = free + [k] if fit_lattice else free
    chi2_prev, weights, last, cov, system = np.inf, None, None, None, None
    chi2_before, stale, used_fresh = np.inf, False, True
    for it in range(CRYSTAL_FULL_FIELD_ITERATIONS if common else FULL_FIELD_ITERATIONS):
        # The Jacobians of the first step serve the next steps (in the
        # basin they hardly change; building them is most of the cost):
        # those simulate the patterns only, unless the last step lowered
        # chi2 by a large fraction (far from the solution, as after a
        # change of variants, the first Jacobians converged slowly) or
        # went uphill with them or moved a parameter by more than its
        # standard error (crystal model: along the valley where a PC change
        # is nearly the parent's rotation, a domain map's pcx came 5.4e-3
        # to 5.5e-4 in five steps, 0.7 of the way each, chi2 hardly lower)
        refresh = it == 0 or stale or chi2_before - chi2_prev > JACOBIAN_REFRESH * chi2_before
        stale = False
        arrays = problem.lattice_arrays(stretch)
        residual, j_geo, j_rot, var = _intensity_system(
            problem, arrays, geometry, rotations, solved, processing, refresh, fit_lattice,
            weights is None,
        )  # fmt: skip
        if weights is None:
            # Weights fixed at the first step, so that chi2 compares steps
            weights = 1 / var
        if refresh:
            jg, jr = j_geo, j_rot
            # Jacobians and weights fixed until the next refresh: their
            # normal equations serve every residual until then
            all_free = JointSystem.build(
                jg, jr, weights, prior_rad, common=common, geometry_prior=geo_prior
            )
            some_free = all_free
            if free and len(free) < len(solved):
                # The free columns' alone, from the same weighted stack
                some_free = all_free.columns(cols, None if geo_prior is None else geo_prior[cols])
        offsets = problem.rotation_offsets(rotations)
        at = None if not fit_lattice else np.r_[np.zeros(k), stretch - 1]
        full = all_free.solve(residual, offsets, geometry_offsets=at)
        if full.chi2 > chi2_prev:
            # The last step went uphill: undo it and stop, unless, with
            # the crystal model, it was made with older Jacobians than its
            # start's. There the parent's rotation moves every pattern at
            # once: a domain map's second step from 1.3e-3 off went uphill
            # and the PC stopped 3.2e-4 off, the fixed point from the truth
            # 7e-5 off. With free rotations, stepping again moved
            # polycrystals' errors both ways, 4-8 % larger in sum
            # (benchmarks/experiments/README.md)
            history[-1]["accepted"] = False
            geometry, rotations, stretch = last
            if common and not used_fresh:
                stale = True
                continue
            break
        used_fresh = refresh
        system = _System(
            geometry,
            rotations,
            residual,
            jg,
            jr,
            weights,
            offsets,
            common,
            all_free,
            geo_prior,
            at,
        )
        # Cluster-robust over the patterns, as the DIC stage's: pixels of
        # a pattern share its misfit (blur, interpolation), which the
        # white-noise model the bound is made of misses (measured: 2-3 %
        # larger on 121 Ni patterns, and one azimuthal error at 3.0 model
        # standard errors over nine maps)
        cov = full.covariance
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        if not free:
            break
        if some_free is all_free:
            upd = full
        else:
            upd = some_free.solve(
                residual, offsets, geometry_offsets=None if at is None else at[cols]
            )
        # The stretch's signature is linear over a tenth of a percent only
        # (sharp bands): a longer step is cut there, the whole step with it
        step_lattice = float(upd.delta[-1]) if fit_lattice else 0.0
        cut = min(1.0, LATTICE_STEP / abs(step_lattice)) if step_lattice else 1.0
        step_lattice *= cut
        delta = dict(zip([solved[i] for i in free], (cut * float(d) for d in upd.delta)))
        chi2_before, chi2_prev, last = chi2_prev, full.chi2, (geometry, rotations, stretch)
        geometry = geometry.updated(_expand(delta, split))
        rotations = rotations * rotations_from_vectors(cut * upd.rotations)
        stretch += step_lattice
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
            + ("" if processing.static else ", static background left in")
            + (f", held {', '.join(held)}" if held else "")
            + (f", c axis stretch {stretch - 1:+.2e}" if fit_lattice else "")
        )
        # Steps this small leave the covariance as it was; the
        # orientations, refined here too, must have settled as well (with
        # the first step's Jacobians they converge more slowly: a
        # noise-free BaTiO3 map ended 0.052 deg off on average, at 0.05)
        rotation_step = np.rad2deg(np.sqrt((upd.rotations**2).sum(axis=-1)).max())
        if (
            rotation_step <= FULL_FIELD_ROTATION_STOP
            and all(abs(delta[solved[i]]) <= FULL_FIELD_STOP * se[i] for i in free)
            and abs(step_lattice) <= FULL_FIELD_STOP * se[-1]
        ):
            break
        stale = cut < 1 or (
            common
            and (any(abs(delta[solved[i]]) > se[i] for i in free) or abs(step_lattice) > se[-1])
        )
    lattice_se, slope = 0.0, np.zeros(k)
    if fit_lattice and cov is not None:
        lattice_se = float(np.sqrt(max(cov[k, k], 0.0)))
        # The geometry's regression on the stretch: where they share a
        # valley, an error of the stretch is the geometry's too
        slope = cov[:k, k] / cov[k, k] if cov[k, k] > 0 else slope
        cov = cov[:k, :k]
    return geometry, rotations, cov, system, (stretch, lattice_se, slope)
