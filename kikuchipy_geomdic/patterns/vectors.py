"""The displacement vectors of one pair of patterns, with OpenCV or without.

:func:`pattern_vectors` preprocesses a simulated and an experimental
pattern (:mod:`~kikuchipy_geomdic.patterns.preprocessing`), finds
Shi-Tomasi features in the simulated one per ROI, tracks them into the
experimental one with pyramidal Lucas-Kanade (LK) optical flow, and keeps
the vectors that pass the tests of
:func:`~kikuchipy_geomdic.patterns.roi.filter_vectors`;
:func:`~kikuchipy_geomdic.patterns.displacement.measure_displacements`
runs it on every pair of a map. The defaults of the DIC options, which
both take, are defined here.

Backends
--------
``dic="opencv"`` uses :func:`cv2.goodFeaturesToTrack` (run per ROI, so
that every ROI gets its quota) and :func:`cv2.calcOpticalFlowPyrLK`, as
the paper does. ``dic="skimage"`` needs no OpenCV: the same Shi-Tomasi
strength (Sobel derivatives, box window, scikit-image's
:func:`~skimage.feature.structure_tensor_eigenvalues`), the same greedy
per-ROI selection, and a pyramidal LK tracker written here with
NumPy/SciPy (Bouguet's scheme as in OpenCV, in floating point).
``dic="auto"`` takes OpenCV when it can be imported. Both backends pick the
same features and agree to a few hundredths of a pixel.

After tracking, each vector is attached to the point where LK actually
measured it, the structure-tensor weighted centre of its window, not to
the feature itself; where the displacement varies (pcz, tilt) this halved
the error per vector on simulated patterns.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from scipy import ndimage

from kikuchipy_geomdic.patterns._features import _features_opencv, _features_skimage
from kikuchipy_geomdic.patterns._lucas_kanade import (
    _max_levels,
    _track_numpy,
    _track_opencv,
    _window_centres,
)
from kikuchipy_geomdic.patterns.preprocessing import (
    _check_tracking,
    _prepare,
    _standardise,
    _to_uint8,
)
from kikuchipy_geomdic.patterns.roi import _check_grid, _tracking_labels, filter_vectors

__all__ = ["pattern_vectors", "resolve_backend"]

#: The DIC options of one pattern pair with their defaults, in the order of
#: :func:`~kikuchipy_geomdic.patterns.displacement.measure_displacements`'
#: signature, which takes its defaults from here: their one definition
#: (the options are described there).
_DIC_DEFAULTS = {
    "rois": (8, 8),
    "binning": 1,
    "noise": 0.0,
    "blur": 0.0,
    "dic": "auto",
    "max_roi_crossings": 2,
    "forward_backward": 0.2,
    "robust": 3.0,
    "features_per_roi": 8,
    "window": 11,
    "levels": 3,
    "smoothing": 0.7,
}


def _import_cv2():
    try:
        import cv2
    except ImportError:
        return None
    return cv2


def resolve_backend(dic: str = "auto") -> str:
    """Return the DIC backend to use: "opencv" or "skimage".

    Parameters
    ----------
    dic
        "auto" (OpenCV when importable, else scikit-image), "opencv" or
        "skimage".

    Returns
    -------
    backend

    Raises
    ------
    ImportError
        If "opencv" is asked for and :mod:`cv2` cannot be imported.

    Examples
    --------
    >>> from kikuchipy_geomdic.patterns.vectors import resolve_backend
    >>> resolve_backend("skimage")
    'skimage'
    """
    if dic not in ("auto", "opencv", "skimage"):
        raise ValueError(f"dic must be 'auto', 'opencv' or 'skimage', not {dic!r}")
    if dic == "skimage":
        return dic
    if _import_cv2() is not None:
        return "opencv"
    if dic == "opencv":
        raise ImportError(
            "dic='opencv' needs OpenCV (pip install opencv-python-headless); or use dic='skimage'"
        )
    return "skimage"


def pattern_vectors(
    simulated: np.ndarray,
    experimental: np.ndarray,
    rng: np.random.Generator | int | None = None,
    index: int = 0,
    **options,
) -> tuple[np.ndarray, np.ndarray]:
    """Return the displacement vectors of one pattern pair.

    Parameters
    ----------
    simulated, experimental
        One simulated and one experimental 2D pattern of one shape.
    rng
        Generator (or seed) of the noise added to *simulated*.
    index
        Names the pattern in error messages.
    **options
        The DIC options of
        :func:`~kikuchipy_geomdic.patterns.displacement.measure_displacements`
        (``rois``, ``binning``, ``noise``, ``blur``, ``dic``, ``max_roi_crossings``,
        ``forward_backward``, ``robust``, ``features_per_roi``,
        ``window``, ``levels``, ``smoothing``), with its defaults.

    Returns
    -------
    xy_a, xy_b
        Endpoints (n, 2) of the vectors that passed every test, in
        full-resolution pixel coordinates: a feature in A and where it was
        tracked to in B.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy import ndimage
    >>> from kikuchipy_geomdic.patterns.vectors import pattern_vectors
    >>> a = ndimage.gaussian_filter(np.random.default_rng(0).random((60, 60)), 2)
    >>> b = ndimage.shift(a, (0.5, 1.0), mode="nearest")  # x + 1, y + 0.5
    >>> xy_a, xy_b = pattern_vectors(a, b, rois=(4, 4), dic="skimage")
    >>> xy_a.shape[1], np.round(np.median(xy_b - xy_a, axis=0), 1)
    (2, array([1. , 0.5]))
    """
    o = _dic_options(options)
    rois, binning, window = o["rois"], o["binning"], o["window"]
    backend = resolve_backend(o["dic"])
    a = np.asarray(simulated, dtype=np.float64)
    b = np.asarray(experimental, dtype=np.float64)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(
            f"Simulated and experimental patterns must be 2D of one shape, not "
            f"{a.shape} and {b.shape}"
        )
    shape, rois = _check_grid(a.shape, rois)
    _check_tracking(shape, rois, binning, window)
    a = _standardise(a, index, "Simulated")
    b = _standardise(b, index, "Experimental")
    if o["blur"]:
        a = ndimage.gaussian_filter(a, o["blur"], mode="nearest")
        a = _standardise(a, index, "Simulated")
    if o["noise"]:
        a = a + np.random.default_rng(rng).normal(0.0, o["noise"], a.shape)  # std(a) is 1
    a, b = _prepare(a, binning, o["smoothing"]), _prepare(b, binning, o["smoothing"])
    # Features closer than half a window to the edge are not used: their
    # LK window would reach outside the pattern
    labels = _tracking_labels(shape, rois, binning, a.shape, window // 2)
    top = _max_levels(a.shape, window, o["levels"])
    if backend == "opencv":
        cv2 = _import_cv2()
        img_a, img_b = _to_uint8(a, b)
        pts = _features_opencv(cv2, a, labels, o["features_per_roi"])
        track = partial(_track_opencv, cv2, window=window, levels=top)
    else:
        img_a, img_b = a, b
        pts = _features_skimage(a, labels, o["features_per_roi"])
        track = partial(_track_numpy, window=window, levels=top)
    end = pts
    if len(pts):
        end, ok = track(img_a, img_b, pts)
        if o["forward_backward"] is not None and ok.any():
            back, ok_back = track(img_b, img_a, end)
            miss = np.hypot(*(back - pts).T) * binning
            ok &= ok_back & (miss <= o["forward_backward"])
        pts, end = pts[ok], end[ok]
        shift = _window_centres(a, pts, window)
        pts, end = pts + shift, end + shift
    # Binned pixel k is centred on full-resolution coordinate k b + (b - 1) / 2
    xy_a = pts * binning + (binning - 1) / 2
    xy_b = end * binning + (binning - 1) / 2
    keep = filter_vectors(xy_a, xy_b, shape, rois, o["max_roi_crossings"], o["robust"])
    return xy_a[keep], xy_b[keep]


def _dic_options(options) -> dict:
    """*options* completed with the defaults; an unknown name raises as a
    misspelt keyword argument would."""
    unknown = sorted(set(options) - set(_DIC_DEFAULTS))
    if unknown:
        raise TypeError(f"Unknown DIC option(s) {unknown}: use {list(_DIC_DEFAULTS)}")
    return {**_DIC_DEFAULTS, **options}
