"""The Cramer-Rao bound (kikuchipy_geomdic.calibration.bound) against what it claims:
its scaling with the dose, its ordering, an estimator's scatter and a
Fisher matrix built independently here."""

import types

import numpy as np
import pytest
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration.bound import CramerRaoBound, cramer_rao_bound
from kikuchipy_geomdic.calibration.jacobian import parameter_derivatives
from kikuchipy_geomdic.calibration.result import GeometryRefinementResult
from kikuchipy_geomdic.geometry import copy_detector, rotations_from_vectors
from kikuchipy_geomdic.geometry.maps import flat_index
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation import synthetic

SHAPE = (48, 48)
NAV = (4, 4)


def _map(mp, dose):
    return synthetic.synthetic_map(mp, NAV, shape=SHAPE, dose=dose, seed=0)


def _bound(sm, **kwargs):
    return cramer_rao_bound(
        sm.signal, sm.xmap, sm.geometry, sm.master_pattern, sm.energy, **kwargs
    )


@pytest.fixture(scope="module")
def maps(si_mp):
    return {dose: _map(si_mp, dose) for dose in (50, 800)}


@pytest.fixture(scope="module")
def bounds(maps):
    return {dose: _bound(sm) for dose, sm in maps.items()}


def test_bound_scales_with_dose(bounds):
    # 16 times the counts: a quarter of the bound, for every parameter
    lo, hi = bounds[50], bounds[800]
    assert set(lo.sigma) == {
        "pcx",
        "pcy",
        "pcz",
        "tilt",
        "azimuthal",
        "sample_tilt",
        "tilt-sample_tilt",
    }
    for name in ("pcx", "pcy", "pcz", "azimuthal", "tilt-sample_tilt"):
        for s in ("sigma", "sigma_known_orientations"):
            ratio = getattr(lo, s)[name] / getattr(hi, s)[name]
            assert ratio == pytest.approx(4.0, rel=0.15), (name, s, ratio)
    # Only their difference is determined
    assert lo.sigma["tilt"] == lo.sigma["sample_tilt"] == np.inf


def test_known_orientations_never_worse(bounds):
    for crb in bounds.values():
        for name, free in crb.sigma.items():
            assert crb.sigma_known_orientations[name] <= free
        # A detector angle is a rotation of every crystal: with free
        # orientations only the PC field across the map is left of it
        for name in ("azimuthal", "tilt-sample_tilt"):
            assert crb.sigma[name] > 10 * crb.sigma_known_orientations[name]
        assert np.all(crb.r_squared > 0.3)
        assert isinstance(crb, CramerRaoBound)
        assert "tilt-sample_tilt" in repr(crb)


def test_angle_bound_does_not_depend_on_the_steps(maps):
    # With free orientations the angles' information is a small difference
    # between columns: it must not come from finite-difference error
    sm = maps[50]
    params = ["pcx", "pcy", "pcz", "azimuthal", "tilt"]
    a = _bound(sm, parameters=params)
    b = _bound(
        sm,
        parameters=params,
        steps={"pcx": 5e-5, "pcy": 5e-5, "pcz": 5e-5, "azimuthal": 0.04, "tilt": 0.04},
    )
    # Measured: 0.1-0.2 % between PC steps of 5e-5 and 1e-4 (larger steps
    # average over the interpolation's kinks: 8 % smaller at 4e-4)
    for name in params:
        assert b.sigma[name] == pytest.approx(a.sigma[name], rel=0.01), name


# --------------------------------------------------------------------- #
# Against ground truth: known noise, an estimator, a Fisher matrix
# --------------------------------------------------------------------- #

GAIN, OFFSET = 2.0, 0.5


@pytest.fixture(scope="module")
def tiny(si_mp):
    """Three clean patterns of 40 px, their geometry and orientations."""
    geo = synthetic.default_geometry((3, 3), (40, 40))
    pts = np.array([[0, 0], [1, 2], [2, 1]])
    rot = Rotation.from_euler(np.deg2rad([[10, 30, 50], [80, 40, 20], [150, 20, 70]]))
    clean = simulate_patterns(si_mp, rot, geo.detector(pts), 20).astype(np.float64)
    sigma = 0.1 * clean.std()
    return types.SimpleNamespace(geo=geo, pts=pts, rot=rot, clean=clean, sigma=sigma, mp=si_mp)


