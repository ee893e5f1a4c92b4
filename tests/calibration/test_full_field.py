import numpy as np

from kikuchipy_geomdic.calibration._intensity import (
    MIN_PIXEL_VARIANCE,
    _pixel_variances,
    _project_out,
)


def test_project_out_removes_gain_and_offset():
    rng = np.random.default_rng(1)
    n, k, p = 3, 2, 50
    unit = rng.normal(size=(n, p))
    unit -= unit.mean(axis=1, keepdims=True)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    a = rng.normal(size=(n, k, p)).astype(np.float32)
    scale = np.array([1.0, -2.0, 0.5])
    out = _project_out(a, unit, scale)
    assert out.shape == (n, p, k)
    expected = np.empty((n, p, k))
    for i in range(n):
        basis = np.stack([np.ones(p), unit[i]], axis=1)
        cols = a[i].T.astype(np.float64)
        coef, *_ = np.linalg.lstsq(basis, cols, rcond=None)
        expected[i] = scale[i] * (cols - basis @ coef)
    assert np.allclose(out, expected, atol=1e-5)


def test_pixel_variances_fit_the_squared_residuals():
    # c0 + c1 * model per pattern, by least squares on the squared
    # residuals, c1 >= 0, each variance at least MIN_PIXEL_VARIANCE of
    # the pattern's mean square residual
    rng = np.random.default_rng(2)
    model = rng.random((4, 400)) * 3
    residual = rng.normal(size=(4, 400)) * np.sqrt(1 + 2 * model)
    residual[3] /= 1 + 2 * model[3]  # brighter pixels less noisy: c1 clipped to 0
    var = _pixel_variances(residual, model)
    for i in range(4):
        basis = np.stack([np.ones(400), model[i] - model[i].mean()], axis=1)
        c0, c1 = np.linalg.lstsq(basis, residual[i] ** 2, rcond=None)[0]
        expected = c0 + max(c1, 0.0) * basis[:, 1]
        expected = np.maximum(expected, MIN_PIXEL_VARIANCE * (residual[i] ** 2).mean())
        assert np.allclose(var[i], expected, rtol=1e-12)
    assert (var[3] == var[3][0]).all()


def test_free_model_full_field_follows_a_poorly_determined_dic_stage():
    """A few-grain Ni map of 60 px patterns as the envelope's (EMsoft's
    data, calibrated with ebsdsim's master pattern, camera counts, both
    backgrounds removed, starts indexed 1.8 % off): the DIC stage leaves
    the PC between DETERMINACY_LIMITS and FULL_FIELD_GUARD and ends 5.2e-3
    off (measured); the full field follows and ends within 1e-3, within 3
    of its standard errors, which include the grains' spread."""
    from kikuchipy_geomdic.calibration._full_field import FULL_FIELD_GUARD
    from kikuchipy_geomdic.calibration.uncertainty import DETERMINACY_LIMITS
    from kikuchipy_geomdic.geometry import MapGeometry
    from kikuchipy_geomdic.validation import master_patterns, synthetic
    from kikuchipy_geomdic.validation.camera import Camera

    assert FULL_FIELD_GUARD > DETERMINACY_LIMITS["pcx"]
    geometry = MapGeometry(
        pc=(0.5, 0.2, 0.7), shape=(60, 60), px_size=70.0, binning=8.0,
        step_sizes=(200 / 9, 200 / 9), navigation_shape=(10, 10), tilt=5.0, azimuthal=0.5,
        sample_tilt=70.0, twist=0.0,
    )  # fmt: skip
    sm = synthetic.synthetic_map(
        master_patterns.master_pattern("Ni"), (10, 10), orientations="grains",
        geometry=geometry, seed=3, start="indexed", orientation_error=1.0,
        camera=Camera(dose=150.0, static=True),
        simulator=master_patterns.master_pattern("Ni", kind="emsoft"),
    )  # fmt: skip
    res = sm.signal.refine_geometry_dic(
        sm.start_xmap, sm.start_detector, sm.master_pattern, sm.energy,
        parameters=["pcx", "pcy", "pcz", "tilt", "azimuthal"], orientation_model="free",
        show_progressbar=False,
    )  # fmt: skip
    assert "full-field" in [h.get("stage") for h in res.history]
    truth = sm.geometry.as_dict()
    for name in ("pcx", "pcy", "pcz"):
        err = res.parameters[name] - truth[name]
        assert abs(err) <= 1.5e-3, (name, err)
        assert abs(err) <= 3 * res.standard_errors[name], (name, err, res.standard_errors[name])
    assert set(res.adequacy["systematic"]) >= {"pcx", "pcy", "pcz"}


def test_holding_an_angle_leaves_a_fitted_lattice_free():
    """Putting a held angle back keeps the lattice's stretch free: the PC's
    covariance is the one marginal over the stretch (not the one given
    it), the stretch takes its step, and the PC's regression on it is
    returned for its systematic part to carry."""
    from orix.quaternion import Rotation

    from kikuchipy_geomdic.calibration._intensity import _hold, _System
    from kikuchipy_geomdic.calibration.solve import JointSystem, solve_joint
    from kikuchipy_geomdic.validation.synthetic import default_geometry

    rng = np.random.default_rng(2)
    solved, n, p = ("pcx", "pcy", "pcz", "tilt"), 12, 200
    jg = rng.normal(size=(n, p, 5))
    jg[..., 4] = 0.9 * jg[..., 2] + 0.3 * jg[..., 4]  # the stretch shares pcz's valley
    jr, w = rng.normal(size=(n, p, 3)), np.ones((n, p))
    residual = rng.normal(size=(n, p))
    prior, offsets = np.r_[np.full(4, np.inf), 1.0], np.zeros(5)
    kw = dict(prior=1e-3, offsets=np.zeros((n, 3)), geometry_prior=prior)
    normal = JointSystem.build(jg, jr, w, 1e-3, geometry_prior=prior)
    geometry = default_geometry()
    system = _System(
        geometry, Rotation.identity((n,)), residual, jg, jr, w, np.zeros((n, 3)), False,
        normal, prior, offsets,
    )  # fmt: skip
    cov = np.diag(np.full(4, 1e-8))
    _, _, out, lattice = _hold(system, ("tilt",), geometry, solved, {}, cov)
    free = solve_joint(
        jg[..., [0, 1, 2, 4]], jr, residual, w, **{**kw, "geometry_prior": prior[[0, 1, 2, 4]]}
    )
    given = solve_joint(jg[..., :3], jr, residual, w, prior=1e-3, offsets=np.zeros((n, 3)))
    assert np.allclose(out[:3, :3], free.covariance[:3, :3])
    assert out[2, 2] > 2 * given.covariance[2, 2]
    step, se, slope = lattice
    assert np.isclose(step, free.delta[3]) and np.isclose(se, np.sqrt(free.covariance[3, 3]))
    assert np.allclose(slope[:3], free.covariance[:3, 3] / free.covariance[3, 3])
    assert slope[3] == 0 and abs(slope[2]) > 0.5
