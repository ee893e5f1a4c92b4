"""Tests of :mod:`kikuchipy_geomdic.patterns.simulation`: chunked simulation in
bounded memory gives the patterns of a single chunk."""

import numpy as np
import pytest
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation

from kikuchipy_geomdic.patterns import simulation
from kikuchipy_geomdic.validation import master_patterns

SHAPE = (20, 24)
#: Bytes of direction cosines per pattern, as simulate_patterns counts them
PER_PATTERN = SHAPE[0] * SHAPE[1] * 3 * 8


@pytest.fixture(scope="module")
def mp():
    return master_patterns.master_pattern("Si", kind="kinematical", half_size=50)


def _rotations(n=5):
    rng = np.random.default_rng(1)
    q = rng.normal(size=(n, 4))
    return Rotation(q / np.linalg.norm(q, axis=1, keepdims=True))


def _detector(n):
    # One PC per pattern, all different: a chunk must get its own PCs
    pc = np.column_stack(
        [np.linspace(0.45, 0.55, n), np.linspace(0.25, 0.3, n), np.linspace(0.55, 0.65, n)]
    )
    return EBSDDetector(SHAPE, pc=pc, px_size=70, binning=8, tilt=2, sample_tilt=70)


@pytest.fixture
def calls(monkeypatch):
    """Number of patterns kikuchipy projects per call."""
    sizes = []
    original = EBSDMasterPattern.get_patterns

    def spy(self, rotations, *args, **kwargs):
        sizes.append(rotations.size)
        return original(self, rotations, *args, **kwargs)

    monkeypatch.setattr(EBSDMasterPattern, "get_patterns", spy)
    return sizes


@pytest.mark.parametrize("n_pc", [5, 1])
def test_small_budget_same_patterns_as_one_chunk(mp, calls, n_pc):
    rot, det = _rotations(5), _detector(n_pc)
    whole = simulation.simulate_patterns(mp, rot, det, 20)
    assert calls == [5]
    calls.clear()
    chunked = simulation.simulate_patterns(mp, rot, det, 20, max_bytes=2 * PER_PATTERN)
    assert calls == [2, 2, 1]  # the budget did split the simulation
    assert chunked.shape == (5,) + SHAPE and chunked.dtype == np.float32
    assert np.array_equal(chunked, whole)
    # Patterns differ from each other: a chunk given another's PC or
    # rotation would be caught
    assert not np.allclose(whole[0], whole[2])


def test_budget_below_one_pattern_simulates_one_at_a_time(mp, calls):
    rot, det = _rotations(3), _detector(3)
    whole = simulation.simulate_patterns(mp, rot, det, 20)
    calls.clear()
    single = simulation.simulate_patterns(mp, rot, det, 20, max_bytes=1)
    assert calls == [1, 1, 1]
    assert np.array_equal(single, whole)


def test_chunked_same_as_kikuchipy(mp):
    rot, det = _rotations(4), _detector(4)
    ours = simulation.simulate_patterns(mp, rot, det, 20, max_bytes=3 * PER_PATTERN)
    ref = mp.get_patterns(rot, det, 20, dtype_out=np.float32, compute=True, show_progressbar=False)
    assert np.allclose(ours, np.asarray(ref.data).reshape(ours.shape), atol=1e-6)


def test_pc_count_must_match(mp):
    with pytest.raises(ValueError, match="3 PCs for 5 rotations"):
        simulation.simulate_patterns(mp, _rotations(5), _detector(3), 20)


def test_no_rotations(mp):
    out = simulation.simulate_patterns(mp, _rotations(0), _detector(1), 20)
    assert out.shape == (0,) + SHAPE
