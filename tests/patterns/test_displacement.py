"""Tests of the DIC displacement measurement (paper section 2.2).

Ground truth is :func:`kikuchipy_geomdic.geometry.projection.forward_map`: for a
geometry change it says where every pixel of pattern A lands in pattern
B. The measured ROI displacement u_(r,i) (Eq. 1) is compared with the
true displacement averaged exactly as the measurement is: at the same
vectors' A endpoints (the points where LK measured them), with the same
ROI membership rule (:func:`~kikuchipy_geomdic.patterns.roi.roi_average`
with ``values=`` the truth). The error is the RMS over patterns and ROIs
with vectors of the length of u_measured - u_true, in pixels.

Patterns are 120 x 120 px simulated from the dynamical Si master pattern
at PC (0.5, 0.3, 0.6), sample tilt 70 deg, 20 kV.
"""

import inspect
import sys
import warnings

import dask
import dask.array as da
import numpy as np
import pytest
from kikuchipy.detectors import EBSDDetector
from numpy.testing import assert_allclose, assert_array_equal
from orix.quaternion import Rotation
from scipy import ndimage

from kikuchipy_geomdic.geometry import forward_map
from kikuchipy_geomdic.patterns import displacement as dsp
from kikuchipy_geomdic.patterns.roi import roi_average
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.patterns.vectors import _DIC_DEFAULTS, pattern_vectors, resolve_backend

SHAPE = (120, 120)
PC_A = (0.5, 0.3, 0.6)
ANGLES_A = (0.0, 0.0, 70.0, 0.0)  # tilt, azimuthal, sample_tilt, twist
N_CASE = 6  # Patterns per geometry case

#: Geometry B per case: (pc, angles)
CASES = {
    "pc_shift": ((0.51, 0.285, 0.6), ANGLES_A),
    "pcz": ((0.5, 0.3, 0.62), ANGLES_A),
    "tilt": (PC_A, (1.0, 0.0, 70.0, 0.0)),
    "azimuthal": (PC_A, (0.0, 1.0, 70.0, 0.0)),
    "combined": ((0.51, 0.31, 0.59), (0.5, 0.5, 70.0, 0.0)),
}

#: Measured on these data (RMS per ROI, px), both backends within 0.01:
#: noise-free 0.03-0.04; noisy 0.09-0.10
TOL_CLEAN = 0.05
TOL_NOISY = 0.2

#: Noise model of the "experimental" patterns: detector blur of 1 px,
#: then Poisson counts with 1000 counts at full contrast over a background
#: of 500 (per-pixel SNR of the band contrast about 3-4), and the paper's
#: Gaussian noise (5 % of the std) on the simulated patterns
PSF = 1.0
DOSE = 1000
NOISE_A = 0.05


def _detector(pc, angles):
    tilt, azimuthal, sample_tilt, twist = angles
    return EBSDDetector(
        shape=SHAPE,
        pc=pc,
        tilt=tilt,
        azimuthal=azimuthal,
        sample_tilt=sample_tilt,
        twist=twist,
    )


def _random_rotations(n, seed):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return Rotation(q / np.linalg.norm(q, axis=1, keepdims=True))


def _experimental(patterns, seed):
    """Blur and Poisson shot noise, as a camera would add."""
    rng = np.random.default_rng(seed)
    b = ndimage.gaussian_filter(patterns.astype(np.float64), (0, PSF, PSF))
    lo = b.min(axis=(1, 2), keepdims=True)
    hi = b.max(axis=(1, 2), keepdims=True)
    return rng.poisson(DOSE * (0.5 + (b - lo) / (hi - lo))).astype(np.float32)


def _true_u(field, pc_b, angles_b, pc_a=PC_A, angles_a=ANGLES_A):
    """Forward-map displacement averaged like the measurement (N, R, 2)."""
    u = np.zeros_like(field.u)
    for i, v in enumerate(field.vectors):
        xb, yb = forward_map(v[:, 0], v[:, 1], pc_a, angles_a, pc_b, angles_b, SHAPE)
        truth = np.stack([xb - v[:, 0], yb - v[:, 1]], axis=1)
        u[i], counts, _ = roi_average(v[:, :2], v[:, 2:], field.shape, field.rois, values=truth)
        assert_array_equal(counts, field.counts[i])
    return u


def _rms(field, true_u):
    has = field.counts > 0
    return float(np.sqrt(np.mean(np.sum((field.u - true_u)[has] ** 2, axis=-1))))


@pytest.fixture(scope="module")
def patterns(si_mp):
    """Pattern A per orientation and pattern B per case, noise-free."""
    rot = _random_rotations(N_CASE, seed=1)
    a = simulate_patterns(si_mp, rot, _detector(PC_A, ANGLES_A), 20)
    b = {k: simulate_patterns(si_mp, rot, _detector(*g), 20) for k, g in CASES.items()}
    return a, b


