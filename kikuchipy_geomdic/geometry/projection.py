"""kikuchipy's projection: the sample-to-detector rotation, the PC field
over a map and the forward map of pixels from one geometry to another.

Pixel coordinates are ``(x, y)`` with the centre of pixel ``(row j,
column i)`` at ``(i, j)``; the shift to kikuchipy's ``(i + 0.5, j + 0.5)``
happens only in :func:`forward_map`.

Layer 1 (geometry): imports nothing of the package outside its own layer.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from kikuchipy.detectors import EBSDDetector

__all__ = ["sample_to_detector_matrix", "pc_field", "forward_map"]


def sample_to_detector_matrix(
    tilt: float, azimuthal: float, sample_tilt: float, twist: float = 0.0
) -> np.ndarray:
    """Return kikuchipy's sample-to-detector rotation matrix.

    Parameters
    ----------
    tilt, azimuthal, sample_tilt, twist
        Angles in degrees, as in :class:`~kikuchipy.detectors.EBSDDetector`.

    Returns
    -------
    matrix
        Array of shape (3, 3) with ``matrix @ v_sample = v_detector``.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.geometry import sample_to_detector_matrix
    >>> a = sample_to_detector_matrix(5, 0, 70)
    >>> b = sample_to_detector_matrix(0, 0, 65)
    >>> bool(np.allclose(a, b))  # only tilt - sample_tilt matters
    True
    """
    # Taken from kikuchipy itself so the two can never disagree
    det = EBSDDetector(
        tilt=float(tilt),
        azimuthal=float(azimuthal),
        sample_tilt=float(sample_tilt),
        twist=float(twist),
    )
    return det.sample_to_detector.to_matrix().reshape(3, 3)


def pc_field(
    pc: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    reference: tuple[float, float],
    step_sizes: tuple[float, float],
    shape: tuple[int, int],
    px_size: float,
    binning: float,
    tilt: float,
    azimuthal: float,
    sample_tilt: float,
    twist: float = 0.0,
) -> np.ndarray:
    r"""Return the PC at map positions from one global geometry.

    The beam moves over the sample surface; the PC is the foot of the
    perpendicular from the beam's impact point to the detector screen.
    A beam displacement :math:`\mathbf{s}` in the sample frame is
    :math:`\mathbf{M}\mathbf{s}` in the detector frame, with
    :math:`\mathbf{M}` the full sample-to-detector rotation (all four
    angles), so the PC moves within the screen by its X and Y components
    and ``pcz`` changes by its Z component.

    Parameters
    ----------
    pc
        Bruker PC ``(pcx, pcy, pcz)`` at the *reference* map position.
    rows, cols
        Map positions (row, column), in steps, of any shape (fractional
        values allowed).
    reference
        Map position (row, column) where the PC equals *pc*.
    step_sizes
        Map step sizes (dy, dx) in the same length unit as *px_size*
        (kikuchipy uses micrometres).
    shape
        Detector shape (rows, columns), binned.
    px_size
        Unbinned detector pixel size.
    binning
        Detector binning.
    tilt, azimuthal, sample_tilt, twist
        Angles in degrees.

    Returns
    -------
    pcs
        Array of shape ``rows.shape + (3,)``.

    Notes
    -----
    With ``azimuthal = twist = 0`` this equals
    :meth:`~kikuchipy.detectors.EBSDDetector.extrapolate_pc` (Singh et al.
    2017, appendix A), which ignores the two other angles. kikuchipy's
    sample frame has :math:`X_s` along decreasing map rows and
    :math:`Y_s` along decreasing map columns.

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry import pc_field
    >>> pcs = pc_field(
    ...     (0.5, 0.2, 0.6), rows=[0, 10], cols=[0, 0], reference=(0, 0),
    ...     step_sizes=(10, 10), shape=(120, 120), px_size=70, binning=4,
    ...     tilt=0, azimuthal=0, sample_tilt=70,
    ... )
    >>> pcs.shape
    (2, 3)
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    pc = np.asarray(pc, dtype=np.float64).reshape(3)
    dy, dx = step_sizes
    nrows, ncols = shape
    s = np.stack(
        [
            -(rows - reference[0]) * dy,
            -(cols - reference[1]) * dx,
            np.zeros_like(rows),
        ],
        axis=-1,
    )
    m = sample_to_detector_matrix(tilt, azimuthal, sample_tilt, twist)
    d = s @ m.T / (px_size * binning)  # Detector frame, in binned pixels
    # The source sits at (pcx Nx, -pcy Ny, -pcz Ny) from the screen's
    # upper-left corner in the detector frame
    return pc + np.stack([d[..., 0] / ncols, -d[..., 1] / nrows, -d[..., 2] / nrows], axis=-1)


