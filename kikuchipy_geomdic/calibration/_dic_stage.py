"""The DIC stage: the joint solver's loop (:func:`_joint_loop`, one
:func:`_joint_step` per iteration) and the choice between it and the
paper's (:func:`_dic_stage`).

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

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from kikuchipy_geomdic.calibration._dic_fit import (
    DAMPING_FACTOR,
    MAX_TRIALS,
    MIN_RETRY_DAMPING,
    PAPER_DAMPING,
    _expand,
    _joint_solve,
    _linearise,
    _prior_per_axis,
    _solved_values,
)
from kikuchipy_geomdic.calibration._paper import _paper_loop
from kikuchipy_geomdic.calibration._problem import _LoopOutcome, _Problem, _State, _step_record
from kikuchipy_geomdic.calibration._progress import _Progress
from kikuchipy_geomdic.calibration.solve import JointUpdate
from kikuchipy_geomdic.calibration.uncertainty import (
    _PC,
    DETERMINACY_LIMITS,
    SIGNIFICANCE,
    UNDETERMINED_RANGE,
    _insignificant_moves,
)
from kikuchipy_geomdic.geometry import MapGeometry, rotations_from_vectors, solved_parameters
from kikuchipy_geomdic.patterns import displacement as dsp

#: A step that lowers the displacement by less than this fraction ends
#: the joint loop: the measurement's noise floor is reached.
MIN_FALL = 0.1

#: An RMS displacement (px) the DIC stage ends above means its features
#: were not matched, and the geometry it reports is not determined by
#: them. Measured at the end (unweighted RMS): BaTiO3 domain maps of 120
#: px from users' starts 2.6 px at 150 counts/px (PC 3.4e-3 off, covered),
#: 5.3-6.1 px at 30 (PC 6.5e-3 to 1.9e-2 off, once at 4.4 standard
#: errors); Si at 0.3 counts/px 5.6 px; kikuchipy's real Ni patterns of
#: 60 px 1.8 px; realistic Ni maps of 96 px under 0.6 px
UNMATCHED_RMS_PX = 4.0


def _check_matched(
    outcome: _LoopOutcome, explain: Callable[[], str] | None = None
) -> tuple[_LoopOutcome, bool]:
    """*outcome*, not converged and with a warning, if its last field's RMS
    displacement is above :data:`UNMATCHED_RMS_PX`; and whether it is
    below (the features matched). *explain*, called only then, may add
    the cause to the warning."""
    field = outcome.state.field
    rms = _rms_displacement(field) * field.shape[1]
    if not rms > UNMATCHED_RMS_PX:
        return outcome, True
    cause = explain() if explain is not None else ""
    warnings.warn(
        f"The DIC stage ended with an RMS displacement of {rms:.1f} px (above "
        f"{UNMATCHED_RMS_PX:g} px): the simulated and the recorded features "
        "did not match (patterns too noisy for DIC, or orientations or variants far off), so "
        "the geometry is not determined by them; the result is marked not converged"
        + (f". {cause}" if cause else ""),
        UserWarning,
        stacklevel=3,
    )
    return replace(outcome, converged=False), False


def _dic_stage(
    problem: _Problem,
    progress: _Progress,
    basin: float,
    *,
    geometry0: MapGeometry,
    solver: str,
    jacobian: str,
    prior: float | None,
    damping: float | None,
    max_iterations: int,
    ncc_tolerance: float,
) -> _LoopOutcome:
    """The DIC stage from *geometry0*: the joint loop, which ends once the
    RMS displacement is below *basin*, or the paper's; *damping* None is
    each solver's default."""
    if solver == "joint":
        return _joint_loop(
            problem,
            geometry0,
            prior,
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
    fixed
        Parameters kept at their start throughout (see :func:`_joint_loop`).
    standard_errors
        Of each solved parameter at the last linearisation (None before).
    """

    state: _State
    damping: float
    hold: bool = True
    settled: bool = False
    kept: tuple[str, ...] | None = None
    moved: tuple[str, ...] = ()
    fixed: tuple[str, ...] = ()
    standard_errors: dict[str, float] | None = None


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
    solved: Sequence[str], update: JointUpdate, carry: _JointCarry, one_crystal: bool = False
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
    not be kept because its sigma there is large. On *one_crystal* (the
    crystal model) a poorly determined angle never leaves its start here:
    the angles are then seen through the tie to one parent, which a misfit
    all patterns share can fit, so a "significant" step is no evidence (a
    domain map of 96 x 128 px patterns: the tilt from 0.9 to 3.6 deg off,
    accepted at 3.1 standard errors); the full field judges them against
    the free-rotation standard errors."""
    se = dict(zip(solved, update.standard_errors))
    step = dict(zip(solved, update.delta))
    poor = [n for n in solved if se[n] > DETERMINACY_LIMITS[n] and n not in carry.moved]
    hold = carry.hold and not carry.settled
    weak = [n for n in poor if n not in _PC] if hold else []
    if not hold or len(weak) == len(solved):
        # Nothing else to settle first: significance alone decides
        hold = False
        weak = [n for n in poor if abs(step[n]) < SIGNIFICANCE * se[n]]
    if one_crystal:
        weak += [n for n in poor if n not in _PC]
    weak = [n for n in solved if n in weak or n in carry.fixed]
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
    common = problem.crystal is not None
    update, var = _joint_solve(
        state.field, linear, range(len(solved)), offsets, prior_rad, 0.0, common
    )
    hold, weak, free, released = _choose_free(solved, update, carry, one_crystal=common)
    carry = replace(carry, hold=hold, standard_errors=dict(zip(solved, update.standard_errors)))
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
        update, _ = _joint_solve(state.field, linear, columns, offsets, prior_rad, lam, common)
        delta = _expand(dict(zip(free, update.delta)), split)
        trial = _State.measure(
            problem,
            state.geometry.updated(delta),
            state.rotations * rotations_from_vectors(update.rotations),
        )
        after = _rms_displacement(trial.field, var)
        # A step that takes a poorly determined parameter off its start
        # must lower the displacement by more than its noise floor
        # (MIN_FALL): near the floor a consistent landing point is enough
        # for the others, but along a degenerate direction every point is
        # consistent, and any small fall is luck (on one crystal with
        # domains the azimuthal angle jumped from -0.45 to 21.6 deg,
        # judged significant, with the RMS displacement at 0.3950 ->
        # 0.3953 % of the width, and ended at 39 deg; at 30 counts/px it
        # jumped to 25.7 deg at 0.5240 -> 0.5210 % and ended at 50 deg,
        # the PC 9.5e-3 off at 19 standard errors)
        floor = (1 - MIN_FALL) if released else 1.0
        accepted = bool(after < floor * before) or (
            not released
            and after < (1 + MIN_FALL) * before
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
                replace(
                    carry, state=trial, damping=lam / DAMPING_FACTOR, settled=settled,
                    kept=weak, moved=moved,
                ),
                tuple(records),
            )  # fmt: skip
        lam = max(DAMPING_FACTOR * lam, MIN_RETRY_DAMPING)
    return _JointStep(
        replace(carry, state=state, damping=lam, settled=False, kept=weak),
        tuple(records),
        "stalled",
    )


def _joint_loop(
    problem: _Problem,
    geometry0: MapGeometry,
    prior: float | None,
    damping: float,
    max_iterations: int,
    progress: _Progress,
    basin: float = 0.0,
    fixed: tuple[str, ...] = (),
) -> _LoopOutcome:
    """The joint refinement from *geometry0* and the starting orientations:
    :func:`_joint_step` until it converges or stalls, or for
    *max_iterations*, or until the RMS displacement after a step is below
    *basin* (a fraction of the width); the parameters *fixed* kept at
    their start.

    A poorly determined angle that took a significant step is refined like
    any other from then on, but where it ends is judged too: if its whole
    move is below :data:`SIGNIFICANCE` standard errors, the data do not
    determine it and it may only have walked with the noise or with a
    common rotation of the orientations. The refinement is then run again
    from the start with it fixed (measured on a 13 x 13 BaTiO3 stripe map,
    one crystal with domains, from users' starts: the azimuthal angle
    walked from -0.45 to 17 deg, 2.8 standard errors of 6.2 deg; the PC
    ended 3.8e-3 off, and a reindex at that geometry had 151 of 169
    points wrong with ``converged`` = 1)."""
    outcome, carry = _joint_run(
        problem, geometry0, prior, damping, max_iterations, progress, basin, fixed
    )
    walked = _walked(problem, geometry0, carry)
    if not walked:
        return outcome
    progress.write(
        f"  {', '.join(walked)}: moved by less than {SIGNIFICANCE:g} standard errors of "
        f"more than its determinacy limit, or by more than {UNDETERMINED_RANGE:g} deg, so "
        "not determined by the map; refined again from the start with it held"
    )
    again, _ = _joint_run(
        problem, geometry0, prior, damping, max_iterations, progress, basin, fixed + walked
    )
    return replace(again, history=outcome.history + again.history)


def _walked(problem: _Problem, geometry0: MapGeometry, carry: _JointCarry) -> tuple[str, ...]:
    """The poorly determined angles that ended less than
    :data:`SIGNIFICANCE` standard errors from their start, but not at it,
    or farther than :data:`UNDETERMINED_RANGE`."""
    se = carry.standard_errors
    if se is None:
        return ()
    solved, split = solved_parameters(problem.parameters)
    moved = _solved_values(carry.state.geometry, solved, split) - _solved_values(
        geometry0, solved, split
    )
    walked = _insignificant_moves(solved, [se[n] for n in solved], moved)
    return tuple(
        n for n, d in zip(solved, moved) if n in walked and d != 0 and n not in carry.fixed
    )


def _joint_run(problem, geometry0, prior, damping, max_iterations, progress, basin, fixed):
    """One run of :func:`_joint_loop`'s iterations; the outcome and the
    last carry."""
    start = _State.measure(problem, geometry0, problem.start_rotations)
    carry = _JointCarry(start, damping, fixed=tuple(fixed))
    history: list[dict[str, Any]] = []
    converged = rechosen = variants_best = False
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
                converged = variants_best = True
                break
            carry = replace(carry, state=changed)
        if step.end == "stalled":
            # Nothing lowers the displacement any more. Short of the
            # basin, one crystal's points tied to the starts' variants (an
            # indexer's: random) may be what holds it; chosen once here,
            # nearer than the start, they let it go on (tutorial 03's map:
            # stalled 4e-3 off, then PC 3.9e-4 off; 7.5e-5 with it). Free
            # rotations absorb a wrong variant, and going on moved a
            # domain map's azimuthal 1.35 deg to 3.4 standard errors
            choose = problem.crystal is not None and not rechosen
            changed = _best_variant_state(problem, carry.state) if choose else None
            if changed is not None:
                rechosen = True
                carry = replace(carry, state=changed)
                continue
            variants_best = choose
            # The measurement's floor, if an earlier step got there
            converged = any(h["accepted"] for h in history)
            break
    else:
        converged = carry.settled
    outcome = _LoopOutcome(carry.state, history, converged, start.field, variants_best)
    return outcome, carry


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
    update, _ = _joint_solve(
        field, linear, range(len(free)), offsets, prior, 0.0, problem.crystal is not None
    )
    se = np.where(np.isfinite(update.standard_errors), update.standard_errors, np.inf)
    return bool(np.all(np.abs(update.delta) < SIGNIFICANCE * se))


def _within_errors(update: JointUpdate) -> bool:
    se = update.standard_errors
    return bool(np.all(np.abs(update.delta) <= np.where(np.isfinite(se), se, np.inf)))
