"""Tests of the preprocessing before the DIC."""

import numpy as np
from numpy.testing import assert_allclose

from kikuchipy_geomdic.patterns.preprocessing import bin_pattern


def test_bin_pattern_centres_match_coordinate_rule():
    # A ramp equal to the x coordinate, binned, equals the full-resolution
    # coordinate of each binned pixel centre: k b + (b - 1) / 2
    for b in (2, 3, 4):
        ramp = np.tile(np.arange(121.0), (7, 1))
        binned = bin_pattern(ramp, b)
        k = np.arange(121 // b)
        assert binned.shape == (7 // b, 121 // b)
        assert_allclose(binned[0], k * b + (b - 1) / 2)
