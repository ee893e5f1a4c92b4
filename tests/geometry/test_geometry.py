"""Tests of :mod:`kikuchipy_geomdic.geometry`.

Every test compares the module against a truth that does not come from the
module itself: kikuchipy's ``EBSDDetector.extrapolate_pc``, kikuchipy's
direction cosines of detector pixels (the directions its simulation
projects), patterns simulated by kikuchipy, and features tracked between
such patterns with OpenCV's pyramidal Lucas-Kanade.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals.util._master_pattern import (
    _get_direction_cosines_from_detector,
)
from numpy.testing import assert_allclose
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import (
    DEFAULT_PARAMETERS,
    EQUIVALENT_PARAMETERS,
    PARAMETERS,
    MapGeometry,
    check_parameters,
    forward_map,
    pc_field,
    sample_to_detector_matrix,
)
from kikuchipy_geomdic.patterns import simulation
from kikuchipy_geomdic.validation import master_patterns

ANGLE_NAMES = ("tilt", "azimuthal", "sample_tilt", "twist")


# --------------------------------------------------------------------- #
# Independent helpers
# --------------------------------------------------------------------- #


def kp_matrix(tilt, azimuthal, sample_tilt, twist=0.0):
    """kikuchipy's sample-to-detector matrix (M @ v_sample = v_detector)."""
    det = EBSDDetector(tilt=tilt, azimuthal=azimuthal, sample_tilt=sample_tilt, twist=twist)
    return det.sample_to_detector.to_matrix().reshape(3, 3)


def kp_directions(shape, pc, tilt, azimuthal, sample_tilt, twist=0.0):
    """kikuchipy's unit sample-frame directions of all pixels, (rows, cols, 3)."""
    det = EBSDDetector(
        shape,
        pc=pc,
        tilt=tilt,
        azimuthal=azimuthal,
        sample_tilt=sample_tilt,
        twist=twist,
    )
    return _get_direction_cosines_from_detector(det).reshape(tuple(shape) + (3,))


def own_directions(x, y, shape, pc, angles):
    """Unit sample-frame direction of pixel coordinates (x, y) (centre of
    pixel (j, i) at (i, j)), written from the detector model: the screen
    is the plane Z_d = 0 with pixel (j, i) centred at (i + 1/2, -(j + 1/2))
    and the source at (pcx Nx, -pcy Ny, -pcz Ny), in binned pixels."""
    nrows, ncols = shape
    screen = np.stack(np.broadcast_arrays(x + 0.5, -(np.asarray(y) + 0.5), 0.0), axis=-1)
    source = np.array([pc[0] * ncols, -pc[1] * nrows, -pc[2] * nrows])
    v = (screen - source) @ kp_matrix(*angles)  # Detector -> sample: M.T v
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def beam_shift(drow, dcol, dy, dx, sign_rows=-1.0, sign_cols=-1.0, swap=False):
    """Beam displacement in the sample frame for a map step (drow, dcol).

    kikuchipy's convention (verified in ``test_sample_frame_convention``):
    X_s along decreasing map rows, Y_s along decreasing map columns.
    """
    a = sign_rows * np.asarray(drow, float) * dy
    b = sign_cols * np.asarray(dcol, float) * dx
    if swap:
        a, b = b, a
    return np.stack([a, b, np.zeros_like(a)], axis=-1)


def moved_source_pc(pc0, s_sample, angles, shape, px_size, binning):
    """PC after moving the source by *s_sample* (micrometres) in front of a
    FIXED screen: foot of the perpendicular and distance to the plane."""
    nrows, ncols = shape
    m = kp_matrix(*angles)
    source = np.array([pc0[0] * ncols, -pc0[1] * nrows, -pc0[2] * nrows])
    # Source in the sample frame (origin: the screen's upper-left corner)
    src_s = source @ m + np.asarray(s_sample) / (px_size * binning)
    x_d = src_s @ m[0]  # Components along detector axes X_d, Y_d, Z_d
    y_d = src_s @ m[1]
    z_d = src_s @ m[2]  # Screen plane is Z_d = 0, source at Z_d < 0
    return np.stack([x_d / ncols, -y_d / nrows, -z_d / nrows], axis=-1)


def directions_from_moved_source(pc0, s_sample, angles, shape, px_size, binning):
    """Unit sample-frame directions from a moved source to the pixels of
    the fixed screen, (rows, cols, 3)."""
    nrows, ncols = shape
    m = kp_matrix(*angles)
    j, i = np.indices(shape, dtype=float)
    screen_d = np.stack([i + 0.5, -(j + 0.5), np.zeros_like(i)], axis=-1)
    source_d = np.array([pc0[0] * ncols, -pc0[1] * nrows, -pc0[2] * nrows])
    screen_s = screen_d @ m
    source_s = source_d @ m + np.asarray(s_sample) / (px_size * binning)
    v = screen_s - source_s
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def extrapolated(shape, px_size, binning, tilt, sample_tilt, pc, ref, nav, steps):
    """kikuchipy's PC map; pc_indices flat [row, col] (the documented (2, n)
    form averages over the wrong axis for a single PC)."""
    det = EBSDDetector(
        shape,
        px_size=px_size,
        binning=binning,
        tilt=tilt,
        sample_tilt=sample_tilt,
        pc=pc,
    )
    new = det.extrapolate_pc(pc_indices=[ref[0], ref[1]], navigation_shape=nav, step_sizes=steps)
    return new.pc


