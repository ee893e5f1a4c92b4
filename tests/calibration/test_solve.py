import numpy as np
import pytest

from kikuchipy_geomdic.calibration.solve import (
    JointSystem,
    coupling_matrix,
    solve_joint,
    solve_update,
)


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


class TestJoint:
    """solve_joint against a dense least-squares solve of the same system."""

    @staticmethod
    def _system(n=6, m=10, k=3, seed=0):
        rng = np.random.default_rng(seed)
        jg = rng.normal(size=(n, m, k))
        jr = rng.normal(size=(n, m, 3))
        w = rng.uniform(0.5, 2, size=(n, m))
        b = rng.normal(size=(n, m))
        return jg, jr, b, w

    @staticmethod
    def _dense(jg, jr, b, w, prior=None, offsets=None):
        n, m, k = jg.shape
        a = np.zeros((n * m, k + 3 * n))
        a[:, :k] = jg.reshape(n * m, k)
        for i in range(n):
            a[i * m : (i + 1) * m, k + 3 * i : k + 3 * i + 3] = jr[i]
        sw = np.sqrt(w.ravel())
        a, rhs = a * sw[:, None], -b.ravel() * sw
        if prior is not None:
            p = np.zeros((3 * n, k + 3 * n))
            p[:, k:] = np.eye(3 * n) / prior
            a = np.vstack([a, p])
            rhs = np.concatenate([rhs, -offsets.ravel() / prior])
        x = np.linalg.lstsq(a, rhs, rcond=None)[0]
        return x[:k], x[k:].reshape(n, 3), np.linalg.inv(a.T @ a)[:k, :k]

    def test_schur_equals_dense(self):
        jg, jr, b, w = self._system()
        u = solve_joint(jg, jr, b, w)
        dp, dw, cov = self._dense(jg, jr, b, w)
        np.testing.assert_allclose(u.delta, dp, atol=1e-10)
        np.testing.assert_allclose(u.rotations, dw, atol=1e-10)
        np.testing.assert_allclose(u.model_covariance / u.variance_factor, cov, rtol=1e-8)
        # Never below the model in any direction
        assert np.linalg.eigvalsh(u.covariance - u.model_covariance).min() > -1e-12

    def test_prior_equals_dense(self):
        jg, jr, b, w = self._system(seed=1)
        off = np.random.default_rng(2).normal(size=(6, 3)) * 0.1
        u = solve_joint(jg, jr, b, w, prior=0.3, offsets=off)
        dp, dw, _ = self._dense(jg, jr, b, w, prior=0.3, offsets=off)
        np.testing.assert_allclose(u.delta, dp, atol=1e-10)
        np.testing.assert_allclose(u.rotations, dw, atol=1e-10)

    @pytest.mark.parametrize("exact", [False, True])
    def test_chi2_after_and_scores_equal_the_residuals(self, exact):
        # solve takes them from the normal equations' blocks; a residual the
        # step removes entirely (exact) takes the fallback to the residual
        jg, jr, b, w = self._system(n=8, m=40, k=3, seed=6)
        rng = np.random.default_rng(7)
        if exact:
            b = -(jg @ rng.normal(size=3) + (jr @ rng.normal(size=(8, 3, 1)))[..., 0])
        off = None if exact else rng.normal(size=(8, 3)) * 0.05
        u = JointSystem.build(jg, jr, w, None if exact else 0.3).solve(b, off)
        assert (u.predicted_chi2 < 1e-20 * u.chi2) == exact
        r = b + jg @ u.delta + (jr @ u.rotations[..., None])[..., 0]
        direct = float((w * r**2).sum())
        assert u.predicted_chi2 == pytest.approx(direct, rel=1e-9, abs=1e-20)
        assert u.chi2 == pytest.approx(float((w * b**2).sum()), rel=1e-12)
        # The covariance's cluster-robust part is made of the scores
        scores = np.swapaxes(jg * w[..., None], 1, 2) @ r[..., None]
        s_inv = u.model_covariance / u.variance_factor
        robust = s_inv @ (scores[..., 0].T @ scores[..., 0]) @ s_inv * 8 / 5
        d = robust - u.model_covariance
        mu, v = np.linalg.eigh((d + d.T) / 2)
        expected = u.model_covariance + (v * np.clip(mu, 0, None)) @ v.T
        np.testing.assert_allclose(u.covariance, expected, rtol=1e-8, atol=1e-15)

    @pytest.mark.parametrize("common", [False, True])
    def test_columns_are_the_system_built_from_them(self, common):
        # The full field cuts the free parameters' system from the whole
        # one: every block the same to the last bit as built anew
        jg, jr, b, w = self._system(n=8, m=40, k=4, seed=8)
        sd = np.array([np.inf, np.inf, np.inf, 0.5])
        whole = JointSystem.build(jg, jr, w, 0.3, common=common, geometry_prior=sd)
        cols = [0, 3]
        cut = whole.columns(cols, sd[cols])
        anew = JointSystem.build(jg[..., cols], jr, w, 0.3, common=common, geometry_prior=sd[cols])
        for name in ("c", "bb", "a0", "a_inv", "a_inv_b", "s_pattern", "full", "mu", "v"):
            assert np.array_equal(getattr(cut, name), getattr(anew, name)), name
        assert np.array_equal(cut.stack(), anew.js)
        assert (cut.k, cut.n_rot) == (anew.k, anew.n_rot)
        off = np.random.default_rng(9).normal(size=(8, 3)) * 0.05
        assert all(map(np.array_equal, cut.products(b), anew.products(b)))
        u, v = cut.solve(b, off), anew.solve(b, off)
        assert np.array_equal(u.delta, v.delta) and np.array_equal(u.covariance, v.covariance)
        # Cut twice, as the full field holds parameters in a cut system
        twice = cut.columns([1], sd[[3]])
        once = JointSystem.build(jg[..., [3]], jr, w, 0.3, common=common, geometry_prior=sd[[3]])
        assert np.array_equal(twice.stack(), once.js) and np.array_equal(twice.c, once.c)
        assert all(map(np.array_equal, twice.products(b), once.products(b)))
        # No prior on the geometry: that of build's default
        plain = JointSystem.build(jg[..., [1, 2]], jr, w, 0.3, common=common)
        assert np.array_equal(whole.columns([1, 2]).mu, plain.mu)

    def test_common_rotation_pinned_only_by_prior(self):
        # A geometry column that equals a rotation common to every pattern
        # is undetermined without a prior and determined with one
        jg, jr, b, w = self._system(seed=3)
        jg[..., 0] = jr[..., 2]
        free = solve_joint(jg, jr, b, w)
        assert free.null_space.shape[1] == 1
        assert np.isinf(free.standard_errors[0])
        pinned = solve_joint(jg, jr, b, w, prior=0.01)
        assert pinned.null_space.shape[1] == 0
        assert np.isfinite(pinned.standard_errors[0])
        # Reduced sensitivity is zero without a prior: nothing survives
        assert free.reduced_norms[0] < 1e-6 * free.full_norms[0]

    def test_standard_errors_match_scatter(self):
        # Monte Carlo: noise of known sigma, sigma estimated from residuals
        jg, jr, _, _ = self._system(n=20, m=30, k=2, seed=4)
        rng = np.random.default_rng(5)
        est, se = [], []
        for _ in range(200):
            b = -(jg @ np.array([0.1, -0.2])) + rng.normal(scale=0.3, size=(20, 30))
            u = solve_joint(jg, jr, b, np.ones((20, 30)))
            est.append(u.delta)
            se.append(u.standard_errors)
        scatter = np.std(est, axis=0)
        np.testing.assert_allclose(np.mean(est, axis=0), [0.1, -0.2], atol=3 * scatter.max())
        # Independent noise: the model is right and the robust
        # enlargement costs little (its own noise, 20 patterns)
        ratio = np.mean(se, axis=0) / scatter
        assert np.all((ratio > 0.9) & (ratio < 1.3)), ratio

    def test_standard_errors_see_correlated_errors(self):
        # Each pattern's errors share a part along its geometry signature
        # (a misfit band shifts all its features): the independent model
        # underestimates the scatter several times, the reported one not
        jg, jr, _, _ = self._system(n=20, m=30, k=2, seed=4)
        rng = np.random.default_rng(6)
        est, se, model = [], [], []
        for _ in range(200):
            common = np.einsum("nmk,nk->nm", jg, rng.normal(scale=0.2, size=(20, 2)))
            b = -(jg @ np.array([0.1, -0.2])) + common + rng.normal(scale=0.3, size=(20, 30))
            u = solve_joint(jg, jr, b, np.ones((20, 30)))
            est.append(u.delta)
            se.append(u.standard_errors)
            model.append(np.sqrt(np.diag(u.model_covariance)))
        scatter = np.std(est, axis=0)
        assert np.all(np.mean(model, axis=0) < 0.5 * scatter)
        ratio = np.mean(se, axis=0) / scatter
        assert np.all((ratio > 0.8) & (ratio < 1.3)), ratio

    def test_bad_input(self):
        jg, jr, b, w = self._system()
        with pytest.raises(ValueError, match="Shapes"):
            solve_joint(jg, jr[:, :, :2], b, w)
        with pytest.raises(ValueError, match="weights"):
            solve_joint(jg, jr, b, w[:, :3])
        with pytest.raises(ValueError, match="prior"):
            solve_joint(jg, jr, b, w, prior=-1)
        with pytest.raises(ValueError, match="finite"):
            solve_joint(jg, jr, b * np.nan, w)