def _noisy(tiny, rng):
    return GAIN * tiny.clean + OFFSET + tiny.sigma * rng.standard_normal(tiny.clean.shape)


def test_noise_estimate(tiny):
    rng = np.random.default_rng(1)
    obs = _noisy(tiny, rng)
    args = (obs, tiny.rot, tiny.geo, tiny.mp, 20)
    est = cramer_rao_bound(*args, points=tiny.pts, parameters=["pcx", "pcy", "pcz"])
    known = cramer_rao_bound(
        *args, points=tiny.pts, parameters=["pcx", "pcy", "pcz"], noise=tiny.sigma
    )
    assert np.allclose(est.noise, tiny.sigma, rtol=0.05)
    assert np.allclose(est.gain, GAIN, rtol=0.02)
    assert np.allclose(est.offset, OFFSET, atol=0.05 * GAIN * tiny.clean.mean())
    for name in est.sigma:
        assert est.sigma[name] == pytest.approx(known.sigma[name], rel=0.1)


def _estimator_scatter(tiny, seed):
    """Scatter of least-squares estimates of pcx (gain and offset free per
    pattern, the rest known) over 1000 noise draws, over the bound."""
    # Noisier than the other tests: the scatter then spans the bound's
    # difference step, not a fraction of one interpolation kink
    sigma = 2 * tiny.clean.std()
    crb = cramer_rao_bound(
        GAIN * tiny.clean + OFFSET,
        tiny.rot,
        tiny.geo,
        tiny.mp,
        20,
        points=tiny.pts,
        parameters=["pcx"],
        noise=sigma,
    )
    bound = crb.sigma_known_orientations["pcx"]
    # The model on a grid of pcx around the truth, simulated once
    grid = np.linspace(-6, 6, 49) * bound
    shift = np.stack([grid, 0 * grid, 0 * grid], axis=-1)[:, None]
    pcs = tiny.geo.pc_at(tiny.pts)[None] + shift
    det = copy_detector(tiny.geo.detector(tiny.pts), pc=pcs.reshape(-1, 3))
    rot = Rotation(np.tile(tiny.rot.data, (len(grid), 1)))
    model = simulate_patterns(tiny.mp, rot, det, 20).astype(np.float64)
    model = model.reshape(len(grid), 3, -1)
    model -= model.mean(axis=-1, keepdims=True)
    rng = np.random.default_rng(seed)
    trials = 1000
    noise = sigma * rng.standard_normal((trials,) + tiny.clean.shape)
    obs = (GAIN * tiny.clean + OFFSET + noise).reshape(trials, 3, -1)
    obs -= obs.mean(axis=-1, keepdims=True)
    # Sum of squares after the best gain and offset: minus the projections
    dots = np.einsum("tip,kip->tki", obs, model)
    cost = -(dots**2 / (model**2).sum(axis=-1)[None]).sum(axis=-1)
    k = np.argmin(cost, axis=1)
    assert np.all((k > 0) & (k < len(grid) - 1))
    c0, c1, c2 = (cost[np.arange(trials), k + d] for d in (-1, 0, 1))
    est = grid[k] + (grid[1] - grid[0]) * 0.5 * (c0 - c2) / (c0 - 2 * c1 + c2)
    assert abs(np.mean(est)) < 4 * bound / np.sqrt(trials)
    return np.std(est) / bound


def test_estimator_scatter_attains_the_bound(tiny):
    # 1000 draws: the scatter is known to 2.2 % (seeds 2-9 gave 0.94-1.02)
    assert _estimator_scatter(tiny, seed=2) == pytest.approx(1.0, rel=0.1)


