"""The paper's solver (``solver="paper"``): its loop (:func:`_paper_loop`)
and state.

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

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._dic_fit import DAMPING_FACTOR, MAX_TRIALS
from kikuchipy_geomdic.calibration._problem import _LoopOutcome, _Problem, _State, _step_record
from kikuchipy_geomdic.calibration._progress import _Progress
from kikuchipy_geomdic.calibration.solve import solve_update
from kikuchipy_geomdic.geometry import MapGeometry, rotation_vectors, rotations_from_vectors

#: Paper solver: an accepted step that gains less NCC than
#: ``ncc_tolerance`` and lowers the mean displacement by less than this
#: fraction ends the loop: the displacement no longer falls by 10 %.
PAPER_MIN_FALL = 0.1

#: Paper solver: a point whose refined orientation lies further than this
#: (degrees) from its start is no small deviation (another variant not
#: among the operators, or a failed refinement) and is left out of the
#: mean rotation removed by the anchoring.
ANCHOR_MAX_ANGLE = 5.0


@dataclass(frozen=True)
class _PaperState(_State):
    """The paper solver's state: *rotations* are the anchored ones the
    field is measured with, *refined* those kikuchipy refined at
    *geometry* (their mean NCC *ncc*); *disp* is the objective."""

    refined: Rotation
    ncc: float
    disp: float


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
