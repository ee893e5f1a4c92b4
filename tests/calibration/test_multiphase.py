"""Calibration from the master patterns of several phases: the phases
matched to the map's, one joint solve over every phase's points, the
points of a phase without a master pattern left out, and bad input
refused with nothing mutated."""

import numpy as np
import pytest
from conftest import TwoPhaseMap
from orix.crystal_map import CrystalMap, Phase, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic import refine_geometry_dic
from kikuchipy_geomdic.calibration import NotOneCrystalError
from kikuchipy_geomdic.indexing._projection import PhaseArrays
from kikuchipy_geomdic.indexing.orientation import (
    detector_matrix,
    master_pattern_arrays,
    project_arrays,
)
from kikuchipy_geomdic.indexing.phases_to_refine import phases_to_refine
from kikuchipy_geomdic.indexing.variants import variant_operators
from kikuchipy_geomdic.validation import master_patterns

PC = ("pcx", "pcy", "pcz")
OPTIONS = dict(parameters=list(PC), points=36, show_progressbar=False)


def _pc_errors(result, truth):
    return np.array([result.parameters[k] for k in PC]) - truth.pc


def _relabelled(xmap, names):
    """*xmap* with its phases renamed and given only proper point groups
    (as orix reads an .ang file's)."""
    phases = PhaseList(
        {i: Phase(n, point_group="432", structure=xmap.phases[i].structure) for i, n in names}
    )
    return CrystalMap(
        rotations=Rotation(xmap.rotations.data.copy()),
        phase_id=xmap.phase_id.copy(),
        x=xmap.x,
        y=xmap.y,
        phase_list=phases,
        scan_unit="um",
    )


def test_master_patterns_are_matched_to_their_phases_by_the_phase_rule(two_phase):
    # Another order, other names, proper point groups: the lattice decides
    xmap = _relabelled(two_phase.start_xmap, [(0, "nickel"), (1, "silicon")])
    ni, si = two_phase.master_patterns
    found = phases_to_refine(xmap, [si, ni], pseudo_symmetry_ops=[None, None], energy=20)
    assert [(p.name, p.phase_id) for p in found] == [("Si", 1), ("Ni", 0)]
    # One master pattern: today's rule, the phase chosen by name
    (one,) = phases_to_refine(xmap, si, phase="silicon")
    assert one.phase_id == 1


def test_projection_of_a_stack_of_two_phases_uses_each_points_phase(two_phase):
    ni, si = (master_pattern_arrays(m, 20) for m in two_phase.master_patterns)
    q = Rotation.from_euler(np.deg2rad([[10, 20, 30], [40, 50, 60], [70, 80, 90]])).data
    pcs = np.array([[0.5, 0.3, 0.6]] * 3)
    om = detector_matrix(two_phase.detector)
    labels = np.array([1, 0, 1])
    mixed = project_arrays(q, pcs, om, PhaseArrays((ni, si), labels), (30, 30))
    for i, arrays in enumerate([si, ni, si]):
        alone = project_arrays(q[i : i + 1], pcs[i : i + 1], om, arrays, (30, 30))
        np.testing.assert_array_equal(mixed[i], alone[0])
    assert not np.allclose(mixed[0], project_arrays(q[:1], pcs[:1], om, ni, (30, 30))[0])


@pytest.fixture(scope="module")
def calibrations(two_phase):
    t = two_phase
    mps = t.master_patterns
    both = refine_geometry_dic(t.signal, t.start_xmap, t.start_detector, mps, 20, **OPTIONS)
    one = refine_geometry_dic(
        t.signal, t.start_xmap, t.start_detector, t.ni.master_pattern, 20, phase="Ni", **OPTIONS
    )
    return both, one


def test_joint_solve_over_both_phases_recovers_the_geometry(two_phase, calibrations):
    both, one = calibrations
    # Points chosen across the phases, every point simulated from its own
    assert both.points_per_phase == {"Ni": 18, "Si": 18}
    assert one.points_per_phase == {"Ni": 18}
    assert both.converged
    np.testing.assert_array_equal(
        both.xmap.phase_id, two_phase.is_si[np.ravel_multi_index(both.points.T, (6, 6))]
    )
    assert both.xmap.scores.min() > 0.9
    err_both, err_one = _pc_errors(both, two_phase.geometry), _pc_errors(one, two_phase.geometry)
    se_both = np.array([both.standard_errors[k] for k in PC])
    se_one = np.array([one.standard_errors[k] for k in PC])
    # From a start 2 % off: within 5e-5 (measured 2.5e-5 at most), within 4
    # standard errors (4.5-8.6e-5), and at least as well as from one phase
    # (Ni's 18 points: 6.8e-5, standard errors 0.6-1.2e-4)
    assert np.abs(err_both).max() < 5e-5
    assert (np.abs(err_both) < 4 * se_both).all()
    assert (se_both < se_one).all()
    assert np.abs(err_both).max() <= np.abs(err_one).max()


