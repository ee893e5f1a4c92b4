"""The systematic part of the standard errors: the spread of the
geometry's solutions on the detector's regions (one crystal) and on
groups of grains (a polycrystal), against a known shared misfit."""

import numpy as np
from orix.quaternion import Rotation
from orix.quaternion.symmetry import Oh

from kikuchipy_geomdic.calibration._systematic import (
    GRAIN_GROUPS,
    _grain_errors,
    _grain_groups,
    _quadrants,
    _region_errors,
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


def test_grain_errors_cover_a_bias_each_grain_shares():
    """Six grains whose patterns share a bias each: the cluster-robust
    standard errors (patterns independent) miss the whole map's error,
    with the grains' spread added it is covered; without a bias the
    spread adds little."""
    rng = np.random.default_rng(0)
    z_stat, z_total, inflation = [], [], []
    for bias_sd in (0.0, 0.01):
        for _ in range(60):
            jg, jr, b, groups = _grain_map(rng, [15, 12, 10, 8, 6, 3], bias_sd)
            system = JointSystem.build(jg, jr, np.ones(b.shape))
            upd = system.solve(b)
            sys = _grain_errors(system, b, np.zeros((len(b), 3)), groups)
            # The truth is zero: the error is the update itself
            stat = upd.standard_errors
            total = np.sqrt(stat**2 + sys**2)
            if bias_sd:
                z_stat.append(np.abs(upd.delta) / stat)
                z_total.append(np.abs(upd.delta) / total)
            else:
                inflation.append(total / stat)
    assert np.mean(np.array(z_stat) > 3) > 0.3
    assert np.mean(np.array(z_total) > 3) < 0.04
    assert np.median(inflation) < 1.1


def test_grain_errors_need_two_determined_groups():
    rng = np.random.default_rng(1)
    jg, jr, b, groups = _grain_map(rng, [20], 0.01)
    system = JointSystem.build(jg, jr, np.ones(b.shape))
    assert np.all(_grain_errors(system, b, np.zeros((20, 3)), groups) == 0)


def test_grain_groups_of_grains_in_any_symmetry_equivalent():
    rng = np.random.default_rng(3)
    s = _proper_rotations(Oh)
    parents = Rotation(rng.normal(size=(12, 4))).unit
    scatter = Rotation.from_axes_angles(rng.normal(size=(120, 3)), np.deg2rad(0.5))
    grain = np.repeat(np.arange(12), 10)
    # Each point in a random one of its symmetry-equivalent forms
    q = Rotation(s[rng.integers(len(s), size=120)]) * scatter * parents[grain]
    groups = _grain_groups(np.asarray(q.data), s)
    # No grain split, 12 grains pooled into GRAIN_GROUPS of 10 or 20
    assert all(len(np.unique(groups[grain == g])) == 1 for g in range(12))
    assert groups.max() + 1 == GRAIN_GROUPS
    assert set(np.bincount(groups)) <= {10, 20}
    three = _grain_groups(np.asarray(q.data)[grain < 3], s)
    assert np.array_equal(np.unique(three), [0, 1, 2])
