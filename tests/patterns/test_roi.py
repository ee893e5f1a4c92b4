"""Tests of the ROI grid, the per-ROI averaging and weights (Eqs. 1 and 8)
and the per-ROI vector filters."""

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from kikuchipy_geomdic.patterns import roi

SHAPE = (120, 120)


@pytest.mark.parametrize("shape, rois", [((120, 120), (8, 8)), ((10, 13), (3, 4))])
def test_roi_grid_partitions_pixels(shape, rois):
    row_edges, col_edges = roi.roi_edges(shape, rois)
    assert (row_edges[0], row_edges[-1], col_edges[0], col_edges[-1]) == (0, shape[0], 0, shape[1])
    # ROI sizes differ by at most one pixel
    assert np.ptp(np.diff(row_edges)) <= 1 and np.ptp(np.diff(col_edges)) <= 1
    # Every pixel centre is in exactly the ROI whose edges hold it
    j, i = np.indices(shape)
    idx = roi.roi_index(i, j, shape, rois)
    expected = np.zeros(shape, int)
    for r in range(rois[0]):
        for c in range(rois[1]):
            expected[row_edges[r] : row_edges[r + 1], col_edges[c] : col_edges[c + 1]] = (
                r * rois[1] + c
            )
    assert_array_equal(idx, expected)
    assert_array_equal(
        np.bincount(idx.ravel()), np.outer(np.diff(row_edges), np.diff(col_edges)).ravel()
    )
    # Centres are the mean pixel coordinate of each ROI
    centres = roi.roi_centres(shape, rois)
    for r in range(rois[0] * rois[1]):
        assert_allclose(centres[r], [i[idx == r].mean(), j[idx == r].mean()])


def test_roi_index_edges_and_outside():
    # Pixel centres are integers: the edge between columns 14 and 15 is
    # at x = 14.5; outside the pattern and NaN give -1
    x = np.array([14.49, 14.5, -0.5, -0.51, 119.49, 119.5, np.nan])
    y = np.zeros_like(x)
    assert_array_equal(roi.roi_index(x, y, SHAPE, (8, 8)), [0, 1, 0, -1, 7, -1, -1])
    assert_array_equal(roi.roi_index([0, 0], [15.0, 119.0], SHAPE, (8, 8)), [8, 56])


def test_roi_average_counts_crossing_vector_in_both_rois():
    # 2 x 2 ROIs of 10 px; three vectors in ROI 0, one crossing to ROI 1,
    # one leaving the pattern (counts only where it starts)
    a = np.array([[2.0, 2.0], [4.0, 3.0], [6.0, 8.0], [8.0, 2.0], [1.0, 15.0]])
    b = np.array([[3.0, 2.0], [5.0, 4.0], [7.0, 8.0], [11.0, 3.0], [1.0, 25.0]])
    u, counts, positions = roi.roi_average(a, b, (20, 20), (2, 2))
    assert_array_equal(counts, [4, 1, 1, 0])
    assert_allclose(u[0], [(1 + 1 + 1 + 3) / 4, (0 + 1 + 0 + 1) / 4])
    assert_allclose(u[1], [3, 1])
    assert_allclose(u[2], [0, 10])
    assert_allclose(u[3], [0, 0])
    assert_allclose(positions[0], a[:4].mean(axis=0))
    assert_allclose(positions[1], a[3])
    assert_allclose(positions[3], roi.roi_centres((20, 20), (2, 2))[3])
    # Other values averaged with the same membership
    u2, c2, _ = roi.roi_average(a, b, (20, 20), (2, 2), values=np.ones((5, 2)))
    assert_array_equal(c2, counts)
    assert_allclose(u2[:3], 1.0)


def test_roi_weights_eq8_by_hand():
    # Non-zero counts sorted: 2, 8, then 10 x 8, then 20 (11 values):
    # NumPy's 90th percentile sits at index 9, so c90 = 10
    counts = np.array([0, 2, 8, 10, 10, 10, 10, 10, 10, 10, 10, 20])
    w = roi.roi_weights(counts)
    assert_allclose(w, [0, np.sqrt(0.2), np.sqrt(0.8)] + [1.0] * 9)
    assert_array_equal(roi.roi_weights(np.zeros(4)), np.zeros(4))
    # One non-zero count: c90 is that count
    assert_allclose(roi.roi_weights([0, 3, 0]), [0, 1, 0])
    with pytest.raises(ValueError, match="non-negative"):
        roi.roi_weights([1, -1])


def test_filter_vectors_rules():
    a = np.array([[5.0, 5], [6, 5], [5, 6], [6, 6], [5, 7], [50, 50]])
    v = np.array([[1, 0], [1, 0], [1.05, 0], [1, 0.05], [3, 0], [30, 0]])
    b = a + v
    # 10 px ROIs: vector 5 spans 3 ROIs, vector 4 is a 2 px outlier
    assert_array_equal(roi.filter_vectors(a, b, (100, 100), (10, 10)), [1, 1, 1, 1, 0, 0])
    assert_array_equal(
        roi.filter_vectors(a, b, (100, 100), (10, 10), max_roi_crossings=3, robust=None),
        [1, 1, 1, 1, 1, 1],
    )
    assert_array_equal(
        roi.filter_vectors(a, b, (100, 100), (10, 10), robust=None), [1, 1, 1, 1, 1, 0]
    )
    # An end outside the pattern is always dropped
    assert_array_equal(
        roi.filter_vectors([[95.0, 5]], [[101.0, 5]], (100, 100), (10, 10), None, None), [0]
    )
