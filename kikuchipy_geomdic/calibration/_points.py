"""The calibration points: spread evenly over the map
(:func:`calibration_points`), checked, and their patterns read.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import numpy as np
from kikuchipy.signals import EBSD
from orix.crystal_map import CrystalMap

from kikuchipy_geomdic.geometry.maps import flat_index, usable_points


def calibration_points(
    navigation_shape: tuple[int, int], n: int, usable: np.ndarray | None = None
) -> np.ndarray:
    """Return about *n* map points spread evenly over the map.

    Parameters
    ----------
    navigation_shape
        Map shape (rows, columns).
    n
        Number of points wanted.
    usable
        Boolean mask of the map (rows, columns); unusable points
        (non-indexed, NaN patterns) are replaced by the nearest usable
        point not already chosen.

    Returns
    -------
    points
        Integer array (m, 2) of (row, column), ``m <= n``, row-major.

    Examples
    --------
    >>> from kikuchipy_geomdic.calibration.refinement import calibration_points
    >>> calibration_points((10, 20), 8).tolist()
    [[0, 0], [0, 6], [0, 13], [0, 19], [9, 0], [9, 6], [9, 13], [9, 19]]
    """
    ny, nx = navigation_shape
    if usable is None:
        usable = np.ones((ny, nx), dtype=bool)
    n = int(min(n, usable.sum()))
    if n <= 0:
        return np.zeros((0, 2), dtype=int)
    # A grid with the map's aspect ratio and about n nodes
    nr = int(np.clip(round(np.sqrt(n * ny / nx)), 1, ny))
    nc = int(np.clip(int(np.ceil(n / nr)), 1, nx))
    while nr * nc < n:
        nr, nc = min(nr + 1, ny), min(nc + (nr >= ny), nx)
    rows = np.round(np.linspace(0, ny - 1, nr)).astype(int)
    cols = np.round(np.linspace(0, nx - 1, nc)).astype(int)
    grid = np.stack(np.meshgrid(rows, cols, indexing="ij"), -1).reshape(-1, 2)
    # Thin to n nodes evenly along the row-major order
    grid = grid[np.round(np.linspace(0, len(grid) - 1, n)).astype(int)]
    free = usable.copy()
    out = []
    for r, c in grid:
        if not free[r, c]:
            cand = np.argwhere(free)
            if len(cand) == 0:
                break
            r, c = cand[np.argmin(np.hypot(cand[:, 0] - r, cand[:, 1] - c))]
        free[r, c] = False
        out.append((r, c))
    return np.array(sorted(out), dtype=int).reshape(-1, 2)


def _map_points(points, nav: tuple[int, int]) -> np.ndarray:
    """*points* as an (N, 2) integer array of (row, column), checked to lie
    in the map of shape *nav*."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.issubdtype(pts.dtype, np.integer):
        raise ValueError("points must be an int or an (N, 2) integer array of (row, col)")
    outside = (pts < 0).any(axis=1) | (pts[:, 0] >= nav[0]) | (pts[:, 1] >= nav[1])
    if outside.any():
        raise ValueError(
            f"{outside.sum()} point(s) lie outside the map of shape {nav}, e.g. "
            f"{pts[outside][0].tolist()}"
        )
    return pts


def _points(points, usable: np.ndarray, nav: tuple[int, int]) -> np.ndarray:
    if np.ndim(points) == 0:
        return calibration_points(nav, int(points), usable)
    pts = _map_points(points, nav)
    bad = ~usable[pts[:, 0], pts[:, 1]]
    if bad.any():
        raise ValueError(
            f"{bad.sum()} point(s) are not indexed with a phase calibrated from, e.g. "
            f"{pts[bad][0].tolist()}"
        )
    return pts


def _select_points(points, xmap: CrystalMap, phase_ids, nav: tuple[int, int]) -> np.ndarray:
    """The calibration points (N, 2): *points* spread over the usable map
    points of the phases *phase_ids* (one id or several), or the explicit
    array checked; at least one."""
    usable = np.zeros(xmap.shape, dtype=bool)
    for pid in np.atleast_1d(phase_ids):
        usable |= usable_points(xmap, int(pid))
    pts = _points(points, usable.reshape(nav), nav)
    # One pattern is enough where its DIC field determines the parameters
    # (the moving-screen experiment: a PC from each of three patterns);
    # where it does not, the standard errors and the significance rule say so
    if len(pts) < 1:
        raise ValueError("No usable calibration point: at least one is needed")
    return pts


def _experimental(signal: EBSD, pts: np.ndarray, nav: tuple[int, int]) -> np.ndarray:
    data = signal.data
    if len(signal.axes_manager.navigation_shape) == 1:
        sel = data[pts[:, 1]]
    else:
        # Sorted, unique row-major indices read a lazy signal chunk-wise
        data = data.reshape((nav[0] * nav[1],) + data.shape[-2:])
        sel = data[flat_index(pts, nav)]
    if hasattr(sel, "compute"):
        sel = sel.compute()
    sel = np.asarray(sel, dtype=np.float32)
    bad = ~np.isfinite(sel).all(axis=(1, 2))
    if bad.any():
        raise ValueError(
            f"{bad.sum()} calibration pattern(s) contain NaN or infinite values, e.g. "
            f"at (row, col) {pts[bad][0].tolist()}: remove them from xmap or pass "
            "explicit points"
        )
    return sel
