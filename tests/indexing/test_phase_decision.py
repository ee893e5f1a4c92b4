"""Reindexing a map of several phases: each phase's points with its own
master pattern, the phases in one crystal map written to .ang and orix
h5, and with ``decide_phase`` each point's phase decided by its pattern,
mislabelled points put right with their margins, undecidable ones
flagged."""

import numpy as np
import pytest
from orix import io

from kikuchipy_geomdic import reindex

#: Points labelled with the other phase in the start (Ni: 7, 14, 25; Si: 33)
WRONG = np.array([7, 14, 25, 33])


def _misorientation_deg(a, b):
    return np.rad2deg((~a.rotations * b.rotations).angle)


@pytest.fixture(scope="module")
def kept(two_phase):
    t = two_phase
    return reindex(
        t.signal, t.start_xmap, t.detector, t.master_patterns, 20, show_progressbar=False
    )


def test_each_point_keeps_its_phase_by_default(two_phase, kept, tmp_path):
    t = two_phase
    np.testing.assert_array_equal(kept.phase_id, t.xmap.phase_id)
    assert kept.phases.names == ["Ni", "Si"]
    assert kept.converged.all() and kept.refined.all()
    assert _misorientation_deg(kept, t.xmap).max() < 0.1
    assert "phase_margin" not in kept.prop
    # Written and read back with every phase
    io.save(tmp_path / "map.ang", kept)
    io.save(tmp_path / "map.h5", kept)
    for name in ("map.ang", "map.h5"):
        back = io.load(tmp_path / name)
        # .ang numbers the phases from 1: compared by name
        names = [back.phases[int(i)].name for i in back.phase_id.reshape(-1)]
        assert names == [kept.phases[int(i)].name for i in kept.phase_id]


def test_one_phase_of_the_list_is_refined_as_with_its_master_pattern_alone(two_phase, kept):
    t = two_phase
    alone = reindex(
        t.signal, t.start_xmap, t.detector, t.si.master_pattern, 20, phase="Si",
        show_progressbar=False,
    )  # fmt: skip
    si = t.is_si
    np.testing.assert_array_equal(alone.rotations.data[si], kept.rotations.data[si])
    np.testing.assert_array_equal(alone.scores[si], kept.scores[si])


@pytest.fixture(scope="module")
def decided(two_phase):
    t = two_phase
    pid = t.start_xmap.phase_id.copy()
    pid[WRONG] = 1 - pid[WRONG]
    start = t.both(t.ni.start_xmap, t.si.start_xmap, phase_id=pid)
    data = t.signal.data.reshape(-1, *t.signal.data.shape[-2:])
    signal = t.signal.deepcopy()
    # Point 2: half a Ni pattern and half a Si pattern (a phase boundary)
    a = t.ni.signal.data.reshape(data.shape)[2].astype(float)
    b = t.si.signal.data.reshape(data.shape)[2].astype(float)
    signal.data.reshape(data.shape)[2] = (a - a.mean()) / a.std() + (b - b.mean()) / b.std()
    before = start.deepcopy()
    out = reindex(
        signal, start, t.detector, t.master_patterns, 20, decide_phase=True,
        show_progressbar=False,
    )  # fmt: skip
    np.testing.assert_array_equal(start.phase_id, before.phase_id)
    return out


def test_decide_phase_puts_mislabelled_points_right_with_margins(two_phase, decided):
    t = two_phase
    good = np.ones(t.xmap.size, dtype=bool)
    good[2] = False
    np.testing.assert_array_equal(decided.phase_id[good], t.xmap.phase_id[good])
    np.testing.assert_array_equal(np.flatnonzero(decided.prop["phase_changed"]), WRONG)
    # Measured: 58-111 at 200 counts/px
    assert decided.prop["phase_margin"][good].min() > 20
    assert decided.converged[good].all()
    assert _misorientation_deg(decided, t.xmap)[good].max() < 0.1
    # The kept phase scores better than the other
    s0, s1 = decided.prop["phase_score_0"], decided.prop["phase_score_1"]
    np.testing.assert_array_equal((s1 > s0)[good], t.is_si[good])


