"""Tests of the realistic two-phase maps (validation.multiphase; named apart from
tests/calibration/test_multiphase.py, as pytest imports test files by basename)."""

import numpy as np
import pytest
from orix.quaternion import Orientation

from kikuchipy_geomdic.validation import multiphase
from kikuchipy_geomdic.validation.synthetic import DEFAULT_PERTURBATION

NAV = (6, 7)


@pytest.fixture(scope="module")
def hard():
    return multiphase.two_phase_map(
        multiphase.PAIRS["ferrite+martensite"], NAV, (40, 40), mislabel=0.1, seed=4
    )


def test_truth_labels_and_patterns(hard):
    n = NAV[0] * NAV[1]
    assert hard.phase_names == ("Fe_bcc", "Fe_bct")
    assert hard.signal.data.shape == NAV + (40, 40)
    assert hard.signal.data.dtype == np.uint16  # processed as kikuchipy leaves it
    # The truth: both phases, each grain of one phase
    truth = hard.true_phase.ravel()
    assert set(truth) == {0, 1}
    grain = hard.xmap.prop["grain"]
    for g in np.unique(grain):
        assert np.unique(truth[grain == g]).size == 1
    # The vendor's labels: the truth but for round(10 % of 42) points
    wrong = hard.mislabelled.ravel()
    assert wrong.sum() == round(0.1 * n) == 4
    assert np.array_equal(hard.start_phase.ravel() != truth, wrong)
    assert [p.name for _, p in hard.start_xmap.phases] == ["Fe_bcc", "Fe_bct"]
    # The start is what the signal carries, at the perturbed geometry
    assert np.array_equal(hard.signal.xmap.phase_id, hard.start_xmap.phase_id)
    assert np.allclose(hard.signal.detector.pc, hard.start_detector.pc)
    start, true = hard.start_geometry.as_dict(), hard.geometry.as_dict()
    assert start["pcx"] - true["pcx"] == pytest.approx(DEFAULT_PERTURBATION["pcx"])
    # Calibrate with ebsdsim's master patterns, data from de-ebsd's
    for name in hard.phase_names:
        assert "ebsdsim" in hard.master_patterns[name].metadata.General.title
        assert "de-ebsd" in hard.simulators[name].metadata.General.title


def test_start_orientations_are_indexed_near_the_truth(hard):
    # Refined at a geometry 2 % off: degrees from the truth, not tens
    sym = hard.xmap.phases[0].point_group  # m-3m holds 4/mmm's operators
    a = Orientation(hard.xmap.rotations, sym)
    b = Orientation(hard.start_xmap.rotations, sym)
    err = np.rad2deg(a.angle_with(b))
    assert np.median(err) < 4
    assert np.median(err) > 0.2


def test_seeded():
    kw = dict(navigation_shape=(3, 4), shape=(24, 24), mislabel=0.25)
    a = multiphase.two_phase_map(seed=1, **kw)
    b = multiphase.two_phase_map(seed=1, **kw)
    assert np.array_equal(a.signal.data, b.signal.data)
    assert np.array_equal(a.start_xmap.rotations.data, b.start_xmap.rotations.data)
    assert np.array_equal(a.mislabelled, b.mislabelled) and a.mislabelled.sum() == 3
    assert set(a.true_phase.ravel()) == {0, 1}  # both phases even on 12 points


def test_labels_and_options():
    rng = np.random.default_rng(0)
    truth = np.repeat([0, 1], 50)
    label, wrong = multiphase._labels(truth, 0.05, rng)
    assert wrong.sum() == 5 and np.array_equal(label != truth, wrong)
    label, wrong = multiphase._labels(truth, 0.0, rng)
    assert not wrong.any() and np.array_equal(label, truth)
    # A grain draw of one phase only gets a grain of the other
    phases = multiphase._grain_phases(np.arange(3), 1e-9, rng)
    assert sorted(phases) == [0, 0, 1]
    kw = dict(navigation_shape=(3, 4), shape=(24, 24))
    with pytest.raises(ValueError, match="wrong_orientation"):
        multiphase.two_phase_map(wrong_orientation="nearby", **kw)
    with pytest.raises(ValueError, match="two different phases"):
        multiphase.two_phase_map(("ferrite", "Fe_bcc"), **kw)