# --------------------------------------------------------------------- #
# 1. PC field vs kikuchipy's extrapolate_pc (azimuthal = twist = 0)
# --------------------------------------------------------------------- #

# shape, px_size, binning, tilt, sample_tilt, pc, reference, nav, steps
EXTRAPOLATE_CASES = [
    ((60, 80), 50.0, 2, 0.0, 70.0, (0.48, 0.27, 0.63), (1, 5), (5, 7), (3.0, 4.0)),
    ((120, 96), 70.0, 4, 10.0, 70.0, (0.52, 0.35, 0.55), (4, 0), (6, 4), (20.0, 10.0)),
    ((40, 40), 40.0, 1, -5.0, 60.0, (0.5, 0.2, 0.7), (2, 2), (3, 3), (50.0, 50.0)),
    ((90, 60), 60.0, 8, 4.0, 75.0, (0.45, 0.3, 0.6), (0, 3), (4, 5), (7.5, 12.5)),
    ((50, 70), 35.0, 3, 0.0, 70.0, (0.55, 0.25, 0.65), (-2, 9), (3, 6), (15.0, 5.0)),
]


@pytest.mark.parametrize("case", EXTRAPOLATE_CASES)
def test_pc_field_equals_extrapolate_pc(case):
    shape, px, b, tilt, st, pc, ref, nav, steps = case
    truth = extrapolated(shape, px, b, tilt, st, pc, ref, nav, steps)
    rows, cols = np.indices(nav)
    pcs = pc_field(
        pc,
        rows,
        cols,
        reference=ref,
        step_sizes=steps,
        shape=shape,
        px_size=px,
        binning=b,
        tilt=tilt,
        azimuthal=0.0,
        sample_tilt=st,
    )
    assert pcs.shape == nav + (3,)
    assert_allclose(pcs, truth, rtol=0, atol=1e-9)
    # The field actually varies (else the comparison would be empty)
    assert np.ptp(truth.reshape(-1, 3), axis=0).max() > 1e-4

    geo = MapGeometry(
        pc=pc,
        shape=shape,
        px_size=px,
        binning=b,
        step_sizes=steps,
        navigation_shape=nav,
        tilt=tilt,
        sample_tilt=st,
        reference=ref,
    )
    assert_allclose(geo.detector().pc, truth, rtol=0, atol=1e-9)
    assert_allclose(
        geo.pc_at(np.c_[rows.ravel(), cols.ravel()]), truth.reshape(-1, 3), rtol=0, atol=1e-9
    )


def test_sample_frame_convention():
    """X_s along decreasing map rows and Y_s along decreasing map columns:
    the moved-source construction reproduces extrapolate_pc with this
    convention and not with the other ones."""
    shape, px, b, tilt, st = (60, 80), 50.0, 2, 6.0, 70.0
    pc, ref, nav, steps = (0.48, 0.27, 0.63), (2, 3), (5, 7), (9.0, 6.0)
    truth = extrapolated(shape, px, b, tilt, st, pc, ref, nav, steps)
    rows, cols = np.indices(nav)

    def field(**kw):
        s = beam_shift(rows - ref[0], cols - ref[1], *steps, **kw)
        return moved_source_pc(pc, s, (tilt, 0.0, st, 0.0), shape, px, b)

    assert_allclose(field(), truth, rtol=0, atol=1e-9)
    for wrong in ({"sign_rows": 1.0}, {"sign_cols": 1.0}, {"swap": True}):
        assert np.abs(field(**wrong) - truth).max() > 1e-3


# --------------------------------------------------------------------- #
# 2. PC field with azimuthal and twist: moved source, fixed screen
# --------------------------------------------------------------------- #

# shape, px_size, binning, (tilt, azimuthal, sample_tilt, twist)
FIELD_CASES = [
    ((60, 80), 50.0, 2, (0.0, 3.0, 70.0, 0.0)),
    ((60, 80), 50.0, 2, (0.0, 0.0, 70.0, 2.5)),
    ((96, 64), 70.0, 4, (8.0, -4.0, 68.0, 1.5)),
    ((50, 50), 30.0, 1, (-3.0, 12.0, 72.0, -6.0)),
]


@pytest.mark.parametrize("case", FIELD_CASES)
def test_pc_field_moved_source_fixed_screen(case):
    shape, px, b, angles = case
    pc, ref, steps = (0.47, 0.29, 0.61), (1.0, 2.0), (25.0, 40.0)
    points = np.array([[1, 2], [0, 0], [3, 5], [-2, 7], [4.5, -1.25]])
    pcs = pc_field(pc, points[:, 0], points[:, 1], ref, steps, shape, px, b, *angles)
    s = beam_shift(points[:, 0] - ref[0], points[:, 1] - ref[1], *steps)
    truth = moved_source_pc(pc, s, angles, shape, px, b)
    assert_allclose(pcs, truth, rtol=0, atol=1e-9)
    assert np.abs(pcs - pc).max() > 1e-2  # The beam moves the PC measurably

    # kikuchipy's own projection with the PC-field PC sees every pixel of the
    # screen in the direction from the moved source to that (fixed) pixel
    for k, p in enumerate(pcs):
        dc = kp_directions(shape, p, *angles)
        want = directions_from_moved_source(pc, s[k], angles, shape, px, b)
        assert_allclose(dc, want, rtol=0, atol=1e-9)
        # ... and not with the reference PC, unless the beam did not move
        if np.abs(s[k]).max() > 0:
            assert np.abs(kp_directions(shape, pc, *angles) - want).max() > 1e-4