def forward_map(
    x: np.ndarray,
    y: np.ndarray,
    pc_a: np.ndarray,
    angles_a: Sequence[float],
    pc_b: np.ndarray,
    angles_b: Sequence[float],
    shape: tuple[int, int],
    rotation: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Return where a pixel seen with geometry A lands with geometry B.

    A feature of a pattern at ``(x, y)`` under geometry A shows a
    sample-frame direction; the same direction (same crystal orientation)
    lands at ``(x_b, y_b)`` under geometry B. ``(x_b - x, y_b - y)`` is the
    displacement a geometry change causes, predicted without simulating.
    With *rotation*, the crystal is also rotated: its orientation ``g``
    becomes ``g * T`` (orix's right factor, a sample-frame rotation), and
    the feature follows its crystal direction, which now points along
    ``T^-1`` times the old sample direction.

    Parameters
    ----------
    x, y
        Pixel coordinates (centre of pixel (j, i) at (i, j)) under A.
    pc_a, pc_b
        Bruker PCs of shape (3,) or ``(n, 1, 3)``-like, broadcasting
        against *x* and *y* with a trailing axis of 3.
    angles_a, angles_b
        ``(tilt, azimuthal, sample_tilt, twist)`` in degrees.
    shape
        Detector shape (rows, columns).
    rotation
        Rotation matrix ``T`` (3, 3) of the crystal change, or matrices
        broadcasting against *x* with two trailing axes of 3 (e.g.
        ``(n, 1, 3, 3)``, one per pattern). Default: no change.

    Returns
    -------
    x_b, y_b
        Pixel coordinates under B, broadcast shape of the inputs.
        Directions that miss the screen plane of B (behind the source)
        are NaN.

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry import forward_map
    >>> xb, yb = forward_map(
    ...     10.0, 20.0, (0.5, 0.5, 0.6), (0, 0, 70, 0),
    ...     (0.5 + 1 / 60, 0.5, 0.6), (0, 0, 70, 0), shape=(60, 60),
    ... )
    >>> round(float(xb), 9), round(float(yb), 9)  # PCx by +1 px: +1 px
    (11.0, 20.0)
    """
    nrows, ncols = shape
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    pc_a = np.asarray(pc_a, dtype=np.float64)
    pc_b = np.asarray(pc_b, dtype=np.float64)
    # Vector from the source to the pixel centre in detector frame A,
    # in units of binned pixels (as in kikuchipy's direction cosines)
    v_a = np.stack(
        np.broadcast_arrays(
            x + 0.5 - pc_a[..., 0] * ncols,
            pc_a[..., 1] * nrows - (y + 0.5),
            pc_a[..., 2] * nrows,
        ),
        axis=-1,
    )
    m_a = sample_to_detector_matrix(*angles_a)
    m_b = sample_to_detector_matrix(*angles_b)
    if rotation is None:
        v_b = v_a @ (m_b @ m_a.T).T
    else:
        # Row vectors: sample direction s = M_a^T v_a, then T^-1 s, then M_b
        s_a = v_a @ m_a
        v_b = np.einsum("...i,...ij->...j", s_a, np.asarray(rotation, dtype=np.float64))
        v_b = v_b @ m_b.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = pc_b[..., 2] * nrows / v_b[..., 2]
        t = np.where(t > 0, t, np.nan)
        x_b = pc_b[..., 0] * ncols + t * v_b[..., 0] - 0.5
        y_b = pc_b[..., 1] * nrows - t * v_b[..., 1] - 0.5
    return x_b, y_b
