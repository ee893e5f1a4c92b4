"""Tests of the detector models."""

import numpy as np

from kikuchipy_geomdic.validation.camera import degrade_patterns


def test_degrade_is_identity_when_off():
    p = np.random.default_rng(0).random((2, 8, 8)).astype(np.float32)
    assert np.array_equal(degrade_patterns(p), p)