def test_pc_field_azimuthal_and_twist_matter():
    """With azimuthal = twist = 0 the field is extrapolate_pc's; with either
    non-zero it differs (so test 2 is not the azimuthal = 0 case again)."""
    args = dict(
        reference=(0, 0),
        step_sizes=(30, 30),
        shape=(60, 60),
        px_size=60,
        binning=2,
        tilt=0,
        sample_tilt=70,
    )
    base = pc_field((0.5, 0.3, 0.6), [3, 0], [0, 3], azimuthal=0, **args)
    for kw in ({"azimuthal": 3.0}, {"azimuthal": 0.0, "twist": 3.0}):
        other = pc_field((0.5, 0.3, 0.6), [3, 0], [0, 3], **kw, **args)
        assert np.abs(other - base).max() > 1e-4


def test_sample_to_detector_matrix_is_kikuchipys():
    for angles in [(0, 0, 70, 0), (5, 2, 68, -1), (-3, 10, 60, 4)]:
        m = sample_to_detector_matrix(*angles)
        assert m.shape == (3, 3)
        assert_allclose(m, kp_matrix(*angles), rtol=0, atol=1e-15)
        assert_allclose(m @ m.T, np.eye(3), atol=1e-12)


# --------------------------------------------------------------------- #
# Fixtures for simulation
# --------------------------------------------------------------------- #


@pytest.fixture(scope="module")
def mp():
    return master_patterns.master_pattern("Si", kind="dynamical")


@pytest.fixture(scope="module")
def rotations():
    return Rotation.from_euler(np.deg2rad([[10, 20, 30], [100, 40, 250], [200, 60, 120]]))


def simulate(mp, rotations, shape, pc, angles):
    tilt, azimuthal, sample_tilt, twist = angles
    det = EBSDDetector(
        shape,
        pc=pc,
        tilt=tilt,
        azimuthal=azimuthal,
        sample_tilt=sample_tilt,
        twist=twist,
    )
    return simulation.simulate_patterns(mp, rotations, det, energy=20)


# --------------------------------------------------------------------- #
# 3. The tilt degeneracy
# --------------------------------------------------------------------- #


def test_tilt_degeneracy_patterns(mp, rotations):
    shape, pc = (60, 80), (0.5, 0.3, 0.6)
    a = simulate(mp, rotations, shape, pc, (5.0, 1.5, 70.0, 0.8))
    b = simulate(mp, rotations, shape, pc, (0.0, 1.5, 65.0, 0.8))
    c = simulate(mp, rotations, shape, pc, (0.0, 1.5, 70.0, 0.8))
    scale = np.abs(a).max()
    assert_allclose(a, b, rtol=0, atol=1e-6 * scale)
    # Negative control: a real change of tilt - sample_tilt changes them
    assert np.abs(a - c).max() > 0.05 * scale


def test_tilt_degeneracy_geometry():
    assert EQUIVALENT_PARAMETERS == {"sample_tilt": ("tilt", -1.0)}
    assert_allclose(
        sample_to_detector_matrix(5, 2, 70, 1),
        sample_to_detector_matrix(0, 2, 65, 1),
        rtol=0,
        atol=1e-15,
    )
    rows, cols = np.indices((4, 5))
    args = dict(
        reference=(1, 1),
        step_sizes=(40, 30),
        shape=(60, 80),
        px_size=50,
        binning=2,
        azimuthal=2.0,
        twist=1.0,
    )
    f1 = pc_field((0.5, 0.3, 0.6), rows, cols, tilt=5, sample_tilt=70, **args)
    f2 = pc_field((0.5, 0.3, 0.6), rows, cols, tilt=0, sample_tilt=65, **args)
    f3 = pc_field((0.5, 0.3, 0.6), rows, cols, tilt=0, sample_tilt=70, **args)
    assert_allclose(f1, f2, rtol=0, atol=1e-12)
    assert np.abs(f1 - f3).max() > 1e-3

    # A change of sample_tilt by d does what a change of tilt by -d does
    name, (other, factor) = next(iter(EQUIVALENT_PARAMETERS.items()))
    geo = MapGeometry(
        pc=(0.5, 0.3, 0.6),
        shape=(60, 80),
        px_size=50,
        binning=2,
        step_sizes=(40, 30),
        navigation_shape=(4, 5),
        tilt=3,
        azimuthal=2,
        sample_tilt=70,
        twist=1,
    )
    d = 0.7
    g1, g2 = geo.updated({name: d}), geo.updated({other: factor * d})
    pts = np.c_[rows.ravel(), cols.ravel()]
    assert_allclose(g1.pc_at(pts), g2.pc_at(pts), rtol=0, atol=1e-12)
    x, y = np.meshgrid(np.arange(0, 80, 7.0), np.arange(0, 60, 7.0))
    assert_allclose(
        geo.displacement(g1, pts, x.ravel(), y.ravel()),
        geo.displacement(g2, pts, x.ravel(), y.ravel()),
        rtol=0,
        atol=1e-9,
    )


