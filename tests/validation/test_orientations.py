"""Tests of the orientation perturbations and the common rotation of a start."""

import numpy as np
import pytest
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import rotation_vectors
from kikuchipy_geomdic.validation.orientations import (
    common_rotation,
    perturb_rotations,
)


def test_perturb_rotations_rms():
    r = Rotation.identity(4000)
    p = perturb_rotations(r, 0.3, 0)
    rms = np.sqrt(np.mean(np.rad2deg(p.angle) ** 2))
    assert abs(rms - 0.3) < 0.01


class TestCommonRotation:
    def test_recovers_a_common_rotation(self):
        truth = Rotation.random(20)
        t = Rotation.from_axes_angles([1, 2, -2], np.deg2rad(0.8))
        common = common_rotation(truth * t, truth)
        assert np.isclose(common.angle, 0.8)
        assert np.allclose(common.axis, np.array([1, 2, -2]) / 3)
        assert np.allclose(common.vector, 0.8 * np.array([1, 2, -2]) / 3)
        # The left factor (crystal frame) is not what is measured
        assert not np.isclose(common_rotation(t * truth, truth).angle, 0.8)

    def test_sign_and_zero(self):
        truth = Rotation.random(3)
        start = Rotation(-truth.data)  # q and -q: the same rotation
        assert common_rotation(start, truth).angle < 1e-12
        angle, axis = common_rotation(-Rotation.identity(2), Rotation.identity(2))
        assert angle == 0 and np.array_equal(axis, [0, 0, 1])

    def test_symmetry(self):
        from orix.quaternion.symmetry import Oh

        truth = Rotation.random(10)
        t = Rotation.from_axes_angles([0, 0, 1], np.deg2rad(0.5))
        ops = Oh.proper_subgroup[np.arange(10) % 24]
        start = ops * (truth * t)
        assert common_rotation(start, truth).angle > 1
        assert np.isclose(common_rotation(start, truth, symmetry=Oh).angle, 0.5)

    def test_sizes_must_match(self):
        with pytest.raises(ValueError, match="rotations"):
            common_rotation(Rotation.identity(2), Rotation.identity(3))

    def test_rotation_vectors_tiny_angles(self):
        v = np.array([[1e-12, 0, 0], [0, 2e-9, 0], [0, 0, 0], [0.1, -0.2, 0.3]])
        angle = np.linalg.norm(v, axis=1)
        axis = v / np.where(angle > 0, angle, 1)[:, None]
        # orix's from_axes_angles rounds angles below 1e-8 rad to zero
        r = Rotation(np.c_[np.cos(angle / 2), axis * np.sin(angle / 2)[:, None]])
        assert np.allclose(rotation_vectors(r), v, rtol=1e-9, atol=1e-20)
