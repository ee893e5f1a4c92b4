"""Standard errors, determinacy and adequacy: how well the map determines
each parameter (:data:`DETERMINACY_LIMITS`, :data:`SIGNIFICANCE`,
:data:`UNDETERMINED_RANGE`), the DIC stage's standard errors and the check
of the full field against the DIC stage (:data:`ADEQUACY_LIMIT`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from kikuchipy_geomdic.calibration._dic_fit import (
    _joint_solve,
    _linearise,
    _pattern_weights,
    _prior_per_axis,
    _solved_values,
)
from kikuchipy_geomdic.calibration._problem import _Problem, _State
from kikuchipy_geomdic.calibration._systematic import (
    _grain_errors,
    _quadrants,
    _region_errors,
)
from kikuchipy_geomdic.calibration.solve import JointSystem, JointUpdate
from kikuchipy_geomdic.geometry import MapGeometry, solved_parameters

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

#: A poorly determined angle is not moved farther than this (deg) from its
#: start: a microscope's stage and detector readouts are good to a degree or
#: two (the benchmarks' starts are 0.75-1.8 deg off), and a farther move of
#: an angle the map hardly determines was the model's misfit (on one
#: crystal at 30 counts/px, the tilt difference 9.6 deg off at "4.4
#: standard errors", every point of the reindexed map wrong, 73 of them
#: with ``converged`` = 1).
UNDETERMINED_RANGE = 5.0

_PC = ("pcx", "pcy", "pcz")

#: Name of the determined combination of the two equivalent tilts.
TILT_DIFFERENCE = "tilt-sample_tilt"

#: The full field passes its adequacy check when the step the DIC stage
#: would take from the full field's solution is below this many of their
#: combined standard errors for every parameter either determines.
ADEQUACY_LIMIT = 3.0


def _insignificant_moves(solved: Sequence[str], se, moved) -> tuple[str, ...]:
    """The angles among *solved* (standard errors *se*, moves *moved* from
    their start, both in *solved*'s order) that the map determines poorly
    (above :data:`DETERMINACY_LIMITS`) and that moved by less than
    :data:`SIGNIFICANCE` standard errors, or by more than
    :data:`UNDETERMINED_RANGE`: the data did not move them."""
    return tuple(
        n
        for n, sg, d in zip(solved, se, moved)
        if n not in _PC
        and sg > DETERMINACY_LIMITS[n]
        and not SIGNIFICANCE * sg <= abs(d) <= UNDETERMINED_RANGE
    )


def _unkeepable(solved: Sequence[str], se) -> tuple[str, ...]:
    """The angles among *solved* (standard errors *se*, in its order) that
    :func:`_insignificant_moves` holds whatever they do: three standard
    errors reach beyond :data:`UNDETERMINED_RANGE`."""
    return tuple(
        n for n, sg in zip(solved, se) if n not in _PC and SIGNIFICANCE * sg > UNDETERMINED_RANGE
    )


def _named_errors(names: Sequence[str], solved_errors) -> dict[str, float]:
    """Standard errors of the parameters *names* and of the determined tilt
    difference, from *solved_errors*, those of the solved parameters
    (:func:`~kikuchipy_geomdic.geometry.parameters.solved_parameters`)."""
    solved, split = solved_parameters(names)
    se = dict(zip(solved, map(float, solved_errors)))
    if "tilt" in names or "sample_tilt" in names:
        se[TILT_DIFFERENCE] = se["tilt" if "tilt" in solved else "sample_tilt"]
    for name, base in split.items():
        # Only their difference is determined
        se[name] = se[base] = float("inf")
    return {k: se[k] for k in (*names, TILT_DIFFERENCE) if k in se}


def _dic_step(problem: _Problem, state: _State, prior) -> tuple[JointUpdate, Any, Any, Any]:
    """The DIC stage's joint solve with every parameter free at *state*
    (the step it would take from there and its statistical standard
    errors), with its linear system, rotation offsets and the components'
    variances."""
    solved, _ = solved_parameters(problem.parameters)
    linear = _linearise(problem, state.geometry, state.field, solved)
    offsets = problem.rotation_offsets(state.rotations)
    update, var = _joint_solve(
        state.field,
        linear,
        range(len(solved)),
        offsets,
        _prior_per_axis(prior),
        0.0,
        problem.crystal is not None,
    )
    return update, linear, offsets, var


def _dic_update(problem: _Problem, state: _State, prior) -> tuple[JointUpdate, np.ndarray]:
    """The DIC stage's joint solve at *state* (:func:`_dic_step`) and the
    systematic standard errors (K,) that add to its statistical ones:
    the grains' spread (:func:`_grain_errors`) or, with the crystal
    model, the detector quadrants' (:func:`_region_errors`)."""
    update, linear, offsets, var = _dic_step(problem, state, prior)
    jg, jr, b = linear
    if problem.crystal is None:
        # A polycrystal: what each grain's patterns share, from the
        # grains' spread (as the full field's)
        w = _pattern_weights(state.field, var)
        system = JointSystem.build(jg, jr, w, _prior_per_axis(prior))
        q = np.asarray(state.rotations.flatten().data)
        return update, _grain_errors(system, b, offsets, problem.grains(q))[0]
    # One crystal: what the patterns share, from the ROIs' quadrants (as
    # the full field's pixels'). Without it the DIC stage's errors missed
    # a shared misfit by 8-10 of them on a BaTiO3 domain map whose DIC
    # stage stalled outside the full field's basin
    sys = _region_errors(
        b,
        jg,
        jr,
        _pattern_weights(state.field, var),
        offsets,
        _prior_per_axis(prior),
        True,
        _quadrants(state.field.rois, 2),
    )
    return update, sys


def _free_errors(problem: _Problem, state: _State) -> np.ndarray:
    """The DIC stage's statistical standard errors (K,) at *state* with a
    free rotation per pattern and no prior: what the patterns determine
    without the crystal model's tie; measured on the patterns as they are
    (:meth:`_Problem.recorded_field`)."""
    solved, _ = solved_parameters(problem.parameters)
    field = state.field
    if problem.bands_put_back:
        field = problem.recorded_field(state.geometry, state.rotations)
    linear = _linearise(problem, state.geometry, field, solved)
    offsets = np.zeros((state.rotations.size, 3))
    update, _ = _joint_solve(field, linear, range(len(solved)), offsets, None, 0.0, False)
    return update.standard_errors


def _dic_errors(
    problem: _Problem, state: _State, prior
) -> tuple[JointUpdate, dict[str, float], dict[str, float]]:
    """The DIC stage's joint solve at *state* (:func:`_dic_update`) and the
    standard errors of every refined parameter and of the determined tilt
    difference: statistical, and with the systematic part."""
    update, systematic = _dic_update(problem, state, prior)
    names = problem.parameters
    return (
        update,
        _named_errors(names, update.standard_errors),
        _named_errors(names, _total(update, systematic)),
    )


def _total(update: JointUpdate, systematic: np.ndarray) -> np.ndarray:
    """Standard errors (K,) of *update* with the *systematic* ones added."""
    return np.sqrt(update.standard_errors**2 + systematic**2)


def _adequacy(
    problem: _Problem,
    geometry: MapGeometry,
    standard_errors: dict[str, float],
    held: Sequence[str],
    dic_geometry: MapGeometry,
    update: JointUpdate,
) -> dict[str, Any]:
    """Whether the full field's solution (its *geometry*, *standard_errors*
    and the parameters it *held*) agrees with the DIC evidence.

    A misfit every pattern shares (ghost bands, band profiles changed by
    the processing, another simulator's master pattern) biases the full
    field, which compares intensities, more than the DIC stage, which
    tracks where features are; no variance over the patterns can see it.
    The DIC stage's solution can: *dic_geometry*, where it ended, plus
    its last step *update* (in the full field's basin the linear step is
    the DIC's fixed point to well within its standard errors; measured
    again at the full field's solution instead, every PC error and
    standard error of the realistic benchmark's 9 maps came out the
    same). Its difference from the full field's is noise of the DIC's
    standard errors where both are right. Each parameter that neither
    stage leaves undetermined enters, in units of the two standard
    errors combined."""
    solved, split = solved_parameters(problem.parameters)
    steps = (
        _solved_values(dic_geometry, solved, split)
        + update.delta
        - _solved_values(geometry, solved, split)
    )
    z, dic_step = {}, {}
    for name, step, se_dic in zip(solved, steps, update.standard_errors):
        key = TILT_DIFFERENCE if name in ("tilt", "sample_tilt") else name
        se_ff = standard_errors.get(key, np.inf)
        if name in held or max(se_dic, se_ff) > DETERMINACY_LIMITS[name]:
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
