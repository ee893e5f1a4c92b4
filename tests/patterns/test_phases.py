"""Tests of :mod:`kikuchipy_geomdic.patterns.phases`: the one rule that decides
whether a crystal map's phase is the master pattern's.

Silicon read back from an ``.ang`` file has point group 432 and a lattice
in angstrom; the master pattern's phase has m-3m (and, from EMsoft, nm):
the same crystal. BaTiO3 (4mm) and a cubic cell of another size are not.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
from kikuchipy.signals import EBSDMasterPattern
from orix import io as orix_io
from orix.crystal_map import CrystalMap, Phase

from kikuchipy_geomdic.patterns.phases import (
    check_phase,
    describe_phase,
    match_phase,
    phases_match,
    replace_phase,
)
from kikuchipy_geomdic.validation import synthetic


@pytest.fixture(scope="module")
def sm(si_mp):
    return synthetic.synthetic_map(si_mp, (2, 3), shape=(20, 20), seed=1)


@pytest.fixture(scope="module")
def ang_xmap(sm, tmp_path_factory):
    """The map written to an .ang file and read back by orix."""
    path = tmp_path_factory.mktemp("phases") / "map.ang"
    with contextlib.redirect_stdout(io.StringIO()):
        orix_io.save(str(path), sm.xmap)
        return orix_io.load(str(path))


def _two_phase_map(xmap: CrystalMap, other: Phase) -> CrystalMap:
    xm = xmap.deepcopy()
    xm.phases.add(other)
    xm[0, 0].phase_id = 1
    return xm


# --------------------------------------------------------------------- #
# phases_match
# --------------------------------------------------------------------- #


def test_ang_phase_is_silicon(sm, ang_xmap):
    si_ang = ang_xmap.phases[int(ang_xmap.phase_id[0])]
    assert si_ang.point_group.name == "432"
    assert sm.master_pattern.phase.point_group.name == "m-3m"
    assert phases_match(si_ang, sm.master_pattern.phase)
    assert phases_match(sm.master_pattern.phase, si_ang)  # symmetric


def test_other_point_group_refused(sm, bto_mp):
    assert bto_mp.phase.point_group.name == "4mm"
    assert not phases_match(sm.master_pattern.phase, bto_mp.phase)
    assert not phases_match(Phase("Si", point_group="m-3m"), Phase("Si", point_group="4mm"))


def test_lattice_decides_and_allows_nm(sm):
    si = sm.master_pattern.phase
    renamed = si.deepcopy()
    renamed.name = "silicon"
    assert phases_match(si, renamed)  # same crystal, other name: lattice decides
    nm = si.deepcopy()
    nm.structure.lattice.setLatPar(0.5431, 0.5431, 0.5431)
    assert phases_match(si, nm)  # nm against angstrom
    nm.structure.lattice.setLatPar(0.3524, 0.3524, 0.3524)
    assert not phases_match(si, nm)  # nickel's cell, same point group
    stretched = si.deepcopy()
    stretched.structure.lattice.setLatPar(5.431, 5.431, 5.75)
    assert not phases_match(si, stretched)  # 6 % off in c


def test_names_decide_without_lattices():
    assert phases_match(Phase("Si", point_group="m-3m"), Phase("si", point_group="432"))
    assert not phases_match(Phase("Si", point_group="m-3m"), Phase("Ni", point_group="m-3m"))
    assert phases_match(Phase(point_group="m-3m"), Phase("Ni", point_group="m-3m"))
    assert not phases_match(Phase("Si"), Phase("Si"))  # no symmetry: nothing matches


# --------------------------------------------------------------------- #
# check_phase
# --------------------------------------------------------------------- #


def test_check_phase_accepts_ang_map(sm, ang_xmap):
    pid = check_phase(ang_xmap, sm.master_pattern)
    assert pid == int(ang_xmap.phase_id[0])
    assert check_phase(ang_xmap, sm.master_pattern, phase=pid) == pid
    assert check_phase(ang_xmap, sm.master_pattern, phase=ang_xmap.phases[pid].name) == pid
    assert check_phase(sm.xmap, sm.master_pattern) == 0
    assert match_phase(ang_xmap, sm.master_pattern) == pid  # the same rule


def test_check_phase_refuses_other_phase_naming_both(sm, ang_xmap, bto_mp):
    with pytest.raises(ValueError) as e:
        check_phase(ang_xmap, bto_mp)
    msg = str(e.value)
    assert msg.startswith("The master pattern's phase 'BaTiO3' (4mm, a b c = 3.99")
    assert "does not match the crystal map's phase 'Si' (432, a b c = 5.43" in msg


def test_check_phase_refuses_other_lattice(sm):
    ni_like = sm.master_pattern.phase.deepcopy()
    ni_like.name = "Ni"
    ni_like.structure.lattice.setLatPar(3.524, 3.524, 3.524)
    mp = EBSDMasterPattern(
        sm.master_pattern.data, projection="lambert", hemisphere="both", phase=ni_like
    )
    with pytest.raises(ValueError, match=r"'Ni' \(m-3m, a b c = 3.524.*'Si' \(m-3m"):
        check_phase(sm.xmap, mp)


def test_check_phase_several_phases(sm):
    xm = _two_phase_map(sm.xmap, Phase("other", point_group="m-3m"))
    with pytest.raises(ValueError, match=r"several phases \['Si', 'other'\]: choose one"):
        check_phase(xm, sm.master_pattern)
    assert check_phase(xm, sm.master_pattern, phase="Si") == 0
    with pytest.raises(ValueError, match="does not match"):
        check_phase(xm, sm.master_pattern, phase="other")


def test_check_phase_no_indexed_points(sm):
    xm = sm.xmap.deepcopy()
    xm.phase_id = -1
    with pytest.raises(ValueError, match="no indexed points"):
        check_phase(xm, sm.master_pattern)


@pytest.mark.parametrize("phase", ["Ni", 3])
def test_check_phase_unknown_phase(sm, phase):
    with pytest.raises(ValueError, match=rf"Phase {phase!r} is not in the crystal map's phases"):
        check_phase(sm.xmap, sm.master_pattern, phase=phase)


def test_check_phase_master_pattern_without_symmetry(sm):
    mp = EBSDMasterPattern(
        sm.master_pattern.data, projection="lambert", hemisphere="both", phase=Phase("Si")
    )
    with pytest.raises(ValueError, match="no phase symmetry"):
        check_phase(sm.xmap, mp)


# --------------------------------------------------------------------- #
# replace_phase, describe_phase
# --------------------------------------------------------------------- #


def test_replace_phase_keeps_everything_else(sm, ang_xmap):
    pid = check_phase(ang_xmap, sm.master_pattern)
    new = replace_phase(ang_xmap, pid, sm.master_pattern.phase)
    assert new.phases[pid].point_group.name == "m-3m"
    assert new.phases[pid].color == ang_xmap.phases[pid].color
    assert ang_xmap.phases[pid].point_group.name == "432"  # input untouched
    np.testing.assert_array_equal(new.rotations.data, ang_xmap.rotations.data)
    np.testing.assert_array_equal(new.phase_id, ang_xmap.phase_id)
    np.testing.assert_array_equal(new.x, ang_xmap.x)
    assert set(new.prop) == set(ang_xmap.prop)
    assert new.scan_unit == ang_xmap.scan_unit


def test_describe_phase():
    assert describe_phase(Phase("Si", point_group="m-3m")) == "'Si' (m-3m)"
    assert describe_phase(Phase()) == "'(unnamed)' (no symmetry)"