# --------------------------------------------------------------------- #
# 4a. forward_map: exact checks
# --------------------------------------------------------------------- #

GENERIC_A = ((0.47, 0.31, 0.62), (3.0, 2.0, 69.0, 1.0))
SHAPE_NS = (48, 64)  # Non-square


def test_forward_map_preserves_kikuchipy_directions():
    """The point forward_map returns is seen, under geometry B, in the same
    sample direction as the start point under A. Directions at pixel
    centres are kikuchipy's; between centres from the detector model,
    which is first checked to equal kikuchipy's at every pixel centre."""
    shape = SHAPE_NS
    pc_a, ang_a = GENERIC_A
    pc_b, ang_b = (0.5, 0.27, 0.66), (1.0, -3.0, 71.0, 2.0)
    j, i = np.indices(shape, dtype=float)
    for pc, ang in ((pc_a, ang_a), (pc_b, ang_b)):
        assert_allclose(
            own_directions(i, j, shape, pc, ang),
            kp_directions(shape, pc, *ang),
            rtol=0,
            atol=1e-12,
        )
    # Pixel centres of A, and arbitrary fractional points
    rng = np.random.default_rng(0)
    x = np.concatenate([i.ravel(), rng.uniform(-5, 70, 200)])
    y = np.concatenate([j.ravel(), rng.uniform(-5, 50, 200)])
    xb, yb = forward_map(x, y, pc_a, ang_a, pc_b, ang_b, shape)
    assert np.all(np.isfinite(xb)) and np.all(np.isfinite(yb))
    assert_allclose(
        own_directions(xb, yb, shape, pc_b, ang_b),
        own_directions(x, y, shape, pc_a, ang_a),
        rtol=0,
        atol=1e-9,
    )
    # The round trip B -> A returns the start point
    xa, ya = forward_map(xb, yb, pc_b, ang_b, pc_a, ang_a, shape)
    assert_allclose(xa, x, atol=1e-9)
    assert_allclose(ya, y, atol=1e-9)


def test_forward_map_identity():
    pc, ang = GENERIC_A
    x, y = np.meshgrid(np.arange(64.0), np.arange(48.0))
    xb, yb = forward_map(x, y, pc, ang, pc, ang, SHAPE_NS)
    assert_allclose(xb, x, atol=1e-10)
    assert_allclose(yb, y, atol=1e-10)


@pytest.mark.parametrize("axis", [0, 1])
def test_forward_map_pc_shift_exact(axis):
    """+1 px of pcx * width moves every pixel by +1 px in x; +1 px of
    pcy * height moves every pixel by +1 px in y (down the image)."""
    shape = SHAPE_NS
    nrows, ncols = shape
    pc_a, ang = GENERIC_A
    pc_b = np.array(pc_a)
    pc_b[axis] += 1 / (ncols if axis == 0 else nrows)
    x, y = np.meshgrid(np.arange(-3.0, 67.0, 2.5), np.arange(-3.0, 51.0, 2.5))
    xb, yb = forward_map(x, y, pc_a, ang, pc_b, ang, shape)
    assert_allclose(xb - x, 1.0 if axis == 0 else 0.0, rtol=0, atol=1e-9)
    assert_allclose(yb - y, 1.0 if axis == 1 else 0.0, rtol=0, atol=1e-9)


@pytest.mark.parametrize("axis", [0, 1])
def test_pc_shift_moves_simulated_pattern(mp, rotations, axis):
    """The sign in the test above is kikuchipy's: the simulated pattern
    moves by exactly one pixel, right for pcx, down for pcy."""
    shape = SHAPE_NS
    nrows, ncols = shape
    pc_a, ang = GENERIC_A
    pc_b = np.array(pc_a)
    pc_b[axis] += 1 / (ncols if axis == 0 else nrows)
    a = simulate(mp, rotations[:1], shape, pc_a, ang)[0]
    b = simulate(mp, rotations[:1], shape, pc_b, ang)[0]
    scale = np.abs(a).max()
    if axis == 0:
        assert_allclose(b[:, 1:], a[:, :-1], rtol=0, atol=1e-4 * scale)
        assert np.abs(b[:, :-1] - a[:, 1:]).max() > 0.02 * scale
    else:
        assert_allclose(b[1:], a[:-1], rtol=0, atol=1e-4 * scale)
        assert np.abs(b[:-1] - a[1:]).max() > 0.02 * scale


