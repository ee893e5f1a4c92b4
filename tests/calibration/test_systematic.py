"""The systematic part of the standard errors: the spread of the
geometry's solutions on the detector's regions (one crystal) and over
the grains left out in turn (a polycrystal), against a known shared
misfit."""

import numpy as np
from orix.quaternion import Rotation
from orix.quaternion.symmetry import Oh

from kikuchipy_geomdic.calibration._systematic import (
    PRIOR_PARTS,
    _grain_errors,
    _grains,
    _quadrants,
    _region_errors,
    _with_prior,
)
from kikuchipy_geomdic.calibration.solve import JointSystem, solve_joint
from kikuchipy_geomdic.indexing.variants import _proper_rotations


def test_region_errors_see_a_misfit_the_regions_share_unequally():
    rng = np.random.default_rng(2)
    n, ny, nx, k = 20, 8, 8, 2
    p = ny * nx
    jg = rng.normal(size=(n, p, k))
    jr = rng.normal(size=(n, p, 3))
    w = np.full((n, p), 1e4)
    noise = rng.normal(scale=1e-2, size=(n, p))
    kw = dict(prior=1e-3, common=True, shape=_quadrants((ny, nx)), offsets=np.zeros((n, 3)))
    clean = _region_errors(noise, jg, jr, w, kw["offsets"], kw["prior"], True, kw["shape"])
    # The top half of the detector pulls parameter 0 one way, the bottom
    # the other: a misfit no pattern-to-pattern variance sees
    pull = np.where(np.arange(p) < p // 2, 1.0, -1.0) * 0.05
    biased = noise - jg[..., 0] * pull[None]
    sys = _region_errors(biased, jg, jr, w, kw["offsets"], kw["prior"], True, kw["shape"])
    se = solve_joint(jg, jr, noise, w, prior=1e-3, common=True).standard_errors
    assert clean[0] < 2 * se[0]
    assert sys[0] > 0.02


def _grain_map(rng, sizes, bias_sd, k=2, m=40):
    """A linear free-rotation system of grains of *sizes* patterns, each
    grain's patterns pulling the geometry by one bias (sd *bias_sd*)."""
    groups = np.repeat(np.arange(len(sizes)), sizes)
    n = len(groups)
    jg = rng.normal(size=(n, m, k))
    jr = rng.normal(size=(n, m, 3))
    bias = rng.normal(scale=bias_sd, size=(len(sizes), k))[groups]
    b = rng.normal(scale=1e-2, size=(n, m)) - np.einsum("nmk,nk->nm", jg, bias)
    return jg, jr, b, groups


def _z_and_inflation(rng, sizes, bias_sd, maps=60):
    """|error| / standard error (maps, K) with the grains' part, and the
    standard errors over the solve's own."""
    z, inflation, z_stat = [], [], []
    for _ in range(maps):
        jg, jr, b, groups = _grain_map(rng, sizes, bias_sd)
        system = JointSystem.build(jg, jr, np.ones(b.shape))
        upd = system.solve(b)
        sys, _ = _grain_errors(system, b, np.zeros((len(b), 3)), groups)
        # The truth is zero: the error is the update itself
        stat = upd.standard_errors
        total = np.sqrt(stat**2 + sys**2)
        z.append(np.abs(upd.delta) / total)
        z_stat.append(np.abs(upd.delta) / stat)
        inflation.append(total / stat)
    return np.array(z), np.array(inflation), np.array(z_stat)


def test_grain_errors_cover_a_bias_each_grain_shares():
    """Six grains whose patterns share a bias each: the cluster-robust
    standard errors (patterns independent) miss the whole map's error,
    with the grains' spread added it is covered; without a bias the
    spread adds little."""
    rng = np.random.default_rng(0)
    z, _, z_stat = _z_and_inflation(rng, [15, 12, 10, 8, 6, 3], 0.01)
    assert np.mean(z_stat > 3) > 0.3
    assert np.mean(z > 3) < 0.05
    _, inflation, _ = _z_and_inflation(rng, [15, 12, 10, 8, 6, 3], 0.0)
    assert np.median(inflation) < 1.3


def test_grain_errors_are_the_errors_size_on_many_grains():
    """Thirty grains sharing a bias each: the RMS of error / standard
    error is about 1 (not wider than it must be), and the standard errors
    shrink with the grains' number as the error does."""
    rng = np.random.default_rng(4)
    z, inflation, _ = _z_and_inflation(rng, [4] * 30, 0.01, maps=80)
    assert 0.8 < np.sqrt(np.mean(z**2)) < 1.25
    assert np.mean(z <= 1) > 0.55
    assert np.median(inflation) > 2  # the grains' biases dominate the noise
    z_many, _, _ = _z_and_inflation(rng, [4] * 120, 0.01, maps=40)
    assert 0.8 < np.sqrt(np.mean(z_many**2)) < 1.25


def test_effective_grains_count_unequal_grains_as_fewer():
    rng = np.random.default_rng(5)
    for sizes, low, high in (([10] * 6, 5, 7), ([40, 2, 2, 2, 2, 2], 1, 2.5)):
        jg, jr, b, groups = _grain_map(rng, sizes, 0.0)
        system = JointSystem.build(jg, jr, np.ones(b.shape))
        _, effective = _grain_errors(system, b, np.zeros((len(b), 3)), groups)
        assert low < effective < high, (sizes, effective)


def test_grain_errors_need_three_grains():
    rng = np.random.default_rng(1)
    jg, jr, b, groups = _grain_map(rng, [10, 10], 0.01)
    system = JointSystem.build(jg, jr, np.ones(b.shape))
    assert np.all(_grain_errors(system, b, np.zeros((20, 3)), groups)[0] == 0)


def test_grains_of_grains_in_any_symmetry_equivalent():
    rng = np.random.default_rng(3)
    s = _proper_rotations(Oh)
    parents = Rotation(rng.normal(size=(12, 4))).unit
    scatter = Rotation.from_axes_angles(rng.normal(size=(120, 3)), np.deg2rad(0.5))
    grain = np.repeat(np.arange(12), 10)
    # Each point in a random one of its symmetry-equivalent forms
    q = Rotation(s[rng.integers(len(s), size=120)]) * scatter * parents[grain]
    labels = _grains(np.asarray(q.data), s)
    # No grain split, none merged
    assert all(len(np.unique(labels[grain == g])) == 1 for g in range(12))
    assert len(np.unique(labels)) == 12


def test_the_prior_fades_as_the_grains_grow_in_number():
    """The DIC stage's variance raises a few grains' standard error by a
    share PRIOR_PARTS / (grains - 1 + PRIOR_PARTS) of the difference,
    is all there is from one grain, and never lowers one."""
    se, prior = 1.0, 3.0
    assert _with_prior(se, prior, 1.0) == prior
    six = _with_prior(se, prior, 6.0)
    assert np.isclose(six**2, 1 + PRIOR_PARTS / (5 + PRIOR_PARTS) * 8)
    assert se < _with_prior(se, prior, 121.0) < 1.1 < six < prior
    assert _with_prior(prior, se, 6.0) == prior
