"""Tests of :mod:`kikuchipy_geomdic.indexing.orientation`: the per-pattern
Gauss-Newton solver against kikuchipy's projection and against the truth.

Patterns are synthetic with known orientations; the kernel's projection is
checked against kikuchipy's ``get_patterns`` and its rotation derivative
against central differences, so the solver's optimum is kikuchipy's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from kikuchipy.detectors import EBSDDetector
from orix.quaternion import Rotation

from kikuchipy_geomdic.indexing import orientation as ori
from kikuchipy_geomdic.indexing._gauss_newton import _quat_step
from kikuchipy_geomdic.indexing._lambert import (
    SUMS,
    _atan_unit,
    _direction_columns,
    _direction_cosines,
    _project,
    _rotation_matrix,
    _step_sums,
)
from kikuchipy_geomdic.indexing.variants import variant_operators
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation import synthetic
from kikuchipy_geomdic.validation.orientations import perturb_rotations


@pytest.fixture(scope="module")
def det():
    # Not square, off-centre PC, all angles non-zero: every term counts
    return EBSDDetector((48, 64), pc=[0.52, 0.31, 0.6], sample_tilt=70, tilt=3, azimuthal=1.0)


@pytest.fixture(scope="module")
def polycrystal(si_mp):
    """Noisy 120 px patterns of a 6 x 6 polycrystal (dose 300)."""
    return synthetic.synthetic_map(
        si_mp, (6, 6), orientations="random", shape=(120, 120), dose=300, seed=3
    )


def misorientation(a: Rotation, b: Rotation) -> np.ndarray:
    return np.rad2deg((~a.flatten() * b.flatten()).angle)


def test_projection_equals_kikuchipy(si_mp, det):
    rot = Rotation.random(4)
    ours = ori.project_patterns(rot, det, si_mp, 20)
    theirs = simulate_patterns(si_mp, rot, det, 20)
    scale = np.abs(theirs).max()
    # float32 master pattern, float64 kernel: equal to float32 rounding
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5 * scale)


def test_polynomial_arctangent_within_its_bound():
    # The kernel's arctangent on [-1, 1], endpoints included, against libm
    t = np.concatenate([np.linspace(-1, 1, 200_001), [-1.0, -0.0, 1.0]])
    err = max(abs(_atan_unit(v) - math.atan(v)) for v in t)
    assert err < 3e-11


def test_projection_with_pc_per_pattern_and_batio3(bto_mp):
    det = EBSDDetector((30, 30), pc=[[0.5, 0.3, 0.6], [0.45, 0.35, 0.55]], sample_tilt=70)
    rot = Rotation.random(2)
    ours = ori.project_patterns(rot, det, bto_mp, 20)
    theirs = simulate_patterns(bto_mp, rot, det, 20)
    for a, b in zip(ours, theirs):
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99999


def test_rotation_derivative_matches_central_differences(si_mp, det):
    arrays = ori.master_pattern_arrays(si_mp, 20)
    dc = _direction_cosines(det.pc.reshape(3), det.nrows, det.ncols, ori.detector_matrix(det))
    # Seeded: an unseeded draw made the test depend on the tests run before it
    q = np.random.default_rng(0).normal(size=4)
    q /= np.linalg.norm(q)
    value = np.empty(dc.shape[0])
    jac = np.empty((dc.shape[0], 3))
    _project(q, dc, arrays.upper, arrays.lower, arrays.scale, value, jac, True)
    h = 1e-5
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        up, down = np.empty_like(value), np.empty_like(value)
        _project(
            _quat_step(w, q),
            dc,
            arrays.upper,
            arrays.lower,
            arrays.scale,
            up,
            jac.copy(),
            False,
        )  # noqa: E501
        _project(
            _quat_step(-w, q),
            dc,
            arrays.upper,
            arrays.lower,
            arrays.scale,
            down,
            jac.copy(),
            False,
        )  # noqa: E501
        fd = (up - down) / (2 * h)
        # Bilinear interpolation is piecewise: a few pixels straddle a
        # master-pattern cell edge within +-h
        assert np.corrcoef(fd, jac[:, k])[0, 1] > 0.999
        assert np.median(np.abs(fd - jac[:, k])) < 1e-3 * np.abs(jac[:, k]).mean()


def test_gauss_newton_sums_equal_the_stored_pattern_and_jacobian(si_mp, det):
    """The one-pass sums a Gauss-Newton step uses (the branch-free vector
    kernel) are those of the projection and Jacobian stored per pixel,
    over orientations that put pixels in both hemispheres and on both
    sides of the Lambert square's diagonals."""
    arrays = ori.master_pattern_arrays(si_mp, 20)
    pc, om = det.pc.reshape(3), ori.detector_matrix(det)
    dc = _direction_cosines(pc, det.nrows, det.ncols, om)
    np.testing.assert_allclose(_direction_columns(pc, det.nrows, det.ncols, om), dc.T, atol=1e-15)
    e = np.random.default_rng(0).normal(size=dc.shape[0])
    hemispheres = set()
    for q in Rotation.random(8).data:
        v, j = np.empty(dc.shape[0]), np.empty((dc.shape[0], 3))
        _project(q, dc, arrays.upper, arrays.lower, arrays.scale, v, j, True)
        sums = np.empty(SUMS)
        _step_sums(q, np.ascontiguousarray(dc.T), arrays.hemispheres, arrays.scale, e, sums)
        jj = j.T @ j
        expected = [v.sum(), v @ v, v @ e, *j.sum(0), *(j.T @ v), *(j.T @ e)]
        expected += [jj[0, 0], jj[0, 1], jj[0, 2], jj[1, 1], jj[1, 2], jj[2, 2]]
        np.testing.assert_allclose(sums, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
        hemispheres.update(np.sign(dc @ _rotation_matrix(q)[2]).tolist())
    assert hemispheres == {-1.0, 1.0}  # can fail: both hemispheres were looked up


def test_refine_recovers_truth_from_starts_degrees_off(polycrystal):
    sm = polycrystal
    patterns = sm.signal.data.reshape(-1, 120, 120)
    rng = np.random.default_rng(0)
    start = perturb_rotations(sm.xmap.rotations, 2.0, rng, centred=False)
    assert misorientation(start, sm.xmap.rotations).mean() > 1.5  # can fail
    res = ori.refine_patterns(patterns, start, sm.detector, sm.master_pattern, 20)
    err = misorientation(res.rotations, sm.xmap.rotations)
    assert err.max() < 0.03, err.max()
    assert res.converged.all()
    assert res.evaluations.max() < 30
    assert (res.rotations.data[:, 0] >= 0).all()  # one sign, as orix stores


def test_small_patterns_refine_from_starts_degrees_off(si_mp):
    """Patterns too small to bin by 4 (60 px) get the heavy smoothings at
    their coarsest level, binned by 2, first: starts 5 deg off reach the
    truth (with only that level's 1 deg smoothing, 16 of 36 stopped
    degrees away, most of them claiming convergence)."""
    assert ori._schedule((60, 60), None) == [(2, 6.0), (2, 3.0), (2, 1.0), (1, 0.0)]
    assert ori._schedule((60, 60), (1,)) == [(1, 0.0)]  # no binned level: as asked
    sm = synthetic.synthetic_map(
        si_mp, (6, 6), orientations="random", shape=(60, 60), dose=300, seed=3
    )
    start = perturb_rotations(sm.xmap.rotations, 5.0, np.random.default_rng(0), centred=False)
    assert misorientation(start, sm.xmap.rotations).mean() > 4  # can fail
    patterns = sm.signal.data.reshape(-1, 60, 60)
    res = ori.refine_patterns(patterns, start, sm.detector, sm.master_pattern, 20)
    err = misorientation(res.rotations, sm.xmap.rotations)
    assert err.max() < 0.05, np.sort(err)[-5:]
    assert res.converged.all()


def test_same_optimum_as_kikuchipy(polycrystal):
    """Both maximise the same NCC: the optima agree far below the noise."""
    from kikuchipy_geomdic.indexing.reindex import refine_orientations

    sm = polycrystal
    patterns = sm.signal.data.reshape(-1, 120, 120)[:8]
    rng = np.random.default_rng(1)
    start = perturb_rotations(sm.xmap.rotations[:8], 0.5, rng)
    det = sm.detector.deepcopy()
    det.pc = det.pc.reshape(-1, 3)[:8]
    ours = ori.refine_patterns(patterns, start, det, sm.master_pattern, 20)
    nm = refine_orientations(patterns, start, det, sm.master_pattern, 20, sm.master_pattern.phase)
    assert misorientation(ours.rotations, nm.rotations).max() < 0.01
    # Gauss-Newton finds the maximum at least as well as Nelder-Mead
    assert (ours.scores >= nm.scores - 1e-5).all()


def test_nan_pattern_gives_nan_score(polycrystal):
    sm = polycrystal
    patterns = sm.signal.data.reshape(-1, 120, 120)[:2].astype(np.float32).copy()
    patterns[1, 3, 3] = np.nan
    det = sm.detector.deepcopy()
    det.pc = det.pc.reshape(-1, 3)[:2]
    res = ori.refine_patterns(patterns, sm.xmap.rotations[:2], det, sm.master_pattern, 20)
    assert np.isfinite(res.scores[0]) and np.isnan(res.scores[1])
    assert not res.converged[1]


def test_bad_input_is_refused(polycrystal, det):
    sm = polycrystal
    patterns = sm.signal.data.reshape(-1, 120, 120)
    with pytest.raises(ValueError, match="stack"):
        ori.refine_patterns(patterns[0], sm.xmap.rotations[:1], sm.detector, sm.master_pattern)
    with pytest.raises(ValueError, match="shape"):
        ori.refine_patterns(patterns, sm.xmap.rotations, det, sm.master_pattern)
    with pytest.raises(ValueError, match="orientations"):
        ori.refine_patterns(patterns, sm.xmap.rotations[:3], sm.detector, sm.master_pattern)
    with pytest.raises(ValueError, match="PCs"):
        short = sm.detector.deepcopy()
        short.pc = short.pc.reshape(-1, 3)[:5]
        ori.refine_patterns(patterns, sm.xmap.rotations, short, sm.master_pattern)
    stereographic = sm.master_pattern.deepcopy()
    stereographic.projection = "stereographic"
    with pytest.raises(ValueError, match="'lambert' master pattern is required"):
        ori.master_pattern_arrays(stereographic, 20)
    with pytest.raises(ValueError, match="divide"):
        ori.pyramid_levels((120, 120), (7, 1))
    with pytest.raises(ValueError, match="ending with 1"):
        ori.pyramid_levels((120, 120), (4, 2))


def test_smoothing_continues_across_the_equator():
    """A smoothed hemisphere near its edge takes in the other hemisphere,
    mirrored across the edge: no seam at the equator."""
    n = 41
    upper = np.zeros((n, n), np.float32)
    lower = np.ones((n, n), np.float32)
    arrays = ori.MasterPatternArrays(upper, lower)
    px_deg = np.degrees(np.sqrt(np.pi / 2) / arrays.scale)
    smooth = arrays.smoothed(3 * px_deg)
    # Half the weight comes from across the edge, none in the middle
    assert 0.4 < smooth.upper[n // 2, -1] < 0.6
    assert smooth.upper[n // 2, n // 2] < 1e-6
    assert 0.4 < smooth.lower[0, n // 2] < 0.6


def test_poor_points_and_neighbour_seeds():
    scores = np.full((5, 5), 0.5)
    scores[2, 2] = 0.2  # one misindexed point in a grain
    scores[0, 4] = np.nan  # a NaN pattern is never poor
    poor = ori.poor_points(scores)
    assert np.argwhere(poor).tolist() == [[2, 2]]
    # A whole low region is poor against the map, not its neighbours
    scores[3:, 3:] = 0.1
    assert ori.poor_points(scores)[4, 4]
    q = np.tile([1.0, 0.0, 0.0, 0.0], (5, 5, 1))
    q[1, 1] = Rotation.from_axes_angles([0, 0, 1], np.deg2rad(30)).data
    q[1, 2] = Rotation.from_axes_angles([0, 0, 1], np.deg2rad(30.5)).data  # same grain
    usable = np.ones((5, 5), bool)
    usable[3, 3] = False
    seeds = ori.neighbour_seeds(q, (2, 2), usable)
    assert len(seeds) == 2  # identity and the 30 deg grain, each once


def test_neighbour_disagreement_with_symmetry_and_variants():
    """Neighbours in other variants or symmetry equivalents of one parent
    agree; a point 0.5 deg off them does not; invalid points are NaN."""
    ops = variant_operators()
    parent = Rotation.from_axes_angles([1, 2, 3], np.deg2rad(40))
    q = np.tile(parent.data, (4, 4, 1))
    q[0, :] = (ops[2] * parent).data  # a 90 deg domain
    q[:, 0] = (Rotation.from_axes_angles([0, 0, 1], np.pi / 2) * parent).data  # 4-fold equivalent
    q[2, 2] = (Rotation.from_axes_angles([1, 0, 0], np.deg2rad(0.5)) * parent).data
    valid = np.ones((4, 4), bool)
    valid[3, 3] = False
    sym = Rotation.from_axes_angles([0, 0, 1], np.arange(4) * np.pi / 2).data
    eq = np.concatenate([(Rotation(sym) * op).data for op in ops])
    d = ori.neighbour_disagreement(q, valid, eq)
    assert np.isnan(d[3, 3])
    assert abs(d[2, 2] - 0.5) < 1e-6
    others = valid.copy()
    others[2, 2] = False
    assert d[others].max() < 1e-6
    # Without the equivalents the domains disagree
    assert ori.neighbour_disagreement(q, valid)[0, 1] > 10


def test_compare_variants_picks_the_shown_variant_under_noise(bto_mp):
    """All six BaTiO3 variants as candidates, the pattern of each in turn
    with shot noise: the shown one is kept, its confidence index near its
    NCC and its margin positive; plain NCC differs in the third decimal
    for the 180 deg partner."""
    det = EBSDDetector((60, 60), pc=[0.5, 0.3, 0.6], sample_tilt=70)
    r = Rotation.from_euler(np.deg2rad([[10, 30, 50]]))
    ops = variant_operators()
    q = np.stack([(op * r).data.reshape(4) for op in ops])[None]
    arrays = ori.master_pattern_arrays(bto_mp, 20)
    rng = np.random.default_rng(0)
    for k in range(6):
        clean = ori.project_patterns(ops[k] * r, det, bto_mp)
        counts = 200 * (clean - clean.min()) / np.ptp(clean) + 50
        noisy = rng.poisson(counts).astype(np.float32)
        c = ori.compare_variants(noisy, q, det.pc.reshape(-1, 3), ori.detector_matrix(det), arrays)
        assert c.variant[0] == k
        assert c.margin[0] > 0 and 0.5 * c.ncc[0, k] < c.confidence[0] < 1.2 * c.ncc[0, k]
        partner = k ^ 1  # +z/-z, +x/-x, +y/-y
        assert abs(c.ncc[0, k] - c.ncc[0, partner]) < 0.03


def test_variant_significance_is_a_calibrated_z_score(bto_mp):
    """The significance of a polarity call (+z against -z) divides the
    margin by its standard error estimated from the pattern's own
    residual: over many noise draws of one pattern the margins scatter by
    that standard error (white noise: within 15 %), and a pattern without
    signal gives calls of significance within the noise."""
    det = EBSDDetector((60, 60), pc=[0.5, 0.3, 0.6], sample_tilt=70)
    r = Rotation.from_euler(np.deg2rad([[10, 30, 50]]))
    ops = variant_operators()
    q = np.stack([(ops[k] * r).data.reshape(4) for k in (0, 1)])[None]
    arrays = ori.master_pattern_arrays(bto_mp, 20)
    clean = ori.standardise(ori.project_patterns(r, det, bto_mp).reshape(1, -1))
    rng = np.random.default_rng(1)
    n = 200
    noisy = (0.3 * clean + rng.normal(size=(n, clean.size))).reshape(n, 60, 60)
    pcs, om = np.tile(det.pc.reshape(-1, 3), (n, 1)), ori.detector_matrix(det)
    c = ori.compare_variants(noisy, np.repeat(q, n, axis=0), pcs, om, arrays)
    # With two candidates the kept one's confidence index is the margin
    m = np.where(c.variant == 0, c.confidence, -c.confidence)  # signed: +z against -z
    se = c.confidence / c.significance
    assert 0.85 < m.std() / se.mean() < 1.15, (m.std(), se.mean())
    assert abs(m.mean() - 0.3) < 3 * m.std() / np.sqrt(n)  # unbiased: the NCC scale
    # Noise alone: |z| of the kept call is that of the larger of two
    # mirrored normal draws, rarely beyond 3
    pure = rng.normal(size=(n, 60, 60))
    c0 = ori.compare_variants(pure, np.repeat(q, n, axis=0), pcs, om, arrays)
    assert np.mean(c0.significance >= 2) < 0.1 and np.mean(c0.significance >= 3) < 0.02