def test_a_point_its_pattern_does_not_decide_is_flagged(decided):
    # The half-and-half pattern: measured margin 1.1
    assert decided.prop["phase_margin"][2] < 2.5
    assert decided.converged[2] == 0


def test_phase_calls_in_parts_are_the_calls_in_one(two_phase, decided, monkeypatch):
    # The parts run on dask's threads; each point is compared on its own
    import dask

    from kikuchipy_geomdic.indexing import _phase_maps
    from kikuchipy_geomdic.indexing._projection import detector_matrix, detector_pcs

    t = two_phase
    n = t.xmap.size
    patterns = np.asarray(t.signal.data, dtype=np.float64).reshape(n, *t.signal.data.shape[-2:])
    q = decided.rotations.data.reshape(-1, 4)
    candidates = np.stack([q, q[::-1]], axis=1)
    pcs = detector_pcs(t.detector, n)
    om = detector_matrix(t.detector)
    arrays = tuple(_master_arrays(t))
    one = _phase_maps._compare(patterns, candidates, pcs, om, arrays)
    monkeypatch.setitem(dask.config.config, "num_workers", 3)
    parts = _phase_maps._compare_parts(patterns, candidates, pcs, om, arrays)
    for a, b in zip(one, parts):
        np.testing.assert_array_equal(a, b)


def _master_arrays(t):
    from kikuchipy_geomdic.indexing.orientation import master_pattern_arrays

    return [master_pattern_arrays(mp, 20) for mp in t.master_patterns]


def test_decide_phase_needs_two_phases_and_this_packages_solver(two_phase):
    t = two_phase
    with pytest.raises(ValueError, match="decide_phase=True needs master patterns of two"):
        reindex(t.signal, t.start_xmap, t.detector, [t.ni.master_pattern], 20, phase="Ni",
                decide_phase=True)  # fmt: skip
    with pytest.raises(ValueError, match="decide_phase=True needs method='geomdic'"):
        reindex(t.signal, t.start_xmap, t.detector, t.master_patterns, 20, decide_phase=True,
                method="kikuchipy")  # fmt: skip


def test_bad_phases_are_refused_before_any_work(two_phase):
    t = two_phase
    ni, si = t.master_patterns
    with pytest.raises(ValueError, match="Two master patterns"):
        reindex(t.signal, t.start_xmap, t.detector, [ni, si, ni], 20)
    with pytest.raises(ValueError, match="Different energies"):
        reindex(t.signal, t.start_xmap, t.detector, [ni, si], [20, 10])


def test_plot_phases_marks_flagged_and_wrong_points():
    """The phase figure counts the points not to trust and, given the
    truth, those of another phase; the map is not modified."""
    import matplotlib

    matplotlib.use("Agg")
    from orix.crystal_map import CrystalMap, Phase, PhaseList
    from orix.quaternion import Rotation

    from kikuchipy_geomdic.plotting import plot_phases

    phases = PhaseList([Phase(n, point_group="m-3m") for n in ("ferrite", "austenite")])
    converged = np.ones(12)
    converged[[1, 5]] = 0
    xmap = CrystalMap(
        Rotation.identity((12,)), phase_id=np.arange(12) % 2, phase_list=phases,
        x=np.arange(12) % 4, y=np.arange(12) // 4, prop={"converged": converged},
    )  # fmt: skip
    truth = np.arange(12) % 2
    truth[[0, 7, 9]] = 1 - truth[[0, 7, 9]]
    fig = plot_phases(xmap, truth=truth)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["ferrite", "austenite", "not to trust (2)", "wrong phase (3)"]
    assert np.array_equal(xmap.prop["converged"], converged)
