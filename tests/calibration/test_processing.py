import numpy as np
import pytest
from kikuchipy.signals import EBSD
from scipy import ndimage

from kikuchipy_geomdic.calibration import _processing
from kikuchipy_geomdic.calibration._processing import _Processing
from kikuchipy_geomdic.validation.camera import Camera, camera_counts

SHAPE = (24, 30)
N = 40


@pytest.fixture(scope="module")
def patterns():
    rng = np.random.default_rng(0)
    s0 = ndimage.gaussian_filter(rng.normal(size=(N,) + SHAPE), (0, 1.5, 1.5)).reshape(N, -1)
    columns = ndimage.gaussian_filter(rng.normal(size=(N,) + SHAPE + (4,)), (0, 2, 2, 0))
    y, x = (np.indices(SHAPE) + 0.5) / SHAPE[1]
    lobe = np.exp(-((x - 0.5) ** 2 + (y - 0.3) ** 2) / 0.2)
    return s0, columns.reshape(N, -1, 4), lobe / lobe.mean()


@pytest.mark.parametrize(
    "psf, highpass, contrast, ghost",
    [
        (0, 0, 0, False),
        (0.7, 4.0, 0, True),
        (0.7, 4.0, 0.2, False),
        (0.7, 4.0, 0.2, True),
        (1.2, 0, 0.1, False),
    ],
)
def test_columns_are_the_derivatives_of_the_processed_patterns(
    patterns, psf, highpass, contrast, ghost
):
    # Every step of the processing is differentiated by hand: a column
    # must be the central difference of the processed pattern along it.
    # The ghost, the map's mean pattern, is held: a pattern moves it by
    # 1 / N of its own change
    s0, columns, lobe = patterns
    proc = _Processing(SHAPE, psf, highpass, contrast, ghost, lobe=lobe)
    x, d = proc(s0, (columns[..., :3], columns[..., 3:]))
    assert x.shape == s0.shape and x.dtype == np.float64
    assert d.shape == (N, 4, s0.shape[1]) and d.dtype == np.float32
    h, tol = 1e-4, 2 / N if ghost else 2e-4
    for k in range(4):
        fd = np.stack(
            [
                (proc(s0 + h * c)[0][i] - proc(s0 - h * c)[0][i]) / (2 * h)
                for i in (0, 1)
                for c in [np.where(np.arange(N)[:, None] == i, columns[..., k], 0)]
            ]
        )
        assert np.abs(d[:2, k] - fd).max() < tol * np.abs(fd).max(), k


@pytest.mark.parametrize("shape", [(96, 96), (60, 80), (97, 131)])
@pytest.mark.parametrize("fraction", [1 / 8, 1 / 12])
def test_lowpass_is_kikuchipys_dynamic_background(shape, fraction):
    # The model's low-pass is the background kikuchipy divides by in
    # remove_dynamic_background (frequency domain, its window cut at two
    # sigma, the edges replicated), to float32 rounding, on a lobed
    # pattern, whose slopes at the edges the borders act on
    from kikuchipy.pattern import get_dynamic_background

    y, x = np.indices(shape) + 0.5
    lobe = np.exp(-((x - 50) ** 2 + (y - 70) ** 2) / (2 * 55**2))
    lobe *= 1 + 0.1 * np.sin(x / 3) * np.cos(y / 4)
    sigma = shape[1] * fraction
    expected = get_dynamic_background(lobe.astype(np.float32), std=sigma)
    model = _Processing(shape, highpass=sigma)._lowpass(lobe[None, None])[0, 0]
    assert np.abs(model / expected - 1).max() < 1e-5


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_blur_is_scipys_gaussian_filter(patterns, dtype, monkeypatch):
    planes = patterns[1][:3].reshape((3,) + SHAPE + (4,)).transpose(0, 3, 1, 2).astype(dtype)
    proc = _Processing(SHAPE, psf=0.9)
    expected = ndimage.gaussian_filter(planes, (0, 0, 0.9, 0.9), mode="nearest")
    tol = 1e-6 if dtype == np.float32 else 1e-12
    assert np.abs(proc._blur(planes) - expected).max() < tol
    # Without OpenCV, scipy's
    monkeypatch.setattr(_processing, "_import_cv2", lambda: None)
    assert np.abs(proc._blur(planes) - expected).max() < tol


def test_compared_is_the_pattern_less_its_gaussian_blur(patterns, monkeypatch):
    # Flattened pixels, as the full field holds them: each plane less its
    # blur of COMPARED_HIGHPASS widths, the same with OpenCV or scipy
    flat = patterns[0][:3].reshape(3, -1)
    sigma = _processing.COMPARED_HIGHPASS * SHAPE[1]
    blurred = ndimage.gaussian_filter(
        flat.reshape((3,) + SHAPE), (0, sigma, sigma), mode="nearest"
    )
    expected = flat - blurred.reshape(3, -1)
    assert np.abs(_processing._compared(flat, SHAPE) - expected).max() < 1e-10
    monkeypatch.setattr(_processing, "_import_cv2", lambda: None)
    assert np.abs(_processing._compared(flat, SHAPE) - expected).max() < 1e-10


