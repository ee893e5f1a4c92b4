"""Map-level helpers: navigation shape, flat indices of points, whole maps
and their points with a usable orientation (:func:`usable_points`).

A map is handled as (rows, columns) throughout the package: a 1D map of
*n* patterns is a map of shape (1, n). Calibration points are (row, col)
pairs; :func:`flat_index` turns them into indices of the flattened map
(the order of ``signal.data.reshape(-1, *signal_shape)`` and of a whole
crystal map's points).

Layer 1 (geometry): imports nothing of the package outside its own layer.
"""

from __future__ import annotations

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD
from orix.crystal_map import CrystalMap

__all__ = [
    "navigation_shape",
    "flat_index",
    "check_whole_map",
    "check_signal_and_detector",
    "usable_points",
]


def navigation_shape(obj) -> tuple[int, int]:
    """Return the (rows, columns) shape of a map.

    Parameters
    ----------
    obj
        A signal (anything with a HyperSpy ``axes_manager``, e.g. an
        ``EBSD`` or ``LazyEBSD`` map) or an orix
        :class:`~orix.crystal_map.CrystalMap`.

    Returns
    -------
    shape
        (rows, columns); a 1D map of *n* points is (1, n), a single point
        (1, 1).

    Raises
    ------
    ValueError
        If the map is neither 1D nor 2D.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy.signals import EBSD
    >>> from kikuchipy_geomdic.geometry.maps import navigation_shape
    >>> navigation_shape(EBSD(np.zeros((2, 3, 5, 5))))
    (2, 3)
    >>> navigation_shape(EBSD(np.zeros((4, 5, 5))))
    (1, 4)
    """
    if isinstance(obj, CrystalMap):
        nav = tuple(int(n) for n in obj.shape)
    else:
        nav = tuple(int(n) for n in obj.axes_manager.navigation_shape[::-1])
    if len(nav) <= 1:
        # A crystal map of one point has shape ()
        return (1, nav[0] if nav else 1)
    if len(nav) != 2:
        raise ValueError(f"The signal must have a 1D or 2D navigation shape, not {nav}")
    return nav


def flat_index(points, navigation_shape: tuple[int, int]) -> np.ndarray:
    """Return the flat (row-major) indices of (row, col) map points.

    Parameters
    ----------
    points
        (N, 2) integer array of (row, col), or one (row, col) pair.
    navigation_shape
        (rows, columns) of the map, e.g. from :func:`navigation_shape`.

    Returns
    -------
    index
        (N,) integer array (a scalar for one pair).

    Raises
    ------
    ValueError
        If a point lies outside the map.

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry.maps import flat_index
    >>> flat_index([[0, 0], [1, 2]], (3, 4)).tolist()
    [0, 6]
    >>> int(flat_index((2, 3), (3, 4)))
    11
    """
    pts = np.asarray(points)
    if pts.shape[-1:] != (2,) or pts.ndim > 2:
        raise ValueError(f"points must be (row, col) pairs, not an array of shape {pts.shape}")
    return np.ravel_multi_index((pts[..., 0], pts[..., 1]), tuple(navigation_shape))


def check_signal_and_detector(signal, detector) -> None:
    """Raise if *signal* is not a kikuchipy EBSD signal or *detector* not
    a kikuchipy detector.

    Parameters
    ----------
    signal
        The map's patterns.
    detector
        Its detector.

    Raises
    ------
    TypeError
        Naming the argument of the wrong type.
    """
    if not isinstance(signal, EBSD):
        raise TypeError(f"signal must be a kikuchipy EBSD signal, not {type(signal).__name__}")
    if not isinstance(detector, EBSDDetector):
        raise TypeError(
            f"detector must be a kikuchipy EBSDDetector, not {type(detector).__name__}"
        )


def check_whole_map(xmap: CrystalMap) -> None:
    """Raise if *xmap* is not a whole crystal map with one rotation per point.

    Parameters
    ----------
    xmap
        Crystal map.

    Raises
    ------
    TypeError
        If *xmap* is not an orix :class:`~orix.crystal_map.CrystalMap`.
    ValueError
        If some points are outside its data (a sliced or masked map) or
        it has several rotations per point.
    """
    if not isinstance(xmap, CrystalMap):
        raise TypeError(f"xmap must be an orix CrystalMap, not {type(xmap).__name__}")
    if not np.all(xmap.is_in_data):
        raise ValueError(
            "The crystal map has points outside its data (a sliced or masked map): "
            "pass the whole map and exclude points with navigation_mask"
        )
    if xmap.rotations_per_point != 1:
        raise ValueError("The crystal map must have one rotation per point")


def usable_points(xmap: CrystalMap, phase_id: int | None = None) -> np.ndarray:
    """Return which map points have a usable orientation.

    Parameters
    ----------
    xmap
        Crystal map; all its points must be in the data.
    phase_id
        Only points of this phase are usable. Default: any indexed phase.

    Returns
    -------
    usable
        Boolean array of ``xmap.shape``: indexed (phase id >= 0, or the
        given phase) with a finite rotation of norm near 1 (zero
        quaternions, which some files use for non-indexed points, and
        NaN rotations are not usable).

    Examples
    --------
    >>> import numpy as np
    >>> from orix.crystal_map import CrystalMap
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.geometry.maps import usable_points
    >>> q = np.array([[1, 0, 0, 0], [0, 0, 0, 0], [np.nan] * 4, [1, 0, 0, 0]])
    >>> xmap = CrystalMap(Rotation(q), phase_id=np.array([0, 0, 0, -1]))
    >>> usable_points(xmap).tolist()
    [True, False, False, False]
    """
    check_whole_map(xmap)
    ok = _usable_rotations(xmap.rotations.data.reshape(-1, 4))
    pid = xmap.phase_id
    ok &= pid >= 0 if phase_id is None else pid == phase_id
    return ok.reshape(xmap.shape)


def _usable_rotations(q) -> np.ndarray:
    """Which quaternions of *q* (..., 4) are usable: finite, of norm near 1
    (zero quaternions mark non-indexed points in some files)."""
    q = np.asarray(q)
    with np.errstate(invalid="ignore"):
        return np.isfinite(q).all(axis=-1) & (np.abs(np.linalg.norm(q, axis=-1) - 1) < 1e-3)