def test_matches_fisher_built_here(tiny):
    """The whole Fisher matrix of PC, every rotation, gain and offset,
    from other steps and orix's own axis-angle rotations, inverted
    without any Schur complement."""
    obs = GAIN * tiny.clean + OFFSET
    names = ["pcx", "pcy", "pcz"]
    crb = cramer_rao_bound(
        obs, tiny.rot, tiny.geo, tiny.mp, 20, points=tiny.pts, parameters=names, noise=1.0
    )
    n, h, hr = len(tiny.pts), 3e-4, np.deg2rad(0.03)

    def sim(geo, rot):
        det = geo.detector(tiny.pts)
        return GAIN * simulate_patterns(tiny.mp, rot, det, 20).reshape(n, -1).astype(float)

    s0 = sim(tiny.geo, tiny.rot) / GAIN
    npx = s0.shape[1]
    k = 3 + 5 * n
    jac = np.zeros((n * npx, k))
    for j, name in enumerate(names):
        d = sim(tiny.geo.updated({name: h}), tiny.rot) - sim(
            tiny.geo.updated({name: -h}), tiny.rot
        )
        jac[:, j] = d.ravel() / (2 * h)
    for axis in range(3):
        v = np.zeros(3)
        v[axis] = 1
        plus = tiny.rot * Rotation.from_axes_angles(v, hr)
        minus = tiny.rot * Rotation.from_axes_angles(v, -hr)
        d = (sim(tiny.geo, plus) - sim(tiny.geo, minus)) / (2 * hr)
        for i in range(n):
            jac[i * npx : (i + 1) * npx, 3 + 3 * i + axis] = d[i]
    for i in range(n):
        jac[i * npx : (i + 1) * npx, 3 + 3 * n + i] = s0[i]
        jac[i * npx : (i + 1) * npx, 3 + 4 * n + i] = 1.0
    cov = np.linalg.inv(jac.T @ jac)
    expected = np.sqrt(np.diag(cov)[:3])
    got = np.array([crb.sigma[name] for name in names])
    assert np.allclose(got, expected, rtol=0.03)
    # Orientations known: drop the rotation columns
    keep = np.r_[0:3, 3 + 3 * n : k]
    cov_known = np.linalg.inv(jac[:, keep].T @ jac[:, keep])
    got = np.array([crb.sigma_known_orientations[name] for name in names])
    assert np.allclose(got, np.sqrt(np.diag(cov_known)[:3]), rtol=0.03)
    # Orientations free cost precision here: the test is not vacuous
    assert np.all(expected > 1.2 * np.sqrt(np.diag(cov_known)[:3]))


def test_angle_column_matches_direct_differences(tiny):
    """The angle columns are built from the PC and rotation columns; with
    the orientations known the bound equals one from direct differences."""
    obs = GAIN * tiny.clean + OFFSET
    crb = cramer_rao_bound(
        obs,
        tiny.rot,
        tiny.geo,
        tiny.mp,
        20,
        points=tiny.pts,
        parameters=["azimuthal", "twist", "tilt"],
        noise=1.0,
    )
    n, h = len(tiny.pts), 0.02
    for name in ("azimuthal", "twist", "tilt"):
        geo_p, geo_m = tiny.geo.updated({name: h}), tiny.geo.updated({name: -h})
        d = (
            simulate_patterns(tiny.mp, tiny.rot, geo_p.detector(tiny.pts), 20)
            - simulate_patterns(tiny.mp, tiny.rot, geo_m.detector(tiny.pts), 20)
        ).reshape(n, -1) * (GAIN / (2 * h))
        s0 = tiny.clean.reshape(n, -1)
        # Gain and offset eliminated per pattern: project them out
        info = 0.0
        for i in range(n):
            a = np.stack([s0[i], np.ones_like(s0[i])], axis=1)
            r = d[i] - a @ np.linalg.lstsq(a, d[i], rcond=None)[0]
            info += r @ r
        single = cramer_rao_bound(
            obs, tiny.rot, tiny.geo, tiny.mp, 20, points=tiny.pts, parameters=[name], noise=1.0
        )
        assert single.sigma_known_orientations[name] == pytest.approx(info**-0.5, rel=0.03)
    # Three angles together: finite, and larger than each alone
    assert all(np.isfinite(v) for v in crb.sigma_known_orientations.values())


