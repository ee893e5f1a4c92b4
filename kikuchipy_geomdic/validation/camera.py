"""Patterns as a detector records them: noise, background, blur.

:func:`degrade_patterns` degrades clean patterns within the full-field
model's own family (``a * blur(S) + b`` plus shot noise); a
:class:`Camera` makes them as a microscope and a user do
(:func:`camera_counts`, then :meth:`Camera.process`).

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import dask.array as da
import numpy as np
from kikuchipy.signals import EBSD
from scipy import ndimage

__all__ = ["degrade_patterns", "Camera", "MODERATE", "REAL_NI", "camera_counts"]


def degrade_patterns(
    patterns: np.ndarray,
    dose: float | None = None,
    background: float = 0.0,
    blur: float = 0.0,
    seed: int = 0,
    index: np.ndarray | None = None,
) -> np.ndarray:
    """Return patterns degraded as on a real detector.

    Parameters
    ----------
    patterns
        Noise-free patterns (n, rows, columns), non-negative intensities.
    dose
        Mean counts per pixel for Poisson shot noise, or ``None``.
    background
        Relative amplitude of a smooth Gaussian background (0 for none).
    blur
        Gaussian blur standard deviation in pixels (0 for none).
    seed
        Seed; pattern *k* draws its noise from ``(seed, index[k])``.
    index
        Map index of each pattern (default ``arange(n)``), so that a
        pattern's noise does not depend on which chunk it was in.

    Returns
    -------
    degraded
        float32 array of the same shape; unchanged patterns if all
        degradations are off.
    """
    out = np.asarray(patterns, dtype=np.float32).copy()
    n, nr, nc = out.shape
    if index is None:
        index = np.arange(n)
    if background:
        y, x = np.mgrid[0:nr, 0:nc]
        g = np.exp(-(((x - 0.45 * nc) / (0.6 * nc)) ** 2 + ((y - 0.35 * nr) / (0.6 * nr)) ** 2))
        out *= (1 + background * g).astype(np.float32)
    if blur:
        out = ndimage.gaussian_filter(out, sigma=(0, blur, blur)).astype(np.float32)
    if dose is not None:
        for k in range(n):
            rng = np.random.default_rng([seed, int(index[k])])
            mean = max(float(out[k].mean()), 1e-12)
            lam = np.clip(out[k], 0, None) * (dose / mean)
            out[k] = rng.poisson(lam).astype(np.float32)
    return out


@dataclass(frozen=True)
class Camera:
    """How a camera records patterns and a user processes them.

    Patterns made by :func:`degrade_patterns` (``a * blur(S) + b`` plus
    shot noise) are in the full-field model's own family; patterns from a
    microscope are not. A :class:`Camera` makes them as a microscope and a
    user do (:func:`camera_counts`, then :meth:`process`):

    1. expected counts ``dose * b_i * B(x, y) * (1 + contrast * K)``, K
       the clean pattern standardised, B a smooth background lobe peaking
       below the pattern centre (corners about 0.3 of the peak), b_i a
       brightness per grain (``1 +- brightness``);
    2. the phosphor's blur (*blur* px) of the expected counts, then
       Poisson noise, stored as uint16;
    3. kikuchipy's static background removal (dividing by the map's mean
       pattern, which on a map of few grains still holds bands: a faint
       inverted ghost common to every pattern) and dynamic background
       removal (dividing by a Gaussian-blurred copy), each stretching the
       result to the full uint16 range.

    Attributes
    ----------
    dose
        Mean counts per pixel (30 for kikuchipy's real Ni patterns).
    contrast
        Kikuchi contrast: relative amplitude of the standardised pattern
        on the background.
    brightness
        Relative spread of the brightness between grains.
    blur
        Standard deviation (px) of the phosphor's Gaussian blur.
    static, dynamic
        Whether the user removes the static and the dynamic background.
        The static background (the map's mean) is kept with the map
        either way, as a microscope records one.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.camera import Camera
    >>> from kikuchipy_geomdic.validation.synthetic import synthetic_map
    >>> sm = synthetic_map("Si", (3, 3), shape=(40, 40), camera=Camera(dose=30))
    >>> sm.signal.data.dtype.name
    'uint16'
    """

    dose: float = 150.0
    contrast: float = 0.1
    brightness: float = 0.1
    blur: float = 0.6
    static: bool = True
    dynamic: bool = True

    def process(self, signal: EBSD) -> None:
        """Remove the static and dynamic backgrounds of a raw map in place,
        as a user does with kikuchipy (lazy signals stay lazy)."""
        mean = signal.data.mean(axis=(0, 1))
        if isinstance(mean, da.Array):
            mean = mean.compute()
        static_bg = np.round(mean).astype(signal.data.dtype)
        if self.static:
            signal.remove_static_background("divide", static_bg=static_bg, show_progressbar=False)
        # Kept with the map, removed or not, as kikuchipy's readers keep
        # the one a microscope records
        signal.static_background = static_bg
        if self.dynamic:
            signal.remove_dynamic_background("divide", show_progressbar=False)


#: Moderate noise: 150 counts per pixel.
MODERATE = Camera(dose=150.0)
#: The noise of kikuchipy's real Ni patterns: 30 counts per pixel.
REAL_NI = Camera(dose=30.0)


def camera_counts(
    patterns: np.ndarray,
    pcs: np.ndarray,
    camera: Camera,
    brightness: np.ndarray | None = None,
    seed: int = 0,
    index: np.ndarray | None = None,
) -> np.ndarray:
    """Return the raw counts a camera records for clean patterns.

    Steps 1 and 2 of :class:`Camera`: a background lobe at each pattern's
    PC, the Kikuchi pattern as a small modulation of it, the phosphor's
    blur, then Poisson noise.

    Parameters
    ----------
    patterns
        Clean simulated patterns (n, rows, columns).
    pcs
        Bruker PC of each pattern (n, 3): the lobe peaks below it and
        widens with pcz.
    camera
        The :class:`Camera`.
    brightness
        Relative brightness b_i of each pattern (n,), default 1.
    seed
        Seed; pattern *k* draws its noise from ``(seed, index[k])``.
    index
        Map index of each pattern (default ``arange(n)``).

    Returns
    -------
    counts
        uint16 array of the shape of *patterns*.
    """
    p = np.asarray(patterns, dtype=np.float64)
    n, nr, nc = p.shape
    pcs = np.asarray(pcs, dtype=float).reshape(n, 3)
    if index is None:
        index = np.arange(n)
    if brightness is None:
        brightness = np.ones(n)
    flat = p.reshape(n, -1)
    k = (flat - flat.mean(axis=1, keepdims=True)) / np.maximum(
        flat.std(axis=1, keepdims=True), 1e-12
    )
    y, x = np.mgrid[0:nr, 0:nc] + 0.5
    out = np.empty(p.shape, dtype=np.uint16)
    for i in range(n):
        # The backscatter lobe: peak a fifth of the height below the PC,
        # width growing with the detector distance
        x0, y0, width = pcs[i, 0] * nc, (pcs[i, 1] + 0.2) * nr, pcs[i, 2] * nc
        lobe = np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * (0.8 * width) ** 2))
        lobe /= lobe.mean()
        expected = (
            camera.dose * brightness[i] * lobe * (1 + camera.contrast * k[i].reshape(nr, nc))
        )
        expected = np.clip(expected, 0, None)
        if camera.blur:
            expected = ndimage.gaussian_filter(expected, camera.blur)
        rng = np.random.default_rng([seed, int(index[i])])
        out[i] = np.minimum(rng.poisson(expected), np.iinfo(np.uint16).max)
    return out
