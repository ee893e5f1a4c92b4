"""Pyramidal Lucas-Kanade tracking, with OpenCV or with NumPy/SciPy.

The NumPy tracker follows Bouguet's scheme as OpenCV implements it
(binomial pyramid, Scharr gradients, bilinear windows, halving a step that
undoes the last one), in floating point. :func:`_window_centres` moves each
vector to where LK measured it, for either backend.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from scipy import ndimage

#: Lucas-Kanade iterations per pyramid level and the step (in pixels of
#: that level) below which an iteration counts as converged.
LK_ITERATIONS = 30
LK_EPSILON = 0.01


def _track_opencv(cv2, img_a, img_b, pts, window, levels):
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, LK_ITERATIONS, LK_EPSILON)
    p0 = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 1, 2)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        img_a, img_b, p0, None, winSize=(window, window), maxLevel=levels, criteria=criteria
    )
    return p1.reshape(-1, 2).astype(np.float64), status.ravel().astype(bool)


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    # OpenCV's pyrDown: 5-tap binomial blur, keep even pixels, so pixel k
    # of level L + 1 sits at pixel 2k of level L
    kernel = np.array([1, 4, 6, 4, 1]) / 16
    pyr = [img]
    for _ in range(levels):
        blurred = ndimage.convolve1d(pyr[-1], kernel, axis=0, mode="reflect")
        blurred = ndimage.convolve1d(blurred, kernel, axis=1, mode="reflect")
        pyr.append(blurred[::2, ::2])
    return pyr


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Scharr derivatives, as OpenCV's LK uses
    d = np.array([-0.5, 0.0, 0.5])
    s = np.array([3.0, 10.0, 3.0]) / 16
    gx = ndimage.correlate1d(ndimage.correlate1d(img, d, 1, mode="nearest"), s, 0, mode="nearest")
    gy = ndimage.correlate1d(ndimage.correlate1d(img, d, 0, mode="nearest"), s, 1, mode="nearest")
    return gx, gy


class _Windows:
    """Bilinear samples of square windows around many points at once.

    All pixels of a window are whole pixels away from its centre, so they
    share one pair of bilinear weights: gather a (w + 1) x (w + 1) patch
    per point and blend its four shifted views. Images are edge-padded so
    that no index needs clipping; centres are clipped to one pixel
    outside the image.
    """

    def __init__(self, images, half):
        self.pad = half + 2
        self.shape = images[0].shape
        self.flat = [np.pad(im, self.pad, mode="edge").ravel() for im in images]
        self.width = self.shape[1] + 2 * self.pad
        o = np.arange(-half, half + 2)
        self.offsets = (o[:, None] * self.width + o[None, :]).ravel()
        self.side = o.size

    def __call__(self, x, y, which=(0,)):
        x = np.clip(x, -1, self.shape[1])
        y = np.clip(y, -1, self.shape[0])
        x0, y0 = np.floor(x), np.floor(y)
        fx = (x - x0)[:, None, None]
        fy = (y - y0)[:, None, None]
        base = (y0.astype(np.int64) + self.pad) * self.width + x0.astype(np.int64) + self.pad
        idx = base[:, None] + self.offsets
        out = []
        for k in which:
            p = self.flat[k][idx].reshape(-1, self.side, self.side)
            top = p[:, :-1, :-1] + fx * (p[:, :-1, 1:] - p[:, :-1, :-1])
            bottom = p[:, 1:, :-1] + fx * (p[:, 1:, 1:] - p[:, 1:, :-1])
            out.append((top + fy * (bottom - top)).reshape(len(x), -1))
        return out


def _track_numpy(img_a, img_b, pts, window, levels):
    """Pyramidal Lucas-Kanade of *pts* from A to B (Bouguet's scheme).

    Returns the end points and a status flag, as cv2.calcOpticalFlowPyrLK.
    """
    half = window // 2
    o = np.arange(-half, half + 1)
    oy, ox = np.repeat(o, o.size), np.tile(o, o.size)
    flow = np.zeros((len(pts), 2))
    ok = np.ones(len(pts), bool)
    pyr_a, pyr_b = _pyramid(img_a, levels), _pyramid(img_b, levels)
    for level in range(levels, -1, -1):
        a, b = pyr_a[level], pyr_b[level]
        h, w = a.shape
        p = pts / 2**level
        t, tx, ty = _Windows([a, *_gradients(a)], half)(p[:, 0], p[:, 1], (0, 1, 2))
        # Template pixels outside A carry no information
        sx, sy = p[:, :1] + ox, p[:, 1:] + oy
        inside = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)
        tx, ty = tx * inside, ty * inside
        g11, g12, g22 = (tx * tx).sum(1), (tx * ty).sum(1), (ty * ty).sum(1)
        det = g11 * g22 - g12**2
        # OpenCV's minEigThreshold test, on intensities of unit variance
        min_eig = (g11 + g22 - np.sqrt((g11 - g22) ** 2 + 4 * g12**2)) / 2
        ok &= min_eig > 1e-4 * np.maximum(inside.sum(1), 1)
        target = _Windows([b], half)
        active = np.flatnonzero(ok)
        last = np.zeros_like(flow)
        for iteration in range(LK_ITERATIONS):
            if active.size == 0:
                break
            (j,) = target(p[active, 0] + flow[active, 0], p[active, 1] + flow[active, 1])
            e = t[active] - j  # tx, ty are zero outside A: no mask needed
            b1 = np.einsum("ij,ij->i", e, tx[active])
            b2 = np.einsum("ij,ij->i", e, ty[active])
            g = (g11[active], g12[active], g22[active], det[active])
            step = np.stack([(g[2] * b1 - g[1] * b2) / g[3], (g[0] * b2 - g[1] * b1) / g[3]], 1)
            # A step undoing the last one oscillates about the optimum:
            # stop halfway, as OpenCV does
            swing = ((step + last[active]) ** 2).sum(1) < LK_EPSILON**2
            swing &= iteration > 0
            step[swing] = -0.5 * last[active[swing]]
            flow[active] += step
            last[active] = step
            active = active[((step**2).sum(1) > LK_EPSILON**2) & ~swing]
        if level:
            flow *= 2
    end = pts + flow
    h, w = img_a.shape
    ok &= (end[:, 0] > -1) & (end[:, 0] < w) & (end[:, 1] > -1) & (end[:, 1] < h)
    return end, ok


def _max_levels(shape, window, levels):
    # Stop the pyramid before a level is narrower than two windows: on
    # coarser levels LK can lock onto a far-away band, and consistently so
    # when tracking back, which the forward-backward test cannot see
    top = 0
    while top < levels and min(shape) / 2 ** (top + 1) >= 2 * window:
        top += 1
    return top


def _window_centres(img: np.ndarray, pts: np.ndarray, window: int) -> np.ndarray:
    r"""Offsets from *pts* to where LK measured the displacement.

    Linearised, LK returns :math:`\mathbf{G}^{-1}\sum_k \mathbf{g}_k
    \mathbf{g}_k^T \mathbf{d}(\mathbf{x}_k)` over its window: the
    displacement weighted by the local structure tensors, not the one at
    the window centre. Where the displacement varies (a pcz or tilt change
    dilates and shears the pattern) it belongs at the structure-weighted
    centre :math:`\mathbf{p} + \mathbf{G}^{-1}\sum_k \mathbf{g}_k
    \mathbf{g}_k^T (\mathbf{x}_k - \mathbf{p})` (exact for a dilation,
    to first order); reporting it there halved the per-vector error on
    simulated pcz changes.
    """
    if len(pts) == 0:
        return np.zeros((0, 2))
    gx, gy = _gradients(img)
    return _centres(gx, gy, np.asarray(pts, dtype=np.float64), window // 2)


@nb.njit(cache=True, nogil=True)
def _centres(gx, gy, pts, half):
    """:func:`_window_centres` of gradients *gx*, *gy* in one pass: each
    window's gradients sampled bilinearly as :class:`_Windows` samples them
    (centres clipped to one pixel outside, the edge repeated), their
    structure sums taken as they are sampled (the NumPy passes over (n,
    window**2) arrays took a tenth of the DIC measurement)."""
    h, w = gx.shape
    out = np.zeros((pts.shape[0], 2))
    for k in range(pts.shape[0]):
        x, y = min(max(pts[k, 0], -1.0), w), min(max(pts[k, 1], -1.0), h)
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        g11 = g12 = g22 = v1 = v2 = 0.0
        for oy in range(-half, half + 1):
            r0 = min(max(int(y0) + oy, 0), h - 1)
            r1 = min(max(int(y0) + oy + 1, 0), h - 1)
            for ox in range(-half, half + 1):
                c0 = min(max(int(x0) + ox, 0), w - 1)
                c1 = min(max(int(x0) + ox + 1, 0), w - 1)
                top = gx[r0, c0] + fx * (gx[r0, c1] - gx[r0, c0])
                sx = top + fy * (gx[r1, c0] + fx * (gx[r1, c1] - gx[r1, c0]) - top)
                top = gy[r0, c0] + fx * (gy[r0, c1] - gy[r0, c0])
                sy = top + fy * (gy[r1, c0] + fx * (gy[r1, c1] - gy[r1, c0]) - top)
                g11 += sx * sx
                g12 += sx * sy
                g22 += sy * sy
                v1 += sx * sx * ox + sx * sy * oy
                v2 += sx * sy * ox + sy * sy * oy
        det = g11 * g22 - g12 * g12
        cx, cy = (g22 * v1 - g12 * v2) / det, (g11 * v2 - g12 * v1) / det
        # Cannot leave the window; a degenerate tensor keeps the centre
        if math.isfinite(cx) and math.isfinite(cy):
            out[k, 0], out[k, 1] = min(max(cx, -half), half), min(max(cy, -half), half)
    return out