@pytest.fixture(scope="module")
def measured(patterns):
    """Fields per (case, backend, noisy), computed once."""
    a, b = patterns
    cache = {}

    def get(case, dic, noisy=False):
        key = (case, dic, noisy)
        if key not in cache:
            if noisy:
                exp = _experimental(b[case], seed=2)
                kw = dict(noise=NOISE_A, blur=PSF)
            else:
                exp, kw = b[case], {}
            cache[key] = dsp.measure_displacements(
                a, exp, dic=dic, seed=0, keep_vectors=True, **kw
            )
        return cache[key]

    return get


# --------------------------------------------------------------------- #
# The field: Eqs. 2, 3 and 8
# --------------------------------------------------------------------- #


def test_field_averages_over_n_eq2_and_orders_b_eq3():
    u = np.array(
        [[[1.0, 2.0], [3.0, 4.0]], [[5.0, 6.0], [0.0, 0.0]]]  # ROI 1 has no vector in pattern 1
    )
    counts = np.array([[2, 1], [3, 0]])
    field = dsp.DisplacementField(u, counts, np.zeros_like(u), (10, 20), (1, 2), "opencv")
    # Eq. 2 divides by N = 2, not by the one pattern with vectors
    assert_allclose(field.mean, [[3.0, 4.0], [1.5, 2.0]])
    assert_allclose(field.residual, [3.0, 4.0, 1.5, 2.0])
    assert_array_equal(field.total_counts, [5, 1])
    # c90 of (5, 1) = 4.6
    assert_allclose(field.weights, [1.0, np.sqrt(1 / 4.6)])
    assert_allclose(field.residual_weights, np.repeat(field.weights, 2))
    sub = field.select([1])
    assert sub.n_patterns == 1
    assert_allclose(sub.mean, [[5.0, 6.0], [0.0, 0.0]])


# --------------------------------------------------------------------- #
# Accuracy against the forward map
# --------------------------------------------------------------------- #


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
@pytest.mark.parametrize("case", list(CASES))
def test_accuracy_noise_free(measured, case, dic):
    field = measured(case, dic)
    assert field.backend == dic
    rms = _rms(field, _true_u(field, *CASES[case]))
    assert rms <= TOL_CLEAN, f"{case} {dic}: {rms:.4f} px"
    # Every ROI measured, several vectors per ROI and pattern
    assert (field.total_counts > 0).all()
    assert field.counts.mean() > 4


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
@pytest.mark.parametrize("case", ["pc_shift", "pcz", "tilt", "combined"])
def test_accuracy_noisy(measured, case, dic):
    field = measured(case, dic, noisy=True)
    rms = _rms(field, _true_u(field, *CASES[case]))
    assert rms <= TOL_NOISY, f"{case} {dic}: {rms:.4f} px"
    # The displacement is well above the error: the field was measured
    true_u = _true_u(field, *CASES[case])
    has = field.counts > 0
    assert np.sqrt(np.mean(np.sum(true_u[has] ** 2, axis=-1))) > 4 * rms


@pytest.mark.parametrize("case", ["pc_shift", "pcz"])
def test_backends_agree(measured, case):
    f_cv, f_sk = measured(case, "opencv"), measured(case, "skimage")
    has = (f_cv.counts > 0) & (f_sk.counts > 0)
    d = np.sqrt(np.mean(np.sum((f_cv.u - f_sk.u)[has] ** 2, axis=-1)))
    assert d < 0.05
    assert abs(f_cv.counts.sum() / f_sk.counts.sum() - 1) < 0.1


def test_binning_reports_full_resolution(patterns):
    a, b = patterns
    field = dsp.measure_displacements(
        a, b["pcz"], binning=2, rois=(4, 4), seed=0, keep_vectors=True
    )
    # Full-resolution displacements of 0.5-2.5 px, tracked at half
    # resolution (errors double with the pixel size): measured 0.08 px
    assert _rms(field, _true_u(field, *CASES["pcz"])) < 0.1
    assert np.abs(field.mean).max() > 1


def test_paper_mode_without_extra_outlier_tests(patterns, measured):
    a, b = patterns
    case = "combined"
    paper = dsp.measure_displacements(
        a,
        _experimental(b[case], seed=2),
        noise=NOISE_A,
        blur=PSF,
        forward_backward=None,
        robust=None,
        seed=0,
        keep_vectors=True,
    )
    full = measured(case, "opencv", noisy=True)
    # The extra tests only remove vectors
    assert paper.counts.sum() > full.counts.sum()
    assert _rms(paper, _true_u(paper, *CASES[case])) <= TOL_NOISY


