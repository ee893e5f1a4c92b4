import numpy as np
import pytest

from kikuchipy_geomdic.solve import coupling_matrix, solve_update


def _problem(seed=0, r=32, k=4):
    rng = np.random.default_rng(seed)
    j = rng.normal(size=(2 * r, k)) * np.array([100, 1, 10, 0.1])[:k]
    p_true = rng.normal(size=k)
    return j, p_true


def test_recovers_linear_update():
    j, p = _problem()
    u = solve_update(j, -j @ p, np.ones(32), damping=0)
    assert np.allclose(u.delta, p, atol=1e-10)
    assert np.allclose(u.predicted_residual, 0, atol=1e-9)
    assert u.null_space.shape == (4, 0)


def test_column_normalisation_makes_scaling_irrelevant():
    # Eq. 9: rescaling a parameter's unit rescales its update only
    j, p = _problem()
    b = -j @ p + np.random.default_rng(1).normal(scale=0.01, size=64)
    u1 = solve_update(j, b, np.ones(32), damping=1e-3)
    scale = np.array([1, 1000, 1, 1e-3])
    u2 = solve_update(j / scale, b, np.ones(32), damping=1e-3)
    assert np.allclose(u2.delta, u1.delta * scale, rtol=1e-9)


def test_damping_matches_eq10():
    j, p = _problem(2)
    b = -j @ p
    w = np.linspace(0.2, 1, 32)
    lam = 0.3
    u = solve_update(j, b, w, damping=lam)
    ww = np.repeat(w, 2)
    jw, bw = j * ww[:, None], b * ww
    s = np.linalg.norm(jw, axis=0)
    jt = jw / s
    expected = np.linalg.solve(jt.T @ jt + lam * np.eye(4), -jt.T @ bw) / s
    assert np.allclose(u.delta, expected, rtol=1e-10)


def test_zero_weight_rois_are_ignored():
    j, p = _problem(3)
    b = -j @ p
    b[:8] += 100  # Garbage in the first four ROIs
    w = np.ones(32)
    w[:4] = 0
    u = solve_update(j, b, w, damping=0)
    assert np.allclose(u.delta, p, atol=1e-9)


def test_exact_degeneracy_gives_minimum_norm_split():
    # Columns 2 and 3 are opposite, like tilt and sample_tilt
    j, p = _problem(4, k=3)
    j = np.column_stack([j, -j[:, 2]])
    b = -j[:, :3] @ p
    for lam in (0, 1e-3):
        u = solve_update(j, b, np.ones(32), damping=lam)
        # The combination is determined; the split is equal and opposite
        assert np.isclose(u.delta[2] - u.delta[3], p[2], rtol=1e-2 if lam else 1e-9)
        assert np.isclose(u.delta[2], -u.delta[3], rtol=1e-9)
    assert u.null_space.shape == (4, 1)
    assert np.allclose(np.abs(u.null_space[2:, 0]), np.sqrt(0.5))
    assert u.singular_values[-1] < 1e-8 * u.singular_values[0]


def test_bad_input():
    j, p = _problem()
    with pytest.raises(ValueError, match="do not match"):
        solve_update(j, np.zeros(10), np.ones(32))
    with pytest.raises(ValueError, match="weights"):
        solve_update(j, np.zeros(64), np.ones(7))
    with pytest.raises(ValueError, match="finite"):
        solve_update(j, np.full(64, np.nan), np.ones(32))
    j0 = j.copy()
    j0[:, 1] = 0
    with pytest.raises(ValueError, match=r"column\(s\) \[1\]"):
        solve_update(j0, np.zeros(64), np.ones(32))


def test_coupling_matrix():
    j = np.array([[1.0, 1.0, -2.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, -2.0]])
    c = coupling_matrix(j)
    assert np.allclose(np.diag(c), 1)
    assert np.allclose(c, c.T)
    assert np.isclose(c[0, 2], -1)
    assert np.isclose(c[0, 1], 0.5)
