"""Pattern preprocessing before the DIC: binning, standardising, smoothing.

Per pattern pair, in this order: both patterns are standardised (zero
mean, unit standard deviation); the simulated one is optionally blurred
(the detector's point spread, which simulations lack) and gets Gaussian
noise (as in the paper); both are binned (:func:`bin_pattern`), smoothed
and standardised again; the OpenCV backend then maps both to 8 bits with
one common linear map. The binning and smoothing happen in
:func:`~kikuchipy_geomdic.patterns.vectors.pattern_vectors`, whose
options they are.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from kikuchipy_geomdic.patterns.roi import roi_edges

__all__ = ["bin_pattern"]

#: An ROI must span at least this many tracking pixels each way.
MIN_ROI_SIZE = 4


def bin_pattern(pattern: np.ndarray, binning: int, dtype=np.float64) -> np.ndarray:
    """Return a pattern binned by averaging *binning* x *binning* blocks.

    Rows and columns left over at the bottom and right edges (when the
    shape is not a multiple of *binning*) are dropped. The centre of
    binned pixel ``k`` is at full-resolution coordinate
    ``k * binning + (binning - 1) / 2``.

    Parameters
    ----------
    pattern
        Array (..., rows, columns): one pattern or a stack; the last two
        axes are binned.
    binning
        Positive integer.
    dtype
        Floating type the blocks are averaged in and returned as.

    Returns
    -------
    binned
        Array of shape ``(..., rows // binning, columns // binning)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.patterns.preprocessing import bin_pattern
    >>> bin_pattern(np.arange(20.0).reshape(4, 5), 2)
    array([[ 3.,  5.],
           [13., 15.]])
    """
    p = np.asarray(pattern, dtype=dtype)
    if binning == 1:
        return p
    nr, nc = p.shape[-2] // binning, p.shape[-1] // binning
    p = p[..., : nr * binning, : nc * binning]
    blocks = p.reshape(p.shape[:-2] + (nr, binning, nc, binning))
    # The block's pixels added as strided views: numpy's mean over the two
    # block axes took 6x as long (0.059 -> 0.009 ms per 96 px pattern, by 2)
    out = blocks[..., :, 0, :, 0].copy()
    for i in range(binning):
        for j in range(binning):
            if i or j:
                out += blocks[..., :, i, :, j]
    out /= binning * binning
    return out


def _centred(z: np.ndarray) -> tuple[np.ndarray, np.floating]:
    # z less its mean, and its standard deviation: numpy's std step by
    # step (the same bits), the centred copy kept for the division (std
    # and mean apart made it twice, four passes per pattern of the DIC)
    d = z - z.mean()
    return d, np.sqrt(np.multiply(d, d).sum() / d.size)


def _standardise(pattern: np.ndarray, index: int, name: str) -> np.ndarray:
    if not np.all(np.isfinite(pattern)):
        raise ValueError(f"{name} pattern {index} contains NaN or infinite values")
    centred, std = _centred(pattern)
    if not std > 1e-12 * max(1.0, np.abs(pattern).max()):
        raise ValueError(f"{name} pattern {index} is constant: nothing to track")
    return centred / std


def _to_uint8(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # OpenCV 5's LK takes only 8-bit images. One linear map for A and B
    # keeps LK's brightness constancy; the full range is kept because
    # the brightest pixels (zone axes, 5-10 std above the mean) are where
    # the corners are, and clipping them would flatten those corners
    lo, hi = min(a.min(), b.min()), max(a.max(), b.max())
    scale = 255 / (hi - lo)
    return tuple(np.rint((z - lo) * scale).astype(np.uint8) for z in (a, b))


def _prepare(z: np.ndarray, binning: int, smoothing: float) -> np.ndarray:
    # Smoothing takes out detail near the Nyquist frequency, which aliases
    # in simulated patterns and biases bilinear LK towards half pixels
    z = bin_pattern(z, binning)
    if smoothing:
        z = ndimage.gaussian_filter(z, smoothing, mode="nearest")
    centred, std = _centred(z)
    if not std > 0:
        raise ValueError("A pattern is constant after binning: nothing to track")
    # One intensity scale for A and B: LK assumes equal brightness
    return centred / std


def _check_tracking(shape, rois, binning, window):
    if int(binning) != binning or binning < 1:
        raise ValueError(f"binning must be a positive integer, not {binning}")
    if int(window) != window or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd integer >= 3, not {window}")
    row_edges, col_edges = roi_edges(shape, rois)
    smallest = min(np.diff(row_edges).min(), np.diff(col_edges).min()) / binning
    if smallest < MIN_ROI_SIZE:
        raise ValueError(
            f"The ROI grid {rois} is too fine for patterns of shape {shape} with "
            f"binning {binning}: the smallest ROI spans {smallest:g} tracking pixels, "
            f"at least {MIN_ROI_SIZE} are needed to hold features"
        )