# --------------------------------------------------------------------- #
# The average over many patterns (Eq. 2)
# --------------------------------------------------------------------- #


@pytest.fixture(scope="module")
def orientation_error_stack(si_mp):
    """64 patterns: B at geometry B with R_i, A at geometry A with dR_i R_i.

    The dR_i are random small rotations (0.25 deg std about each axis,
    zero mean): the orientation errors a refinement starts from. They act
    in the crystal frame (orix: left factor), so each moves its pattern
    in its own direction. (As a right factor they would act in the sample
    frame, where the mean of 64 such errors, here 0.09 deg, is one common
    rotation that no average removes: ~0.1 px.)
    """
    n = 64
    rng = np.random.default_rng(7)
    rot = _random_rotations(n, seed=8)
    vec = rng.normal(0, np.deg2rad(0.25), size=(n, 3))
    angle = np.linalg.norm(vec, axis=1)
    d_rot = Rotation.from_axes_angles(vec / angle[:, None], angle)
    pc_b, angles_b = CASES["combined"]
    a = simulate_patterns(si_mp, d_rot * rot, _detector(PC_A, ANGLES_A), 20)
    b = simulate_patterns(si_mp, rot, _detector(pc_b, angles_b), 20)
    return a, b, pc_b, angles_b


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
def test_average_field_cancels_orientation_errors(orientation_error_stack, dic):
    a, b, pc_b, angles_b = orientation_error_stack
    field = dsp.measure_displacements(a, b, dic=dic, seed=0, keep_vectors=True)
    # The geometry-only truth, averaged over the same vectors
    true_u = _true_u(field, pc_b, angles_b)
    rms = {}
    for n in (4, 16, 64):
        sub = field.select(slice(0, n))
        true_mean = true_u[:n].sum(axis=0) / n
        has = sub.total_counts > 0
        rms[n] = float(np.sqrt(np.mean(np.sum((sub.mean - true_mean)[has] ** 2, axis=-1))))
    # Single patterns are far off (orientation errors), the average is
    # not. Measured: 0.55 per pattern; 0.32, 0.07, 0.03 for N = 4, 16, 64
    per_pattern = _rms(field, true_u)
    assert per_pattern > 0.3, per_pattern
    assert rms[4] > rms[16] > rms[64], rms
    assert rms[64] < 0.05, rms


# --------------------------------------------------------------------- #
# Determinism, schedulers, chunking
# --------------------------------------------------------------------- #


def _assert_fields_equal(f1, f2):
    assert_array_equal(f1.u, f2.u)
    assert_array_equal(f1.counts, f2.counts)
    assert_array_equal(f1.positions, f2.positions)


def test_same_seed_same_result_other_seed_other_noise(patterns):
    a, b = patterns
    kw = dict(noise=0.3, rois=(4, 4))
    f1 = dsp.measure_displacements(a[:3], b["pcz"][:3], seed=5, **kw)
    f2 = dsp.measure_displacements(a[:3], b["pcz"][:3], seed=5, **kw)
    f3 = dsp.measure_displacements(a[:3], b["pcz"][:3], seed=6, **kw)
    _assert_fields_equal(f1, f2)
    assert not np.array_equal(f1.u, f3.u)
    # Both are measurements of the same field
    assert np.abs(f1.mean - f3.mean).max() < 0.3


def test_noise_differs_between_patterns():
    # Two identical pattern pairs get different noise: different vectors
    rng = np.random.default_rng(0)
    a = ndimage.gaussian_filter(rng.random((64, 64)), 2)
    b = ndimage.shift(a, (0.3, 0.6), mode="nearest")
    field = dsp.measure_displacements(
        np.stack([a, a]), np.stack([b, b]), rois=(4, 4), noise=0.5, seed=1, dic="skimage"
    )
    assert not np.array_equal(field.u[0], field.u[1])
    noiseless = dsp.measure_displacements(
        np.stack([a, a]), np.stack([b, b]), rois=(4, 4), seed=1, dic="skimage"
    )
    assert_array_equal(noiseless.u[0], noiseless.u[1])


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
def test_schedulers_and_chunks_give_identical_results(patterns, dic):
    a, b = patterns
    exp = b["combined"]
    kw = dict(noise=0.1, seed=3, dic=dic, keep_vectors=True)
    with dask.config.set(scheduler="synchronous"):
        ref = dsp.measure_displacements(a, exp, chunk_size=1, **kw)
    with dask.config.set(scheduler="threads"):
        threaded = dsp.measure_displacements(a, exp, chunk_size=4, **kw)
        lazy = dsp.measure_displacements(a, da.from_array(exp, chunks=(2, -1, -1)), **kw)
    for f in (threaded, lazy):
        _assert_fields_equal(ref, f)
        assert all(np.array_equal(v, w) for v, w in zip(ref.vectors, f.vectors))