def test_lobe_left_in_under_the_dynamic_removal():
    # Counts on the camera's lobe, the dynamic background removed by
    # kikuchipy, the static not: the model with the lobe left in
    # (static=False) is the data up to the shot noise; dividing it out
    # first, as after a static background removal, is not
    rng = np.random.default_rng(1)
    shape = (60, 60)
    s0 = ndimage.gaussian_filter(rng.normal(size=(4,) + shape), (0, 1.5, 1.5))
    camera = Camera(dose=1e4, contrast=0.2, blur=0.6, static=False)
    raw = camera_counts(s0, np.tile([0.5, 0.3, 0.6], (4, 1)), camera, seed=2)
    signal = EBSD(raw.reshape((2, 2) + shape).astype(np.float32))
    camera.process(signal)
    data = signal.data.reshape(4, -1).astype(np.float64)
    lobe = _processing._fit_lobe(_processing._static_background(signal))

    def misfit(static):
        proc = _Processing(shape, 0.6, shape[1] / 8, 0.2, static=static, lobe=lobe)
        x = proc(s0.reshape(4, -1))[0]
        x, d = x - x.mean(1, keepdims=True), data - data.mean(1, keepdims=True)
        return 1 - (x * d).sum(1) / np.sqrt((x * x).sum(1) * (d * d).sum(1))

    # Measured: 0.005-0.006 against 0.034-0.040
    assert misfit(static=False).max() < 0.01
    assert misfit(static=False).max() < misfit(static=True).min() / 4


@pytest.mark.parametrize(
    "orientations, static, found",
    [("single", True, True), ("single", False, False), ("random", True, False)],
)
def test_bands_divided_out_only_where_the_static_background_took_them(
    si_mp, orientations, static, found
):
    # One crystal: the map's mean is every pattern's bands, and dividing
    # it out leaves the noise; with only the dynamic background removed,
    # or on points of many orientations, the patterns keep their bands
    from kikuchipy_geomdic.validation import synthetic

    sm = synthetic.synthetic_map(
        si_mp, (5, 5), orientations=orientations, shape=(60, 60), seed=0,
        camera=Camera(dose=30, static=static), start="indexed", orientation_error=1.0,
    )  # fmt: skip
    shape = (60, 60)
    sim = sm.master_pattern.get_patterns(
        sm.start_xmap.rotations.reshape(5, 5), sm.start_detector, sm.energy, compute=True,
        show_progressbar=False,
    )  # fmt: skip
    out = _processing._bands_divided_out(
        _processing._static_background(sm.signal),
        np.asarray(sm.signal.data).reshape((-1,) + shape),
        np.asarray(sim.data).reshape((-1,) + shape),
    )
    assert (out is not None) == found
    if found:
        held, kept = out
        # Measured 0.10 against 0.06
        assert held > 1.5 * kept


def test_full_field_fixed_point_on_one_crystal_as_a_camera_makes_it():
    """A Si single crystal at the paper's Table 1 geometry, 100 um, as a
    camera records it (background lobe, blur, 20,000 counts/px: little
    noise) with kikuchipy's dynamic background removal; the full field
    from the truth stays at it. Where every pattern shares one crystal's
    bands, the model's lobe, fitted to the map's mean, took them for the
    lobe, and the model's dynamic background was not kikuchipy's at the
    edges: pcx ended 5.4e-4 off (measured; 1.6e-5 with both right)."""
    import warnings

    import kikuchipy_geomdic as kg
    from kikuchipy_geomdic.geometry import MapGeometry
    from kikuchipy_geomdic.validation import synthetic

    geometry = MapGeometry(
        pc=(0.52, 0.176, 0.858), shape=(120, 120), px_size=70.0, binning=4.0,
        step_sizes=(100 / 9, 100 / 9), navigation_shape=(10, 10), tilt=10.0, azimuthal=-2.0,
        sample_tilt=70.0,
    )  # fmt: skip
    sm = synthetic.synthetic_map(
        "Si", (10, 10), orientations="single", geometry=geometry, seed=3, start="indexed",
        orientation_error=1.0, camera=Camera(dose=2e4, static=False),
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = kg.refine_geometry_dic(
            sm.signal, sm.xmap, sm.detector, sm.master_pattern, sm.energy,
            parameters=["pcx", "pcy", "pcz"], orientation_model="crystal",
            show_progressbar=False,
        )  # fmt: skip
    assert "full-field" in [h.get("stage") for h in res.history]
    err = np.subtract(res.geometry.pc, sm.geometry.pc)
    assert np.abs(err).max() < 5e-5, err
