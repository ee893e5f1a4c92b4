import numpy as np
import pytest

from kikuchipy_geomdic.calibration.jacobian import analytic_jacobian, finite_difference_jacobian
from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, DEFAULT_STEPS
from kikuchipy_geomdic.patterns import displacement as dsp
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation import synthetic
from kikuchipy_geomdic.validation.orientations import perturb_rotations


@pytest.fixture(scope="module")
def jacobians(si_mp):
    sm = synthetic.synthetic_map(si_mp, (5, 5), shape=(120, 120), seed=0)
    pts = np.argwhere(np.ones((5, 5), bool))
    exp = sm.signal.data.reshape(-1, 120, 120)
    rot = sm.xmap.rotations.flatten()

    def measure(g):
        sim = simulate_patterns(si_mp, rot, g.detector(pts), 20)
        return dsp.measure_displacements(sim, exp, seed=0)

    geo = sm.start_geometry
    f0 = measure(geo)
    ja = analytic_jacobian(geo, pts, f0.positions, f0.counts, DEFAULT_PARAMETERS, DEFAULT_STEPS)
    jf = finite_difference_jacobian(
        lambda g: measure(g).residual, geo, DEFAULT_PARAMETERS, DEFAULT_STEPS
    )
    return ja, jf


def test_analytic_matches_finite_difference(jacobians):
    # Measured at 120 x 120 px from the default start (1.5 % of the width
    # off): 5-7.5 % per column, the DIC noise and its ~2 % underestimate
    # of shifts in the finite differences of a 0.6 px change
    ja, jf = jacobians
    rel = np.linalg.norm(ja - jf, axis=0) / np.linalg.norm(jf, axis=0)
    assert rel.max() < 0.1, dict(zip(DEFAULT_PARAMETERS, rel))


def test_sample_tilt_column_is_minus_tilt(jacobians):
    for j in jacobians:
        i, k = DEFAULT_PARAMETERS.index("tilt"), DEFAULT_PARAMETERS.index("sample_tilt")
        assert np.array_equal(j[:, k], -j[:, i])


def test_finite_difference_derives_equivalents_without_measuring():
    from kikuchipy_geomdic.geometry import MapGeometry

    geo = MapGeometry((0.5, 0.3, 0.6), (60, 60), 70, 8, (10, 10), (3, 3), tilt=1.0)
    calls = []

    def b(g):
        calls.append(g)
        return np.array([g.tilt - g.sample_tilt, g.pc[0]])

    j = finite_difference_jacobian(b, geo, ["pcx", "tilt", "sample_tilt"], DEFAULT_STEPS)
    assert len(calls) == 4  # pcx and tilt, +- each
    assert np.allclose(j, [[0, 1, -1], [1, 0, 0]])


def test_rotation_columns_predict_measured_displacements(si_mp):
    # g -> g * T moves every feature as the rotation columns say: the sign
    # and size of J_rot checked against DIC of patterns simulated at g and
    # at g * T (0.3 deg about a skew axis), 96 px
    from orix.quaternion import Rotation

    from kikuchipy_geomdic.calibration.jacobian import pattern_jacobian

    geo = synthetic.default_geometry((1, 1), (96, 96))
    pts = np.zeros((4, 2))
    rot = perturb_rotations(Rotation.identity(4), 90, 3)  # arbitrary orientations
    w = np.deg2rad(0.3) * np.array([0.48, -0.8, 0.36])
    t = Rotation.from_axes_angles(w / np.linalg.norm(w), np.linalg.norm(w))
    det = geo.detector(pts)
    a = simulate_patterns(si_mp, rot, det, 20)
    b = simulate_patterns(si_mp, rot * t, det, 20)
    f = dsp.measure_displacements(a, b, rois=(6, 6), seed=0)
    _, jr = pattern_jacobian(geo, pts, f.positions, ["pcx"], {"pcx": 0.005})
    predicted = -(jr @ w)  # the displacement is minus the Jacobian times the change
    has = f.counts > 0
    err = np.linalg.norm(predicted - f.u, axis=-1)[has]
    size = np.linalg.norm(f.u, axis=-1)[has]
    assert np.sqrt((size**2).mean()) > 0.3  # a measurable rotation (0.38 px)
    assert np.sqrt((err**2).mean()) < 0.05
    # The opposite sign is far off
    err_flipped = np.linalg.norm(-predicted - f.u, axis=-1)[has]
    assert np.sqrt((err_flipped**2).mean()) > 0.5


def test_pattern_jacobian_averages_to_analytic(jacobians, si_mp):
    from kikuchipy_geomdic.calibration.jacobian import pattern_jacobian

    geo = synthetic.default_geometry((3, 3), (60, 60))
    pts = np.argwhere(np.ones((3, 3), bool))
    rng = np.random.default_rng(0)
    pos = rng.uniform(5, 55, size=(9, 16, 2))
    counts = rng.integers(0, 3, size=(9, 16))
    jg, jr = pattern_jacobian(geo, pts, pos, DEFAULT_PARAMETERS, DEFAULT_STEPS)
    assert jg.shape == (9, 16, 2, 6) and jr.shape == (9, 16, 2, 3)
    ja = analytic_jacobian(geo, pts, pos, counts, DEFAULT_PARAMETERS, DEFAULT_STEPS)
    manual = (jg * (counts > 0)[..., None, None]).sum(axis=0).reshape(32, 6) / 9
    np.testing.assert_allclose(ja, manual)


def test_lattice_derivative_against_a_stretched_master_pattern(bto_mp):
    """The derivative by the c axis' stretch is the finite difference of
    patterns projected from the master pattern of a stretched crystal."""
    from dataclasses import replace

    from kikuchipy.detectors import EBSDDetector
    from orix.quaternion import Rotation

    from kikuchipy_geomdic.calibration.jacobian import _directions, lattice_derivative
    from kikuchipy_geomdic.indexing import orientation as ori

    q = Rotation.from_euler(np.deg2rad([[10, 35, 60], [100, 20, 5]])).data
    pc = np.array([[0.5, 0.3, 0.6]] * 2)
    om = ori.detector_matrix(EBSDDetector(sample_tilt=70))
    arrays = ori.master_pattern_arrays(bto_mp, 20)
    shape = (60, 60)
    _, j_rot, _ = ori.project_derivatives(q, pc, om, arrays, shape)
    analytic = lattice_derivative(j_rot, _directions(pc, shape, om), q)
    h = 1e-4
    plus, minus = (
        ori.project_arrays(q, pc, om, replace(arrays, stretch=1 + s * h), shape).reshape(2, -1)
        for s in (1, -1)
    )
    numeric = (plus - minus) / (2 * h)
    for a, n in zip(analytic, numeric):
        assert np.corrcoef(a, n)[0, 1] > 0.99
        assert (a @ n) / (a @ a) == pytest.approx(1, abs=0.03)
