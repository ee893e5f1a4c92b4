"""A calibration of several phases as one-phase problems: the points of
each phase (:func:`_sub_problems`) and what a question asked of every
point (refinement, variants, grains) answers when each phase answers it
for its own points (:func:`_by_phase`). Projection needs none of this:
its arrays know each point's phase
(:class:`~kikuchipy_geomdic.indexing._projection.PhaseArrays`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._crystal import NotOneCrystalError
from kikuchipy_geomdic.calibration._systematic import _grains


def _sub_problems(problem) -> list:
    """(rows, one-phase problem of those points) per phase with points."""
    out = []
    for k, p in enumerate(problem.phases):
        rows = np.flatnonzero(problem.point_phase == k)
        if not rows.size:
            continue
        background = problem.background
        sub = replace(
            problem,
            experimental=problem.experimental[rows],
            points=problem.points[rows],
            start_rotations=problem.start_rotations[rows],
            master_pattern=p.master_pattern,
            phase=p.phase.deepcopy(),
            pseudo_symmetry_ops=p.pseudo_symmetry_ops,
            phases=(p,),
            point_phase=np.zeros(rows.size, dtype=np.int64),
            background=background,
        )
        out.append((rows, sub))
    return out


def _by_phase(problem, ask, rotations: Rotation, *more):
    """``ask(sub, rotations[rows], *more[rows])`` of each phase's
    one-phase problem, its answers (arrays, Rotations or tuples of them)
    put back in the points' order."""
    answers = [
        (rows, ask(sub, rotations[rows], *(m[rows] for m in more)))
        for rows, sub in problem.sub_problems
    ]
    first = answers[0][1]
    if isinstance(first, tuple):
        return tuple(
            _joined([(rows, a[i]) for rows, a in answers], rotations.size)
            for i in range(len(first))
        )
    return _joined(answers, rotations.size)


def _joined(parts, n: int):
    """Per-phase answers ``[(rows, answer)]`` as one in the points' order."""
    first = parts[0][1]
    if isinstance(first, Rotation):
        q = np.empty((n, 4))
        for rows, a in parts:
            q[rows] = a.data.reshape(-1, 4)
        return Rotation(q)
    a0 = np.asarray(first)
    out = np.empty((n,) + a0.shape[1:], dtype=a0.dtype)
    for rows, a in parts:
        out[rows] = np.asarray(a)
    return out


def _best_variants(problem, geometry, rotations: Rotation) -> Rotation:
    """Each phase's points in the variant their patterns show; the very
    *rotations* where no point changes (the DIC stage compares them)."""
    chosen = _by_phase(problem, lambda sub, r: sub.best_variants(geometry, r), rotations)
    # orix renormalises every Rotation it makes, the phases' slices and
    # their join too: where no point changed they differ from *rotations*
    # in the last bits, and the DIC stage, comparing bits, re-measured and
    # stepped on until its iterations ran out (measured on the iron maps
    # of bench_multiphase.py: 10 steps against the one-phase solve's 3, a
    # random walk of the PC at the NCC's noise, 2.5x the CPU time). A
    # changed variant moves a point by degrees, not 1e-12
    if np.allclose(chosen.data, rotations.data, rtol=0.0, atol=1e-12):
        return rotations
    return chosen


def _grain_labels(problem, q: np.ndarray) -> np.ndarray:
    """Grain labels (N,) of the orientations *q* (N, 4): the grains of each
    phase under its own symmetry, numbered across phases."""
    out = np.empty(len(q), dtype=np.int64)
    offset = 0
    for rows, sub in problem.sub_problems:
        labels = _grains(q[rows], sub.grain_group)
        out[rows] = labels + offset
        offset += int(labels.max()) + 1
    return out


def _point_phases(phases, ops, ids) -> tuple[tuple, np.ndarray]:
    """The *phases* with their operators flattened (the first one's
    *ops*, which may come from ``refine_kwargs``), and the index into
    them (N,) of each point's crystal map phase id in *ids*."""
    own = [ops] + [p.pseudo_symmetry_ops for p in phases[1:]]
    phases = tuple(
        replace(p, pseudo_symmetry_ops=None if o is None else Rotation(o).flatten())
        for p, o in zip(phases, own)
    )
    index = {p.phase_id: k for k, p in enumerate(phases)}
    return phases, np.array([index[int(i)] for i in ids], dtype=np.int64)


def _several_phases(orientation_model: str | None, phases) -> None:
    """None, the orientation model of points of several *phases*: a
    rotation per point, not tested for one crystal (they are not one);
    raise for the crystal model."""
    if orientation_model == "crystal":
        raise NotOneCrystalError(
            f"orientation_model='crystal' was asked of points of {len(phases)} phases "
            f"({', '.join(p.name for p in phases)}): one crystal is of one phase. Calibrate "
            "with orientation_model='free', or with one phase's master pattern"
        )
    return None


def _any_operators(phases) -> Rotation | None:
    """The first phase's operators that exist, or None: with several
    phases it says only whether any phase has variants (each phase's own
    are in :attr:`_Problem.phases`)."""
    ops = [p.pseudo_symmetry_ops for p in phases if p.pseudo_symmetry_ops is not None]
    return ops[0] if ops else None
