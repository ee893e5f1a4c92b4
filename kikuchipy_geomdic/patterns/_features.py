"""Shi-Tomasi features per ROI, with OpenCV or with scikit-image.

Both backends rank corners by the same strength (the smaller
structure-tensor eigenvalue, Sobel derivatives, box window) and pick them
greedily per ROI, so that they choose the same features.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import functools

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


@functools.lru_cache(maxsize=32)
def _crops(boxes, shape):
    """Per ROI box: the crop around it with a margin of :data:`BLOCK_SIZE`
    (so that corner strengths at the ROI's edge are those of the whole
    image) and the ROI's mask in it, read-only; None for an empty ROI.
    Cached: the same for every pattern of a map."""
    out = []
    for box in boxes:
        if box is None:
            out.append(None)
            continue
        r0, r1, c0, c1 = box
        R0, R1 = max(r0 - BLOCK_SIZE, 0), min(r1 + BLOCK_SIZE, shape[0])
        C0, C1 = max(c0 - BLOCK_SIZE, 0), min(c1 + BLOCK_SIZE, shape[1])
        mask = np.zeros((R1 - R0, C1 - C0), np.uint8)
        mask[r0 - R0 : r1 - R0, c0 - C0 : c1 - C0] = 255
        mask.flags.writeable = False
        out.append((R0, R1, C0, C1, mask))
    return tuple(out)


def _features_opencv(cv2, z, labels, boxes, per_roi):
    # goodFeaturesToTrack takes float32 (only LK needs 8 bits): 8-bit
    # steps would make corners out of smooth ramps
    img = z.astype(np.float32)
    eig = cv2.cornerMinEigenVal(img, BLOCK_SIZE)
    both = cv2.cornerEigenValsAndVecs(img, BLOCK_SIZE, 3)[..., :2]
    floor = QUALITY_FLOOR * float(both.max())
    roi_max = ndimage.maximum(eig, labels, np.arange(len(boxes)))
    pts = []
    # One call per ROI so that every ROI gets its quota (on the whole
    # image, strong band intersections would take all the corners)
    for crop, top in zip(_crops(boxes, img.shape), roi_max):
        if crop is None or not top > floor:
            continue
        R0, R1, C0, C1, mask = crop
        found = cv2.goodFeaturesToTrack(
            img[R0:R1, C0:C1],
            maxCorners=per_roi,
            qualityLevel=max(QUALITY, floor / top),
            minDistance=MIN_DISTANCE,
            mask=mask,
            blockSize=BLOCK_SIZE,
        )
        if found is not None:
            pts.append(found.reshape(-1, 2).astype(np.float64) + (C0, R0))
    return np.concatenate(pts) if pts else np.zeros((0, 2))


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
    floor = QUALITY_FLOOR * edge.max()
    n_rois = labels.max() + 1
    peak = (resp == ndimage.maximum_filter(resp, size=3, mode="nearest")) & (labels >= 0)
    peak &= resp > floor
    roi_max = np.append(ndimage.maximum(resp, labels, np.arange(n_rois)), np.inf)
    peak &= resp >= QUALITY * roi_max[labels]
    rr, cc = np.nonzero(peak)
    lab, val = labels[rr, cc], resp[rr, cc]
    order = np.lexsort((-val, lab))  # By ROI, strongest first
    rr, cc, lab = rr[order], cc[order], lab[order]
    # Greedy minimum distance within each ROI, as goodFeaturesToTrack
    chosen = []
    for group in np.split(np.arange(lab.size), np.flatnonzero(np.diff(lab)) + 1):
        kept = []
        for k in group:
            if all((rr[k] - rr[q]) ** 2 + (cc[k] - cc[q]) ** 2 >= MIN_DISTANCE**2 for q in kept):
                kept.append(k)
                if len(kept) == per_roi:
                    break
        chosen.extend(kept)
    chosen = np.sort(np.array(chosen, dtype=np.int64))
    return np.stack([cc[chosen], rr[chosen]], axis=1).astype(np.float64)
