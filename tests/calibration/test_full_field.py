import numpy as np

from kikuchipy_geomdic.calibration._full_field import (
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