@pytest.mark.parametrize("name", ["tilt", "azimuthal", "twist"])
def test_angle_is_a_crystal_rotation(tiny, name):
    """At a fixed PC, an angle changes the pattern as the crystal rotation
    the angle columns are built from: the sign and size of that rotation."""
    h = 0.02
    c, _ = parameter_derivatives(tiny.geo, tiny.pts, name, 1e-3)
    det = tiny.geo.detector(tiny.pts)  # The PCs stay those of tiny.geo

    def sim(geo, rot):
        angles = dict(zip(("tilt", "azimuthal", "sample_tilt", "twist"), geo.angles))
        return simulate_patterns(tiny.mp, rot, copy_detector(det, **angles), 20).astype(float)

    by_angle = sim(tiny.geo.updated({name: h}), tiny.rot) - sim(
        tiny.geo.updated({name: -h}), tiny.rot
    )
    w = rotations_from_vectors(c * h)
    by_rotation = sim(tiny.geo, tiny.rot * w) - sim(tiny.geo, tiny.rot * ~w)
    # The opposite rotation gives an error of 2
    err = np.linalg.norm(by_rotation - by_angle) / np.linalg.norm(by_angle)
    assert err < 0.02, err


# --------------------------------------------------------------------- #
# Inputs, chunks, tables
# --------------------------------------------------------------------- #


def test_chunks_array_input_and_points(maps):
    sm = maps[50]
    pts = np.array([[0, 0], [1, 3], [3, 2]])
    names = ["pcx", "pcz", "sample_tilt"]
    a = _bound(sm, points=pts, parameters=names)
    b = _bound(sm, points=pts, parameters=names, max_bytes=1)  # one pattern a chunk
    data = sm.signal.data[pts[:, 0], pts[:, 1]]
    rot = sm.xmap.rotations.data.reshape(NAV + (4,))[pts[:, 0], pts[:, 1]]
    c = cramer_rao_bound(
        data, Rotation(rot), sm.geometry, sm.master_pattern, 20, points=pts, parameters=names
    )
    for other in (b, c):
        assert other.sigma == pytest.approx(a.sigma, rel=1e-9)
    assert a.columns == ("pcx", "pcz", "sample_tilt")
    assert a.sigma["tilt-sample_tilt"] == a.sigma["sample_tilt"]
    d = _bound(sm, points=4, parameters=["pcx"])
    assert len(d.points) == 4


def test_table_with_standard_errors(bounds):
    crb = bounds[50]
    se = {name: 2 * v for name, v in crb.sigma.items()}
    text = crb.table(se)
    assert "ratio" in text and "2.00" in text
    # The result's method shows the same, from its standard errors
    result = types.SimpleNamespace(standard_errors=se)
    assert GeometryRefinementResult.compare_bound(result, crb) == text


def test_bad_input(maps, tiny):
    sm = maps[50]
    mp, geo = sm.master_pattern, sm.geometry
    data = sm.signal.data.reshape((16,) + SHAPE)
    rot = sm.xmap.rotations
    with pytest.raises(ValueError, match="differs from the geometry's detector shape"):
        cramer_rao_bound(data[:, :40, :40], rot, geo, mp, 20)
    with pytest.raises(ValueError, match="15 patterns for a map of 4 x 4"):
        cramer_rao_bound(data[:15], rot, geo, mp, 20)
    with pytest.raises(ValueError, match="3 rotations for 16 patterns"):
        cramer_rao_bound(data, rot[:3], geo, mp, 20)
    with pytest.raises(ValueError, match="2 patterns but 3 points"):
        cramer_rao_bound(data[:2], rot, geo, mp, 20, points=np.array([[0, 0], [1, 1], [2, 2]]))
    with pytest.raises(ValueError, match="outside the map"):
        cramer_rao_bound(data[:1], rot, geo, mp, 20, points=np.array([[4, 0]]))
    nan = data.copy()
    nan[5, 3, 3] = np.nan
    with pytest.raises(ValueError, match=r"1 pattern\(s\) contain NaN .* \(row, col\) \[1, 1\]"):
        cramer_rao_bound(nan, rot, geo, mp, 20)
    with pytest.raises(ValueError, match="fitted exactly"):
        cramer_rao_bound(tiny.clean, tiny.rot, tiny.geo, tiny.mp, 20, points=tiny.pts)
    with pytest.raises(ValueError, match="noise must be positive"):
        cramer_rao_bound(data, rot, geo, mp, 20, noise=0.0)
    with pytest.raises(ValueError, match="Unknown geometry parameter"):
        cramer_rao_bound(data, rot, geo, mp, 20, parameters=["pc_x"])
    with pytest.raises(TypeError, match="geometry must be a MapGeometry"):
        cramer_rao_bound(data, rot, sm.detector, mp, 20)
    with pytest.raises(TypeError, match="patterns must be an EBSD signal or a NumPy array"):
        cramer_rao_bound(data.tolist(), rot, geo, mp, 20)
    with pytest.raises(TypeError, match="rotations must be an orix Rotation"):
        cramer_rao_bound(data, rot.data, geo, mp, 20)