def test_forward_map_pcz_dilation_exact():
    """A pcz change scales about the PC, (pcx Nx - 1/2, pcy Ny - 1/2)."""
    shape = SHAPE_NS
    nrows, ncols = shape
    pc_a, ang = GENERIC_A
    pc_b = (pc_a[0], pc_a[1], pc_a[2] * 1.07)
    xc, yc = pc_a[0] * ncols - 0.5, pc_a[1] * nrows - 0.5
    x, y = np.meshgrid(np.arange(-3.0, 67.0, 2.5), np.arange(-3.0, 51.0, 2.5))
    xb, yb = forward_map(x, y, pc_a, ang, pc_b, ang, shape)
    assert_allclose(xb - xc, 1.07 * (x - xc), rtol=0, atol=1e-9)
    assert_allclose(yb - yc, 1.07 * (y - yc), rtol=0, atol=1e-9)


def test_forward_map_pcz_doubling_on_kikuchipy_pixels():
    """With the PC on a pixel centre and pcz doubled, pixel centres map to
    pixel centres; kikuchipy sees both in the same direction (this fixes
    the half-pixel convention, which tracking cannot resolve)."""
    shape = SHAPE_NS
    nrows, ncols = shape
    i0, j0 = 30, 20
    pc_a = ((i0 + 0.5) / ncols, (j0 + 0.5) / nrows, 0.55)
    pc_b = (pc_a[0], pc_a[1], 2 * pc_a[2])
    ang = GENERIC_A[1]
    j, i = np.mgrid[j0 - 9 : j0 + 10, i0 - 14 : i0 + 15]
    xb, yb = forward_map(i, j, pc_a, ang, pc_b, ang, shape)
    assert_allclose(xb, 2 * i - i0, atol=1e-9)
    assert_allclose(yb, 2 * j - j0, atol=1e-9)
    dc_a = kp_directions(shape, pc_a, *ang)
    dc_b = kp_directions(shape, pc_b, *ang)
    ib, jb = np.round(xb).astype(int), np.round(yb).astype(int)
    assert_allclose(dc_b[jb, ib], dc_a[j, i], rtol=0, atol=1e-9)


@pytest.mark.parametrize("twist", [90.0, -90.0])
def test_forward_map_twist_quarter_turn_on_kikuchipy_pixels(twist):
    """A quarter turn of twist rotates pixel centres about a PC on a pixel
    centre onto pixel centres seen by kikuchipy in the same direction."""
    shape = SHAPE_NS
    nrows, ncols = shape
    i0, j0 = 31, 22
    pc = ((i0 + 0.5) / ncols, (j0 + 0.5) / nrows, 0.6)
    ang_a = GENERIC_A[1]
    ang_b = ang_a[:3] + (ang_a[3] + twist,)
    j, i = np.mgrid[j0 - 15 : j0 + 16, i0 - 15 : i0 + 16]
    xb, yb = forward_map(i, j, pc, ang_a, pc, ang_b, shape)
    assert_allclose(xb, np.round(xb), atol=1e-9)
    assert_allclose(yb, np.round(yb), atol=1e-9)
    assert_allclose(np.hypot(xb - i0, yb - j0), np.hypot(i - i0, j - j0), atol=1e-9)
    ib, jb = np.round(xb).astype(int), np.round(yb).astype(int)
    assert np.abs(ib - i).max() > 10  # Really turned
    dc_a = kp_directions(shape, pc, *ang_a)
    dc_b = kp_directions(shape, pc, *ang_b)
    assert_allclose(dc_b[jb, ib], dc_a[j, i], rtol=0, atol=1e-9)


def test_forward_map_behind_source_is_nan():
    pc, ang = (0.5, 0.5, 0.5), (0.0, 0.0, 70.0, 0.0)
    # Corner pixel is ~55 deg off the screen normal: a 100 deg detector
    # tilt puts its direction behind the screen plane of B
    xb, yb = forward_map([0.0, 30.0], [0.0, 30.0], pc, ang, pc, (100.0, 0.0, 70.0, 0.0), (60, 60))
    assert np.isnan(xb[0]) and np.isnan(yb[0])
    xb2, yb2 = forward_map(0.0, 0.0, pc, ang, pc, (10.0, 0.0, 70.0, 0.0), (60, 60))
    assert np.isfinite(xb2) and np.isfinite(yb2)


def test_forward_map_broadcasts_pc_arrays():
    pc_a, ang = GENERIC_A
    pcs_a = np.array([pc_a, (0.5, 0.3, 0.6)])[:, None, :]
    pcs_b = pcs_a + np.array([0.01, -0.02, 0.03])
    x, y = np.array([[3.0, 10.0, 40.0]]), np.array([[5.0, 30.0, 20.0]])
    xb, yb = forward_map(x, y, pcs_a, ang, pcs_b, ang, SHAPE_NS)
    assert xb.shape == yb.shape == (2, 3)
    for k in range(2):
        xk, yk = forward_map(x[0], y[0], pcs_a[k, 0], ang, pcs_b[k, 0], ang, SHAPE_NS)
        assert_allclose(xb[k], xk, rtol=0, atol=1e-12)
        assert_allclose(yb[k], yk, rtol=0, atol=1e-12)


# --------------------------------------------------------------------- #
# 4b. forward_map vs feature tracking on simulated patterns
# --------------------------------------------------------------------- #

