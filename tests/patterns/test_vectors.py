"""Tests of the vectors of one pattern pair: both trackers, binned
coordinates and the backend choice."""

import numpy as np
import pytest
from numpy.testing import assert_array_equal
from scipy import ndimage

from kikuchipy_geomdic.patterns._lucas_kanade import _track_numpy, _track_opencv
from kikuchipy_geomdic.patterns.preprocessing import _to_uint8
from kikuchipy_geomdic.patterns.vectors import pattern_vectors, resolve_backend


def test_lk_status_flags_fail_on_flat_windows():
    # A flat region has no gradient: both trackers must flag it
    rng = np.random.default_rng(0)
    img = ndimage.gaussian_filter(rng.random((60, 60)), 2)
    img[:, :30] = img.mean()
    img = (img - img.mean()) / img.std()
    pts = np.array([[12.0, 30.0], [45.0, 30.0]])
    _, ok = _track_numpy(img, img, pts, 11, 2)
    assert_array_equal(ok, [False, True])
    cv2 = pytest.importorskip("cv2")
    a8, _ = _to_uint8(img, img)
    _, ok = _track_opencv(cv2, a8, a8, pts, 11, 2)
    assert_array_equal(ok, [False, True])


@pytest.mark.parametrize("dic", ["opencv", "skimage"])
def test_binned_coordinates_have_no_offset(dic):
    # A 4 % dilation about the centre: a position error e shows as a mean
    # displacement error of 0.04 e. Forgetting the (b - 1) / 2 offset of
    # binning 3 would give -0.04 px; measured below 0.01
    c, s = 89.5, 1.04
    errors = []
    for seed in range(4):
        a = ndimage.gaussian_filter(np.random.default_rng(seed).random((180, 180)), 3)
        b = ndimage.affine_transform(a, [1 / s, 1 / s], offset=c - c / s, order=3, mode="nearest")
        xy_a, xy_b = pattern_vectors(a, b, rois=(6, 6), binning=3, dic=dic)
        errors.append(xy_b - xy_a - (s - 1) * (xy_a - c))
    errors = np.concatenate(errors)
    assert len(errors) > 250
    assert np.abs(errors.mean(axis=0)).max() < 0.015


def test_auto_prefers_opencv():
    pytest.importorskip("cv2")
    assert resolve_backend("auto") == "opencv"
    with pytest.raises(ValueError, match="dic must be"):
        resolve_backend("cv2")