@pytest.fixture(scope="module")
def two_phases():
    from kikuchipy_geomdic.validation import multiphase

    return multiphase.two_phase_map(
        multiphase.PAIRS["ferrite+austenite"], (6, 7), (40, 40), seed=1
    )


def test_two_phases_add_their_information(two_phases):
    """A list of master patterns, one per phase: each pattern simulated
    from its phase's, the information of the two phases' patterns summed,
    as the bounds of each phase's points alone combine."""
    tp = two_phases
    names = ["pcx", "pcy", "pcz"]
    mps = [tp.simulators[name] for name in tp.phase_names]
    both = cramer_rao_bound(tp.signal, tp.xmap, tp.geometry, mps, tp.energy, parameters=names)
    assert len(both.points) == tp.xmap.size
    alone = []
    for phase_id, mp in enumerate(mps):
        pts = np.argwhere(tp.xmap.phase_id.reshape(tp.xmap.shape) == phase_id)
        alone.append(
            cramer_rao_bound(
                tp.signal, tp.xmap, tp.geometry, mp, tp.energy, points=pts, parameters=names
            )
        )
    info = sum(np.linalg.inv(b.covariance) for b in alone)
    assert np.allclose(both.covariance, np.linalg.inv(info), rtol=1e-6)
    for name in names:
        assert both.sigma[name] < min(b.sigma[name] for b in alone)
    # Points of no phase with a master pattern (here not indexed): left
    # out, and said so
    xmap = tp.xmap.deepcopy()
    some = np.zeros(xmap.size, dtype=bool)
    some[:3] = True
    xmap[some].phase_id = -1
    with pytest.warns(UserWarning, match="3 of 42 patterns are of phases without a master"):
        fewer = cramer_rao_bound(tp.signal, xmap, tp.geometry, mps, tp.energy, parameters=names)
    assert len(fewer.points) == 39 and not np.isin(0, flat_index(fewer.points, xmap.shape))
    for name in names:
        assert fewer.sigma[name] > both.sigma[name]
    # A calibration's crystal map, one point per pattern, as the whole map's
    pts = np.argwhere(np.ones(tp.xmap.shape, dtype=bool))[::2]
    chosen = np.zeros(tp.xmap.size, dtype=bool)
    chosen[flat_index(pts, tp.xmap.shape)] = True
    per_pattern = tp.xmap[chosen]
    args = (tp.signal, per_pattern, tp.geometry, mps, tp.energy)
    half = cramer_rao_bound(*args, points=pts, parameters=names)
    whole = cramer_rao_bound(*args[:1], tp.xmap, *args[2:], points=pts, parameters=names)
    assert np.allclose(half.covariance, whole.covariance, rtol=1e-12)
    with pytest.raises(ValueError, match="A CrystalMap of 21 points for 42 patterns"):
        cramer_rao_bound(*args, parameters=names)
    with pytest.raises(TypeError, match="needs rotations as a CrystalMap"):
        cramer_rao_bound(
            tp.signal, tp.xmap.rotations, tp.geometry, mps, tp.energy, parameters=names
        )