def test_distributed_client_gives_identical_results(patterns):
    distributed = pytest.importorskip("distributed")
    a, b = patterns
    kw = dict(noise=0.1, seed=3, chunk_size=2, rois=(6, 6))
    with dask.config.set(scheduler="synchronous"):
        ref = dsp.measure_displacements(a, b["tilt"], **kw)
    with distributed.Client(
        processes=False, n_workers=1, threads_per_worker=2, dashboard_address=":0"
    ):
        f = dsp.measure_displacements(a, b["tilt"], **kw)
    _assert_fields_equal(ref, f)


# --------------------------------------------------------------------- #
# Backend choice
# --------------------------------------------------------------------- #


def test_auto_falls_back_to_skimage_without_opencv(patterns, monkeypatch):
    a, b = patterns
    monkeypatch.setitem(sys.modules, "cv2", None)  # import cv2 now fails
    assert resolve_backend("auto") == "skimage"
    with pytest.raises(ImportError, match="opencv-python-headless"):
        resolve_backend("opencv")
    with pytest.raises(ImportError, match="OpenCV"):
        dsp.measure_displacements(a[:1], b["pcz"][:1], dic="opencv")
    field = dsp.measure_displacements(a[:2], b["pcz"][:2], dic="auto", seed=0, keep_vectors=True)
    assert field.backend == "skimage"
    assert _rms(field, _true_u(field, *CASES["pcz"])) <= TOL_CLEAN


# --------------------------------------------------------------------- #
# Bad input
# --------------------------------------------------------------------- #


def test_shape_mismatch(patterns):
    a, b = patterns
    with pytest.raises(ValueError, match="shape"):
        dsp.measure_displacements(a, b["pcz"][:, :100])
    with pytest.raises(ValueError, match="shape"):
        dsp.measure_displacements(a[:3], b["pcz"])
    with pytest.raises(ValueError, match=r"\(N, rows, columns\)"):
        dsp.measure_displacements(a[None], b["pcz"][None])


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
def test_nan_and_constant_patterns(patterns, dic):
    a, b = patterns
    bad = b["pcz"].copy()
    bad[2, 5, 5] = np.nan
    with pytest.raises(ValueError, match="Experimental pattern 2 contains NaN"):
        dsp.measure_displacements(a, bad, dic=dic)
    flat = a.copy()
    flat[1] = 3.0
    with pytest.raises(ValueError, match="Simulated pattern 1 is constant"):
        dsp.measure_displacements(flat, b["pcz"], dic=dic)


def test_roi_grid_too_fine(patterns):
    a, b = patterns
    with pytest.raises(ValueError, match="too fine"):
        dsp.measure_displacements(a, b["pcz"], rois=(40, 40))
    with pytest.raises(ValueError, match="too fine"):
        dsp.measure_displacements(a, b["pcz"], rois=(8, 8), binning=4)
    with pytest.raises(ValueError, match="does not fit"):
        dsp.measure_displacements(a, b["pcz"], rois=(200, 2))


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
def test_featureless_region_gives_zero_weight_with_warning(patterns, dic):
    a, b = patterns
    a, b = a[:2].copy(), b["pc_shift"][:2].copy()
    # A detector shadow: the left quarter carries no pattern
    a[:, :, :30] = a.mean()
    b[:, :, :30] = b.mean()
    with pytest.warns(UserWarning, match="ROIs got no displacement vector"):
        field = dsp.measure_displacements(a, b, dic=dic, seed=0, keep_vectors=True)
    cols = np.arange(64) % 8
    assert_array_equal(field.weights[cols < 2], 0)
    assert (field.weights[cols >= 3] > 0).all()
    assert _rms(field, _true_u(field, *CASES["pc_shift"])) <= TOL_CLEAN


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
def test_no_features_at_all(dic):
    # Smooth ramps have no corners
    y, x = np.mgrid[:64, :64]
    ramp = np.stack([x + 0.5 * y, x + 0.5 * y]).astype(float)
    with pytest.raises(ValueError, match="No displacement vector"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            dsp.measure_displacements(ramp, ramp + 1, rois=(4, 4), dic=dic)


def test_dic_options_are_measure_displacements():
    # pattern_vectors completes its options with the defaults that
    # measure_displacements' signature shows, in its order
    params = inspect.signature(dsp.measure_displacements).parameters
    own = ("simulated", "experimental", "seed", "keep_vectors", "chunk_size")
    options = [(k, p.default) for k, p in params.items() if k not in own]
    assert options == list(_DIC_DEFAULTS.items())
    with pytest.raises(TypeError, match=r"Unknown DIC option\(s\) \['rios'\]"):
        pattern_vectors(np.ones((60, 60)), np.ones((60, 60)), rios=(2, 2))
