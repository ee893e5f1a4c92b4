"""1D line-scan maps: :mod:`kikuchipy_geomdic.geometry.maps` and
:func:`~kikuchipy_geomdic.refine_geometry_dic` on maps of navigation shape
(n,) and (1, n).

The line scan is the first row of a synthetic 2 x 6 silicon map (60 x 60
px patterns, known geometry, the default start perturbation), put into a
1D signal, a (1, n) signal and a 1D crystal map by hand.
"""

import numpy as np
import pytest
from kikuchipy.signals import EBSD
from orix.crystal_map import CrystalMap

import kikuchipy_geomdic as kg
from kikuchipy_geomdic.calibration.refinement import calibration_points
from kikuchipy_geomdic.geometry import copy_detector
from kikuchipy_geomdic.geometry.maps import flat_index, navigation_shape
from kikuchipy_geomdic.validation import synthetic

N = 6
SIZE = 60


@pytest.fixture(scope="module")
def line(si_mp):
    """(synthetic map, patterns (N, 60, 60), start crystal map (N,),
    start detector with N PCs, true PCs (N, 3)) of the map's first row."""
    sm = synthetic.synthetic_map(si_mp, (2, N), shape=(SIZE, SIZE), seed=0)
    dx = sm.geometry.step_sizes[1]
    xmap = CrystalMap(
        rotations=sm.start_xmap.rotations[:N],
        x=np.arange(N) * dx,
        phase_list=sm.start_xmap.phases,
        scan_unit="um",
    )
    det = copy_detector(sm.start_detector, pc=sm.start_detector.pc[0])
    return sm, np.asarray(sm.signal.data[0]), xmap, det, sm.detector.pc[0]


def _signal(data, dx, two_d):
    axes = [{"name": "x", "size": N, "scale": dx, "units": "um"}]
    if two_d:
        axes.insert(0, {"name": "y", "size": 1, "scale": dx, "units": "um"})
        data = data[None]
    axes += [{"name": "dy", "size": SIZE}, {"name": "dx", "size": SIZE}]
    return EBSD(data, axes=axes)


@pytest.mark.parametrize("two_d", [False, True], ids=["(n,)", "(1, n)"])
def test_navigation_shape_and_flat_index(line, two_d):
    sm, data, xmap, _, _ = line
    s = _signal(data, sm.geometry.step_sizes[1], two_d)
    assert s.axes_manager.navigation_dimension == (2 if two_d else 1)
    nav = navigation_shape(s)
    assert nav == (1, N) == navigation_shape(xmap)
    assert flat_index([[0, 0], [0, 4]], nav).tolist() == [0, 4]
    assert int(flat_index((0, N - 1), nav)) == N - 1
    with pytest.raises(ValueError):
        flat_index([[1, 0]], nav)  # a second row does not exist


def test_navigation_shape_refuses_3d():
    with pytest.raises(ValueError, match="1D or 2D"):
        navigation_shape(EBSD(np.zeros((2, 2, 2, 3, 3))))


def test_calibration_points_on_a_line():
    p = calibration_points((1, 50), 7)
    assert p[:, 0].tolist() == [0] * 7
    assert p[0, 1] == 0 and p[-1, 1] == 49 and len(np.unique(p[:, 1])) == 7


@pytest.mark.parametrize("two_d", [False, True], ids=["(n,)", "(1, n)"])
def test_refine_line_scan(line, two_d):
    sm, data, xmap, det, true_pc = line
    s = _signal(data, sm.geometry.step_sizes[1], two_d)
    res = kg.refine_geometry_dic(
        s,
        xmap,
        det,
        sm.master_pattern,
        sm.energy,
        parameters=["pcx", "pcy", "pcz"],
        points=N,
        show_progressbar=False,
    )
    assert res.points.tolist() == [[0, c] for c in range(N)]
    assert res.geometry.navigation_shape == (1, N)
    # One PC per pattern of the line, at the truth; the start was far off
    pc = res.detector.pc.reshape(-1, 3)
    assert pc.shape == (N, 3)
    assert np.abs(det.pc - true_pc).max() > 1e-2
    assert np.abs(pc - true_pc).max() < 3e-4
    # The patterns were read at their columns: refined orientations fit
    assert res.xmap.scores.min() > 0.99
    assert res.converged