TRACK_SHAPE = (120, 120)
TRACK_PC = (0.52, 0.31, 0.62)
TRACK_ANGLES = {"tilt": 2.0, "azimuthal": 1.0, "sample_tilt": 70.0, "twist": 0.5}
TRACK_STEPS = {
    "pcx": 0.005,
    "pcy": 0.005,
    "pcz": 0.005,
    "tilt": 0.5,
    "azimuthal": 0.5,
    "twist": 0.5,
    "sample_tilt": 0.5,
}
LK = dict(
    winSize=(21, 21),
    maxLevel=1,
    criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5),
)


def _angles(d):
    return tuple(d[a] for a in ANGLE_NAMES)


def track(a, b):
    """Track corner features from pattern a to b; return (p0, p1) (n, 2)
    with forward-backward error < 0.03 px, away from the borders."""
    lo, hi = min(a.min(), b.min()), max(a.max(), b.max())
    ia, ib = (np.round((p - lo) / (hi - lo) * 255).astype(np.uint8) for p in (a, b))
    p0 = cv2.goodFeaturesToTrack(ia, maxCorners=300, qualityLevel=0.01, minDistance=4, blockSize=7)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(ia, ib, p0, None, **LK)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(ib, ia, p1, None, **LK)
    p0, p1, p0b = (p.reshape(-1, 2).astype(np.float64) for p in (p0, p1, p0b))
    ok = (st1.ravel() == 1) & (st2.ravel() == 1)
    ok &= np.linalg.norm(p0b - p0, axis=1) < 0.03
    margin, last = LK["winSize"][0] // 2 + 1, TRACK_SHAPE[0] - 1
    for p in (p0, p1):
        ok &= np.all((p > margin) & (p < last - margin), axis=1)
    return p0[ok], p1[ok]


@pytest.fixture(scope="module")
def track_a(mp, rotations):
    return simulate(mp, rotations, TRACK_SHAPE, TRACK_PC, _angles(TRACK_ANGLES))


@pytest.mark.parametrize("name", list(TRACK_STEPS))
def test_forward_map_matches_tracking(mp, rotations, track_a, name):
    pc_b = np.array(TRACK_PC)
    ang_b = dict(TRACK_ANGLES)
    if name.startswith("pc"):
        pc_b["xyz".index(name[-1])] += TRACK_STEPS[name]
    else:
        ang_b[name] += TRACK_STEPS[name]
    b = simulate(mp, rotations, TRACK_SHAPE, pc_b, _angles(ang_b))
    diff, moved, wrong = [], [], []
    for pa, pb in zip(track_a, b):
        p0, p1 = track(pa, pb)
        xb, yb = forward_map(
            p0[:, 0], p0[:, 1], TRACK_PC, _angles(TRACK_ANGLES), pc_b, _angles(ang_b), TRACK_SHAPE
        )
        pred = np.c_[xb, yb]
        diff.append(pred - p1)
        moved.append(p1 - p0)
        wrong.append((2 * p0 - pred) - p1)  # Prediction with the sign flipped
    diff, moved, wrong = map(np.concatenate, (diff, moved, wrong))

    def rms(d):
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))

    assert len(diff) >= 300
    # The test is meaningful: features move by much more than the tolerance,
    # and a prediction with the wrong sign is far off
    assert rms(moved) > 0.25
    assert rms(wrong) > 0.4
    assert rms(diff) <= 0.05, f"{name}: RMS {rms(diff):.4f} px"


# --------------------------------------------------------------------- #
# 5. MapGeometry.updated and check_parameters
# --------------------------------------------------------------------- #


@pytest.fixture
def map_geometry():
    return MapGeometry(
        pc=(0.5, 0.3, 0.6),
        shape=(60, 80),
        px_size=55.0,
        binning=2,
        step_sizes=(10, 10),
        navigation_shape=(3, 4),
        tilt=3.0,
        azimuthal=1.5,
        sample_tilt=69.0,
        twist=0.7,
    )


def test_updated(map_geometry):
    geo = map_geometry
    delta = {"pcx": 0.01, "pcz": -0.02, "tilt": 1.0, "twist": -0.2}
    new = geo.updated(delta)
    assert new is not geo
    for name in ("shape", "px_size", "binning", "step_sizes", "navigation_shape", "reference"):
        assert getattr(new, name) == getattr(geo, name), name
    assert_allclose(new.pc, np.array(geo.pc) + [0.01, 0.0, -0.02], rtol=0, atol=1e-15)
    assert new.tilt == pytest.approx(4.0)
    assert new.twist == pytest.approx(0.5)
    assert new.azimuthal == 1.5 and new.sample_tilt == 69.0
    # Input not modified
    assert geo.pc == (0.5, 0.3, 0.6) and geo.angles == (3.0, 1.5, 69.0, 0.7)
    # Every parameter
    for name in PARAMETERS:
        one = geo.updated({name: 0.25})
        if name.startswith("pc"):
            k = "xyz".index(name[-1])
            assert one.pc[k] == pytest.approx(geo.pc[k] + 0.25, abs=1e-15)
            assert np.delete(one.pc, k).tolist() == np.delete(geo.pc, k).tolist()
        else:
            for a in ANGLE_NAMES:
                want = getattr(geo, a) + (0.25 if a == name else 0.0)
                assert getattr(one, a) == pytest.approx(want, abs=1e-12)


