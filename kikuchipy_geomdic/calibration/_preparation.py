"""The refinement's problem made (:func:`_prepare_problem`): the steps
checked, the calibration points chosen across the phases, their patterns
and starting orientations read, and the starts tested for one crystal.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np
from kikuchipy.signals import EBSD
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration._checks import _check_steps
from kikuchipy_geomdic.calibration._crystal import (
    OTHER_CRYSTAL_FRACTION,
    NotOneCrystalError,
    _one_crystal,
    _other_crystal,
)
from kikuchipy_geomdic.calibration._phases import (
    _any_operators,
    _point_phases,
    _several_phases,
)
from kikuchipy_geomdic.calibration._points import _experimental, _select_points
from kikuchipy_geomdic.calibration._problem import _Problem
from kikuchipy_geomdic.calibration._processing import _bands_divided_out, _static_background
from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.geometry.maps import flat_index

#: The free orientation model warns, and "auto" takes the crystal model,
#: when at least this fraction of the starts lie within 5 deg of one
#: parent: the map looks like one crystal
#: (users' starts of BaTiO3 domain maps: 85-93 %; of a 1 mm Ni crystal 71
#: %; kikuchipy's real 3 x 3 Ni map of three grains 67 %).
ONE_CRYSTAL_NOTE = 0.7


def _prepare_problem(
    signal: EBSD,
    xmap: CrystalMap,
    phases: tuple,
    energy: float,
    names: tuple[str, ...],
    points,
    nav: tuple[int, int],
    steps: Mapping[str, float] | None,
    dic_kwargs: dict,
    refine_kwargs: Mapping[str, Any] | None,
    orientation_model: str | None = "free",
    geometry0: MapGeometry | None = None,
) -> _Problem:
    """Check the steps, select the points, read their patterns and
    starting orientations: the :class:`_Problem` the loops solve. With
    *orientation_model* "crystal" or "auto", the starts are tied to one
    parent when they are one crystal (:func:`_one_crystal`, and by their
    patterns at *geometry0*, :func:`_other_crystal`); "crystal" raises
    :class:`NotOneCrystalError` when they are not; "free" warns when they
    look like one crystal; None (the paper's solver) does neither. The
    points of several *phases* (:class:`PhaseToRefine`) are chosen
    across them and are not one crystal."""
    steps = _check_steps(names, steps)
    ref_kw = dict(refine_kwargs or {})
    ops = ref_kw.pop("pseudo_symmetry_ops", None)
    if len(phases) > 1 and ops is not None:
        raise ValueError(
            "pseudo_symmetry_ops in refine_kwargs with several master patterns: give them as "
            "pseudo_symmetry_ops, one per master pattern"
        )
    if phases[0].pseudo_symmetry_ops is not None:
        ops = phases[0].pseudo_symmetry_ops
    pts = _select_points(points, xmap, [p.phase_id for p in phases], nav)
    exp = _experimental(signal, pts, nav)
    lookup = np.full(nav[0] * nav[1], -1)
    lookup[xmap.id] = np.arange(xmap.size)
    start = Rotation(xmap.rotations.data[lookup[flat_index(pts, nav)]])
    ops = None if ops is None else Rotation(ops).flatten()
    phases, point_phase = _point_phases(phases, ops, xmap.phase_id[lookup[flat_index(pts, nav)]])
    crystal, why = None, ""
    if len(phases) > 1:
        # Free rotations, without the one-crystal test or note
        orientation_model = _several_phases(orientation_model, phases)
    if orientation_model is not None:
        crystal, why = _one_crystal(start, xmap.phases[phases[0].phase_id].point_group, ops)
    if orientation_model == "auto" and (crystal is None or crystal.fraction < ONE_CRYSTAL_NOTE):
        orientation_model = "free"
    if orientation_model == "free":
        if crystal is not None and crystal.fraction >= ONE_CRYSTAL_NOTE:
            warnings.warn(
                f"{100 * crystal.fraction:.0f} % of the starting orientations are within 5 deg "
                "of one parent orientation: the map looks like one crystal, where a misfit "
                "every pattern shares does not average out and the free orientation model's "
                "standard errors can miss it (on BaTiO3 domain maps by 10-22 of them). "
                "orientation_model='crystal' ties the points to one parent and adds the "
                "shared misfit to the standard errors",
                UserWarning,
                stacklevel=3,
            )
        crystal = None
    problem = _Problem(
        experimental=exp,
        points=pts,
        start_rotations=start,
        master_pattern=phases[0].master_pattern,
        energy=float(energy),
        # The master pattern's phase, checked to match xmap's: kikuchipy
        # refuses phases whose atom lists differ in order (as after a
        # round trip through an h5ebsd file)
        phase=phases[0].phase.deepcopy(),
        parameters=names,
        steps=steps,
        dic_kwargs=dic_kwargs,
        refine_kwargs=ref_kw,
        pseudo_symmetry_ops=ops if len(phases) == 1 else _any_operators(phases),
        background=_static_background(signal),
        phases=phases,
        point_phase=point_phase,
    )
    if crystal is not None:
        # The parent in each start's variant, the starts' own errors
        # (absorbed geometry, misindexed points) left behind. The variant
        # is the indexer's until the DIC stage stops short of the basin or
        # reaches it: at a start 1.8 % off, BaTiO3's variants compared
        # there put 32 of 36 points of a six-variant map in a wrong one
        # (significance 1.9), and the PC ended 2e-3 off
        anchors = crystal.anchors(start)
        # Points far from the parent are misindexed or another crystal:
        # their patterns tell which, the parent's best variant refined at
        # the start geometry (unrefined, a start that absorbed the
        # geometry's error fits its pattern better than the parent does)
        far = crystal.far(start)
        # Too few far starts to make another crystal: no refinement needed
        if far.mean() >= OTHER_CRYSTAL_FRACTION:
            best = problem.best_variants(geometry0, anchors)
            why = _other_crystal(
                problem.ncc(geometry0, start), problem.refined_ncc(geometry0, best), far
            )
            crystal = None if why else crystal
    if crystal is None and orientation_model == "crystal":
        raise NotOneCrystalError(
            f"orientation_model='crystal' was asked of a map that is not one crystal: {why}. "
            "Calibrate a polycrystal (or several crystals) with orientation_model='free', "
            "or one crystal's points only (points=...)"
        )
    if crystal is not None:
        problem = replace(problem, start_rotations=anchors, crystal=crystal)
    # Judged last: the crystal's checks compare plain simulations
    if problem.background is None or geometry0 is None:
        return problem
    sim = problem.simulate(geometry0, start)
    divided = _bands_divided_out(problem.background, problem.experimental, sim) is not None
    return replace(problem, mean_divided=divided)