def test_points_of_a_phase_without_master_pattern_are_left_out(two_phase):
    t = two_phase
    pid = t.start_xmap.phase_id.copy()
    pid[[0, 1, 2]] = 2  # three points of a phase given no master pattern
    xmap = t.both(t.ni.start_xmap, t.si.start_xmap, phase_id=pid)
    xmap.phases[2].name, xmap.phases[2].point_group = "BaTiO3", "4mm"
    with pytest.warns(UserWarning, match=r"'BaTiO3' \(3 points\).*left out"):
        res = refine_geometry_dic(
            t.signal, xmap, t.start_detector, t.master_patterns, 20, **{**OPTIONS, "points": 12}
        )
    flat = np.ravel_multi_index(res.points.T, (6, 6))
    assert not np.isin(flat, [0, 1, 2]).any()
    assert set(res.points_per_phase) == {"Ni", "Si"}


def _bad_inputs(t):
    ni, si = t.master_patterns
    bto = master_patterns.master_pattern("BaTiO3")
    emsoft_ni = master_patterns.master_pattern("Ni", kind="emsoft")
    ops = Rotation.from_axes_angles([0, 0, 1], np.pi / 2)
    return [
        (dict(master_pattern=[ni, si, bto]), "'BaTiO3' .* is of no phase in a point of the map"),
        (dict(master_pattern=[ni, emsoft_ni, si]), "Two master patterns, of 'Ni' .* of one phase"),
        (dict(energy=[20, 15]), r"Different energies \[20.0, 15.0\]"),
        (dict(pseudo_symmetry_ops=ops), "One set of pseudo_symmetry_ops for 2 master patterns"),
        (dict(phase="Ni"), "with 2 master patterns each is matched"),
    ]


@pytest.mark.parametrize("case", range(5))
def test_bad_input_is_refused_by_name_with_nothing_mutated(two_phase, case):
    t = two_phase
    change, message = _bad_inputs(t)[case]
    args = {"master_pattern": t.master_patterns, "energy": 20, **change}
    before = (t.signal.data.copy(), t.start_xmap.deepcopy(), t.start_detector.deepcopy())
    with pytest.raises(ValueError, match=message):
        refine_geometry_dic(t.signal, t.start_xmap, t.start_detector, **args, **OPTIONS)
    np.testing.assert_array_equal(t.signal.data, before[0])
    np.testing.assert_array_equal(t.start_xmap.rotations.data, before[1].rotations.data)
    np.testing.assert_array_equal(t.start_xmap.phase_id, before[1].phase_id)
    assert t.start_xmap.phases.names == before[1].phases.names
    np.testing.assert_array_equal(t.start_detector.pc, before[2].pc)


def test_one_crystal_model_is_refused_for_several_phases(two_phase):
    t = two_phase
    with pytest.raises(NotOneCrystalError, match="one crystal is of one phase"):
        refine_geometry_dic(
            t.signal, t.start_xmap, t.start_detector, t.master_patterns, 20,
            orientation_model="crystal", **OPTIONS,
        )  # fmt: skip


def test_pseudo_symmetry_operators_act_on_their_own_phase_only():
    # Ni (no operators) and BaTiO3 (its variants); three BaTiO3 points
    # started in another variant
    t = TwoPhaseMap(names=("Ni", "BaTiO3"))
    ops = variant_operators()[1:]
    q = t.start_xmap.rotations.data.reshape(-1, 4).copy()
    moved = np.array([3, 4, 10])
    q[moved] = ((~ops[0]) * Rotation(q[moved])).data
    start = CrystalMap(
        rotations=Rotation(q), phase_id=t.start_xmap.phase_id, x=t.start_xmap.x,
        y=t.start_xmap.y, phase_list=t.start_xmap.phases, scan_unit="um",
    )  # fmt: skip
    res = refine_geometry_dic(
        t.signal, start, t.start_detector, t.master_patterns, 20,
        pseudo_symmetry_ops=[None, ops], **OPTIONS,
    )  # fmt: skip
    flat = np.ravel_multi_index(res.points.T, (6, 6))
    index = res.xmap.prop["pseudo_symmetry_index"]
    # Each moved point back in its own variant, no other point moved
    np.testing.assert_array_equal(np.flatnonzero(index), np.flatnonzero(np.isin(flat, moved)))
    assert res.points_per_phase == {"Ni": 18, "BaTiO3": 18}
    assert np.abs(_pc_errors(res, t.geometry)).max() < 1e-4


def test_unchanged_variants_of_several_phases_are_the_very_rotations():
    # The DIC stage stops once no point's variant changes, comparing bits:
    # the phases' slices and join, renormalised by orix, must not count
    from kikuchipy_geomdic.calibration._phases import _best_variants

    class Phase:
        def best_variants(self, geometry, rotations):
            return rotations

    class Problem:
        sub_problems = [(np.arange(0, 40, 2), Phase()), (np.arange(1, 40, 2), Phase())]

    rng = np.random.default_rng(0)
    rotations = Rotation.from_axes_angles(rng.normal(size=(40, 3)), rng.uniform(0, 3, 40))
    rotations = rotations * Rotation.from_axes_angles(rng.normal(size=(40, 3)), 0.3)
    assert _best_variants(Problem(), None, rotations) is rotations