def test_updated_detector_keeps_twist(map_geometry):
    new = map_geometry.updated({"pcz": 0.01, "tilt": 1})
    det = new.detector()
    assert det.tilt == 4.0 and det.twist == 0.7
    assert det.navigation_shape == (3, 4)
    assert new.pc_at([new.reference])[0, 2] == pytest.approx(0.61)


def test_updated_empty_delta_is_equal(map_geometry):
    new = map_geometry.updated({})
    assert new == map_geometry


def test_updated_unknown_parameter(map_geometry):
    with pytest.raises(ValueError, match="Unknown geometry parameter"):
        map_geometry.updated({"pcx": 0.1, "roll": 1.0})


def test_check_parameters():
    assert check_parameters(["tilt", "pcx"]) == ("pcx", "tilt")
    assert check_parameters("pcz") == ("pcz",)
    assert check_parameters(list(reversed(PARAMETERS))) == PARAMETERS
    assert check_parameters(("twist", "sample_tilt", "azimuthal")) == (
        "azimuthal",
        "sample_tilt",
        "twist",
    )
    assert DEFAULT_PARAMETERS == (
        "pcx",
        "pcy",
        "pcz",
        "tilt",
        "azimuthal",
        "sample_tilt",
    )
    with pytest.raises(ValueError, match="Unknown geometry parameter"):
        check_parameters(["pcx", "PCx"])
    with pytest.raises(ValueError, match="repeated"):
        check_parameters(["tilt", "tilt"])
    with pytest.raises(ValueError, match="At least one"):
        check_parameters([])


# --------------------------------------------------------------------- #
# 6. MapGeometry
# --------------------------------------------------------------------- #


@pytest.fixture
def geo():
    return MapGeometry(
        pc=(0.49, 0.28, 0.61),
        shape=(60, 80),
        px_size=55.0,
        binning=2,
        step_sizes=(30.0, 45.0),
        navigation_shape=(5, 7),
        tilt=3.0,
        azimuthal=2.0,
        sample_tilt=69.0,
        twist=1.0,
    )


def test_map_geometry_defaults(geo):
    assert geo.reference == (2.0, 3.0)
    assert geo.angles == (3.0, 2.0, 69.0, 1.0)
    assert geo.as_dict() == {
        "pcx": 0.49,
        "pcy": 0.28,
        "pcz": 0.61,
        "tilt": 3.0,
        "azimuthal": 2.0,
        "sample_tilt": 69.0,
        "twist": 1.0,
    }
    assert_allclose(geo.values(["tilt", "pcx"]), [3.0, 0.49], rtol=0, atol=0)
    assert_allclose(geo.values(), [0.49, 0.28, 0.61, 3.0, 2.0, 69.0, 1.0])
    assert geo.values().dtype == np.float64
    line = MapGeometry(
        pc=(0.5, 0.3, 0.6),
        shape=(60, 60),
        px_size=60,
        binning=1,
        step_sizes=(10, 10),
        navigation_shape=(9,),
    )
    assert line.navigation_shape == (1, 9)
    assert line.reference == (0.0, 4.0)
    with pytest.raises(ValueError, match="2D"):
        MapGeometry(
            pc=(0.5, 0.3, 0.6),
            shape=(60, 60),
            px_size=60,
            binning=1,
            step_sizes=(10, 10),
            navigation_shape=(2, 3, 4),
        )


def test_map_geometry_pc_field(geo):
    pts = np.array([[0, 0], [2, 3], [4, 6], [1.5, -2.0]])
    want = pc_field(
        geo.pc,
        pts[:, 0],
        pts[:, 1],
        geo.reference,
        geo.step_sizes,
        geo.shape,
        geo.px_size,
        geo.binning,
        *geo.angles,
    )
    assert_allclose(geo.pc_at(pts), want, rtol=0, atol=0)
    assert_allclose(geo.pc_at([2, 3]), [geo.pc], rtol=0, atol=1e-15)
    det = geo.detector(pts)
    assert det.navigation_shape == (4,)
    assert_allclose(det.pc, want, rtol=0, atol=1e-15)
    assert det.shape == (60, 80) and det.px_size == 55.0 and det.binning == 2
    assert (det.tilt, det.azimuthal, det.sample_tilt, det.twist) == geo.angles
    full = geo.detector()
    assert full.navigation_shape == (5, 7)
    assert_allclose(full.pc[1, 5], geo.pc_at([1, 5])[0], rtol=0, atol=1e-15)


def test_map_geometry_frozen(geo):
    with pytest.raises(dataclasses.FrozenInstanceError):
        geo.tilt = 4.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        geo.pc = (0.5, 0.5, 0.5)


def test_map_geometry_updated(geo):
    new = geo.updated({"pcy": -0.01, "azimuthal": 0.5, "sample_tilt": -1.0})
    assert_allclose(
        new.values() - geo.values(), [0, -0.01, 0, 0, 0.5, -1.0, 0], rtol=0, atol=1e-15
    )
    assert new.reference == geo.reference and new.step_sizes == geo.step_sizes
    assert geo.pc == (0.49, 0.28, 0.61) and geo.azimuthal == 2.0  # Unchanged
    with pytest.raises(ValueError, match="Unknown geometry parameter"):
        geo.updated({"yaw": 1.0})
    assert geo.updated({}) == geo


