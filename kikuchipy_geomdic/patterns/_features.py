"""Shi-Tomasi features per ROI, with OpenCV or with scikit-image.

Both backends rank corners by the same strength (the smaller
structure-tensor eigenvalue, Sobel derivatives, box window) and pick them
with one kernel (:func:`_select`): OpenCV's ``goodFeaturesToTrack`` per
ROI, run once over the whole pattern, so that they choose the same
features.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from scipy import ndimage

#: Shi-Tomasi corners weaker than this fraction of the strongest corner of
#: their ROI are not used (OpenCV's ``qualityLevel``).
QUALITY = 0.01
#: Corners weaker than this fraction of the strongest edge of the whole
#: pattern (largest structure-tensor eigenvalue) are not used either, so
#: that a featureless ROI (flat background, detector shadow, a lone band)
#: yields no vectors instead of noise.
QUALITY_FLOOR = 0.01
#: Smallest distance between two features, in tracking pixels.
MIN_DISTANCE = 3
#: Corner detection window (OpenCV's ``blockSize``).
BLOCK_SIZE = 5


@nb.njit(cache=True, nogil=True)
def _select(resp, labels, n_rois, floor, per_roi):
    """Features (n, 2; x, y) of the corner strengths *resp* (2D): in each
    ROI of *labels* (2D, -1 outside every ROI), its local maxima (3 x 3)
    stronger than :data:`QUALITY` of the ROI's strongest and than *floor*,
    taken strongest first, each at least :data:`MIN_DISTANCE` from those
    taken before, *per_roi* at most; in ROI order, strongest first.

    OpenCV's ``goodFeaturesToTrack`` called per ROI (one call per ROI so
    that every ROI gets its quota: on the whole image, strong band
    intersections would take all the corners) chooses these: the strength
    is the whole pattern's, the same as a crop's with a margin, and so is
    the local maximum; one pass instead of 64 calls per pattern (a
    third of the DIC measurement's time)."""
    ny, nx = resp.shape
    top = np.full(n_rois, -np.inf)
    for i in range(ny):
        for j in range(nx):
            lab = labels[i, j]
            if lab >= 0 and resp[i, j] > top[lab]:
                top[lab] = resp[i, j]
    rr = np.empty(ny * nx, np.int64)
    cc = np.empty(ny * nx, np.int64)
    val = np.empty(ny * nx)
    n = 0
    for i in range(ny):
        for j in range(nx):
            lab = labels[i, j]
            v = resp[i, j]
            if lab < 0 or not (v > floor and v > QUALITY * top[lab]):
                continue
            peak = True
            for ii in range(max(i - 1, 0), min(i + 2, ny)):
                for jj in range(max(j - 1, 0), min(j + 2, nx)):
                    if resp[ii, jj] > v:
                        peak = False
            if peak:
                rr[n], cc[n], val[n] = i, j, v
                n += 1
    order = np.argsort(-val[:n], kind="mergesort")
    kept = np.empty((n_rois, per_roi), np.int64)
    count = np.zeros(n_rois, np.int64)
    for k in order:
        lab = labels[rr[k], cc[k]]
        if count[lab] == per_roi:
            continue
        good = True
        for q in kept[lab, : count[lab]]:
            dy, dx = rr[k] - rr[q], cc[k] - cc[q]
            if dy * dy + dx * dx < MIN_DISTANCE * MIN_DISTANCE:
                good = False
                break
        if good:
            kept[lab, count[lab]] = k
            count[lab] += 1
    out = np.empty((count.sum(), 2))
    m = 0
    for lab in range(n_rois):
        for q in kept[lab, : count[lab]]:
            out[m, 0], out[m, 1] = cc[q], rr[q]
            m += 1
    return out


def _features_opencv(cv2, z, labels, per_roi):
    # Corner strengths from float32 (only LK needs 8 bits): 8-bit steps
    # would make corners out of smooth ramps
    img = z.astype(np.float32)
    eig = cv2.cornerMinEigenVal(img, BLOCK_SIZE)
    both = cv2.cornerEigenValsAndVecs(img, BLOCK_SIZE, 3)[..., :2]
    floor = QUALITY_FLOOR * float(both.max())
    return _select(eig.astype(np.float64), labels, labels.max() + 1, floor, per_roi)


def _eigenvalues(z: np.ndarray) -> np.ndarray:
    # Structure tensor as OpenCV's cornerMinEigenVal computes it (Sobel
    # derivatives, box window), so both backends rank corners alike
    from skimage.feature import structure_tensor_eigenvalues

    gx = ndimage.sobel(z, 1, mode="reflect")
    gy = ndimage.sobel(z, 0, mode="reflect")
    tensor = [
        ndimage.uniform_filter(g, BLOCK_SIZE, mode="reflect") for g in (gy * gy, gx * gy, gx * gx)
    ]
    return structure_tensor_eigenvalues(tensor)  # (largest, smallest)


def _features_skimage(z, labels, per_roi):
    edge, resp = _eigenvalues(z)
    floor = QUALITY_FLOOR * float(edge.max())
    return _select(np.asarray(resp, np.float64), labels, labels.max() + 1, floor, per_roi)