@pytest.mark.parametrize("reference", [None, (0.0, 6.0)])
def test_map_geometry_round_trip_pc_map(geo, reference):
    g = dataclasses.replace(geo, reference=reference)
    det = g.detector()
    back = MapGeometry.from_detector(det, g.step_sizes, g.navigation_shape)
    # The reference of a PC map is the map centre; the field is the same
    assert back.reference == (2.0, 3.0)
    assert back.angles == g.angles and back.shape == g.shape
    assert back.px_size == g.px_size and back.binning == g.binning
    rows, cols = np.indices(g.navigation_shape)
    pts = np.c_[rows.ravel(), cols.ravel()]
    assert_allclose(back.pc_at(pts), g.pc_at(pts), rtol=0, atol=1e-12)
    if reference is None:
        assert_allclose(back.values(), g.values(), rtol=0, atol=1e-12)


def test_map_geometry_round_trip_line():
    g = MapGeometry(
        pc=(0.5, 0.3, 0.6),
        shape=(60, 60),
        px_size=60,
        binning=4,
        step_sizes=(10, 25),
        navigation_shape=(9,),
        azimuthal=3.0,
    )
    det = g.detector()
    assert det.navigation_shape == (9,)
    back = MapGeometry.from_detector(det, g.step_sizes, (9,))
    assert back.navigation_shape == (1, 9)
    assert_allclose(back.values(), g.values(), rtol=0, atol=1e-12)
    assert back.reference == g.reference


def test_map_geometry_from_single_pc_detector():
    det = EBSDDetector(
        (60, 80),
        px_size=55.0,
        binning=4,
        tilt=2.0,
        azimuthal=-1.0,
        sample_tilt=70.0,
        twist=0.4,
        pc=(0.51, 0.29, 0.58),
    )
    g = MapGeometry.from_detector(det, (20.0, 20.0), (4, 6))
    assert g.reference == (1.5, 2.5)
    assert_allclose(g.values(), [0.51, 0.29, 0.58, 2.0, -1.0, 70.0, 0.4], rtol=0, atol=1e-12)
    assert g.shape == (60, 80) and g.px_size == 55.0 and g.binning == 4
    g2 = MapGeometry.from_detector(det, (20.0, 20.0), (4, 6), reference=(0, 5))
    assert g2.reference == (0.0, 5.0)
    assert_allclose(g2.pc_at([0, 5]), [[0.51, 0.29, 0.58]], rtol=0, atol=1e-12)
    # geometry -> detector -> geometry, with one PC at the reference
    again = MapGeometry.from_detector(
        g2.detector([g2.reference]), (20.0, 20.0), (4, 6), reference=g2.reference
    )
    assert_allclose(again.values(), g2.values(), rtol=0, atol=1e-12)


def test_map_geometry_wrong_pc_count():
    det = EBSDDetector((60, 60), pc=np.full((6, 3), 0.5))
    with pytest.raises(ValueError, match="6 PCs"):
        MapGeometry.from_detector(det, (10, 10), (3, 4))


def test_map_geometry_displacement(geo):
    other = geo.updated(
        {"pcx": 0.004, "pcz": -0.003, "tilt": 0.6, "azimuthal": -0.4, "twist": 0.3}
    )
    pts = np.array([[0, 0], [2, 3], [4, 6]])
    x = np.array([5.0, 40.0, 70.0, 12.5])
    y = np.array([3.0, 30.0, 50.0, 44.0])
    uv = geo.displacement(other, pts, x, y)
    assert uv.shape == (3, 4, 2)
    pa, pb = geo.pc_at(pts), other.pc_at(pts)
    for k in range(3):
        xb, yb = forward_map(x, y, pa[k], geo.angles, pb[k], other.angles, geo.shape)
        assert_allclose(uv[k, :, 0], xb - x, rtol=0, atol=1e-12)
        assert_allclose(uv[k, :, 1], yb - y, rtol=0, atol=1e-12)
    # The PC field makes displacements differ between map points
    assert np.abs(uv[0] - uv[2]).max() > 1e-3
    assert np.abs(uv).max() > 0.3
    # No change, no displacement
    assert_allclose(geo.displacement(geo, pts, x, y), 0.0, atol=1e-10)


def test_map_geometry_from_pc_map_with_nan(geo):
    # NaN PCs (unrefined points) must not shift the reference position
    geo = geo.updated({"azimuthal": 2.0})
    det = geo.detector()
    pc = det.pc.copy()
    pc[0] = np.nan
    det.pc = pc
    back = MapGeometry.from_detector(det, geo.step_sizes, geo.navigation_shape)
    expected = geo.pc_at(np.argwhere(np.ones(geo.navigation_shape)))
    assert np.allclose(
        back.pc_at(np.argwhere(np.ones(geo.navigation_shape))), expected, atol=1e-12
    )
    det.pc = np.full_like(pc, np.nan)
    with pytest.raises(ValueError, match="all NaN"):
        MapGeometry.from_detector(det, geo.step_sizes, geo.navigation_shape)


def test_values_unknown_name(geo):
    with pytest.raises(ValueError, match="roll"):
        geo.values(["roll"])
