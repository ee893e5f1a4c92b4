"""What was done to the patterns: the full field's model of how a camera
recorded them and a user processed them (:class:`_Processing`), estimated
from the patterns themselves (:func:`_estimate_processing`), the
signal's static background (:func:`_static_background`) and its lobe
(:func:`_fit_lobe`),
whether dividing by that background took the patterns' bands
(:func:`_bands_divided_out`) and the patterns with them put back
(:func:`_with_mean_bands`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np
from kikuchipy.filters import Window
from kikuchipy.signals import EBSD
from scipy import ndimage

from kikuchipy_geomdic.indexing import orientation as ori
from kikuchipy_geomdic.patterns.vectors import _import_cv2

#: Range and grid (px) of the search for the detector's point spread.
PSF_MAX = 3.0
PSF_STEP = 0.25

#: A Gaussian blur narrower than this (px) is left out: its weight on a
#: neighbouring pixel is below 3e-4.
PSF_NEGLIGIBLE = 0.25

#: High-passes (fractions of the pattern width) the full field tries as
#: the model of the user's dynamic background removal (kikuchipy's
#: default: a width / 8), keeping the one whose model correlates best
#: with the patterns; 0: none.
HIGHPASS_GRID = (0.0, 1 / 12, 1 / 8, 1 / 6)

#: Patterns (at most) on which the full field chooses its high-pass and
#: point spread.
ESTIMATION_PATTERNS = 40

#: Patterns whose derivatives are processed together: their temporaries
#: (4 MB at 8 columns of 120 px) stay in the allocator's reuse, where a
#: whole stack's were new memory at every pass.
DERIVATIVE_BLOCK = 8

#: With the crystal model the full field compares the patterns and its
#: model less their Gaussian blur of this sigma (a fraction of the width;
#: 2.4 px at 120 px): every pattern of one crystal shares its simulator's
#: misfit, largest in the smooth intensities across the bands, which a PC
#: shift can fit, least in the edges and fine lines the geometry places
#: (BaTiO3 domain maps, ebsdsim's data calibrated with de-ebsd's master
#: pattern from users' starts, 12 maps: largest PC error median 3.5e-4
#: unfiltered, 2.7e-4 at 0.01 and 0.02; Si single crystals with the data's
#: own master pattern, 5 maps of 100 um, where the filter only loses
#: signal: largest 2.3e-4 unfiltered, 3.7e-4 at 0.01, 2.7e-4 at 0.02)
COMPARED_HIGHPASS = 0.02

#: Kikuchi contrasts (relative to the background) the full field tries.
CONTRAST_GRID = (0.0, 0.05, 0.1, 0.15, 0.2, 0.3)


#: The compared patterns' mean correlates (high-passed) below this with
#: their simulations' mean where the map's own mean was divided out of
#: them (measured: -0.07 to 0.02 on BaTiO3 domain maps and Ni
#: polycrystals; 0.63-0.67 on the domain maps with only the dynamic
#: background removed).
MEAN_DIVIDED_OUT = 0.2


def _static_background(signal: EBSD) -> np.ndarray | None:
    """The signal's static background (kikuchipy's
    ``EBSD.static_background``) as float64, if it has a usable one: the
    pattern's shape, finite and positive."""
    bg = getattr(signal, "static_background", None)
    shape = tuple(signal.axes_manager.signal_shape[::-1])
    if bg is None or tuple(np.shape(bg)) != shape:
        return None
    bg = np.asarray(bg.compute() if hasattr(bg, "compute") else bg, dtype=np.float64)
    if not np.isfinite(bg).all() or bg.min() <= 0:
        return None
    return bg


def _fit_lobe(background: np.ndarray) -> np.ndarray:
    """The background lobe of a static *background*, mean 1: a Gaussian
    fitted to it (its logarithm, quadratic in x and y, by least squares).
    A map-mean background holds faint bands, which the fit averages out
    where smoothing kept a part (a Gaussian smoothing of an eighth of the
    width left pcz 0.45e-4 off at 20,000 counts/px, the fit 0.24e-4)."""
    shape = background.shape
    y, x = (np.indices(shape).reshape(2, -1) + 0.5) / shape[1]
    basis = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    coef, *_ = np.linalg.lstsq(basis, np.log(background.ravel()), rcond=None)
    lobe = np.exp(basis @ coef).reshape(shape)
    return lobe / lobe.mean()


def _bands_divided_out(
    static_background: np.ndarray, experimental: np.ndarray, simulated: np.ndarray
) -> tuple[float, float] | None:
    """Whether dividing by the *static_background* (rows, columns) took
    the bands of the *experimental* patterns (N, rows, columns), judged
    against their *simulated* ones (N, rows, columns): the map's mean
    was divided out of them (:data:`MEAN_DIVIDED_OUT`), and the
    background correlates better with each pattern's simulation than
    the pattern itself does. On a map of one crystal the map's mean is
    every pattern's bands, and dividing it out leaves little more than
    the noise (BaTiO3 domain maps: 0.13-0.15 against 0.05 at 30
    counts/px, 0.16-0.18 against 0.10 at 150; Ni polycrystals: 0.03-0.05
    against 0.32-0.55, but 0.30-0.34 against 0.28-0.50 where 6 grains
    share the map: the bands are put back only on one crystal).

    Returns the two mean correlations (the background's, the patterns')
    if so, else None. Each is of the patterns high-passed by the model of
    kikuchipy's dynamic background removal (:meth:`_Processing._lowpass`,
    an eighth of the width), the background divided by its lobe
    (:func:`_fit_lobe`) first."""

    shape = static_background.shape
    highpass = _Processing(shape, highpass=shape[1] / 8)

    def flat(a):
        # High-passed, then standardised: correlations are means of products.
        # In float32: the test's two correlations are compared with each
        # other and with MEAN_DIVIDED_OUT, and the float64 low-passes of the
        # patterns were half its cost
        a = np.asarray(a, dtype=np.float32)
        a = a - highpass._lowpass(a)
        return ori.standardise(a.reshape(a.shape[:-2] + (-1,)))

    bands = static_background / _fit_lobe(static_background)
    e, s = flat(experimental), flat(simulated)
    means = flat(np.stack([e.mean(axis=0), s.mean(axis=0)]).reshape((2,) + shape))
    if float((means[0] * means[1]).mean()) >= MEAN_DIVIDED_OUT:
        return None
    held = float((s * flat(bands)).mean(axis=1).mean())
    kept = float((s * e).mean(axis=1).mean())
    return (held, kept) if held > kept else None


def _with_mean_bands(experimental: np.ndarray, static_background: np.ndarray) -> np.ndarray:
    """The *experimental* patterns (N, rows, columns) with the bands of the
    *static_background* (rows, columns) they were divided by put back, as
    float32: each pattern standardised, plus the background divided by its
    lobe (:func:`_fit_lobe`), high-passed by the model of kikuchipy's
    dynamic background removal and standardised.

    On one crystal the map's mean is every pattern's bands, nearly
    noise-free, and dividing it out leaves the variants' differences in
    the noise, which DIC cannot match from a start 1.5 % off (BaTiO3
    domain maps: 8 of 8 kept their start; compared with simulations less
    their own mean, 6 of 8). Put back, the bands bring the DIC stage
    into the full field's basin, and the full field fits the patterns
    as they are, the division modelled (:class:`_Processing`, *ghost*).
    The bands' scale is the patterns' own: DIC matches features,
    whatever their contrast."""
    shape = static_background.shape
    highpass = _Processing(shape, highpass=shape[1] / 8)
    bands = static_background / _fit_lobe(static_background)
    bands = ori.standardise((bands - highpass._lowpass(bands)).reshape(1, -1))
    n = len(experimental)
    e = ori.standardise(np.asarray(experimental, dtype=np.float64).reshape(n, -1))
    return (e + bands).reshape(experimental.shape).astype(np.float32)


def _gaussian_blur(planes: np.ndarray, sigma: float, shape: tuple[int, int]) -> np.ndarray:
    """*planes* (any leading axes, then *shape* or its pixels flattened)
    blurred by a Gaussian of *sigma* px, edges replicated."""
    planes = np.ascontiguousarray(planes)
    flat = planes.reshape((-1,) + tuple(shape))
    cv2 = _import_cv2()
    if cv2 is None:
        return ndimage.gaussian_filter(flat, (0, sigma, sigma), mode="nearest").reshape(
            planes.shape
        )
    # OpenCV's separable filter, plane by plane: scipy's gaussian_filter
    # (mode "nearest", truncated at 4 sigma) to round-off, and 3.5x
    # faster on the (N, K) stacks of Jacobian columns
    radius = int(4.0 * sigma + 0.5)
    depth = cv2.CV_32F if planes.dtype == np.float32 else cv2.CV_64F
    kernel = cv2.getGaussianKernel(2 * radius + 1, sigma, depth)
    out = np.empty_like(planes)
    dst = out.reshape(flat.shape)
    for i in range(len(flat)):
        cv2.sepFilter2D(flat[i], -1, kernel, kernel, dst=dst[i], borderType=cv2.BORDER_REPLICATE)
    return out


def _compared(planes: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """*planes* (any leading axes, then *shape* or its pixels flattened)
    as the full field compares them: less their Gaussian blur of
    :data:`COMPARED_HIGHPASS` times the width. Patterns and model alike:
    a matched filter, not a model of the user's processing."""
    return planes - _gaussian_blur(planes, COMPARED_HIGHPASS * shape[1], shape)


@functools.lru_cache(maxsize=16)
def _lowpass_matrices(shape: tuple[int, int], sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The (rows, rows) and (columns, columns) matrices ``R``, ``Ct`` of
    kikuchipy's dynamic background of patterns of *shape*, ``R @ pattern
    @ Ct``: its frequency-domain filter is a correlation with its
    Gaussian window of *sigma* px (``int(4 * sigma)`` px wide, cut at two
    sigma) over the pattern with its edges replicated. Modelled instead
    as an uncut Gaussian, the weights differed by up to 2.3 % of a row's,
    which a background lobe makes a PC bias (a Si single crystal at
    20,000 counts/px: pcx 5.4e-4 off from the truth; 1.6e-5 with the
    filter itself and the lobe fitted without the mean bands)."""
    if sigma <= 0:
        return np.eye(shape[0]), np.eye(shape[1])
    k = int(4 * sigma)
    window = np.asarray(Window("gaussian", std=sigma, shape=(k, k)), dtype=np.float64)
    weights = window.sum(axis=0) / window.sum()
    before = k - (k - 1) // 2 - 1

    def matrix(n):
        a = np.zeros((n, n))
        rows = np.arange(n)[:, None]
        np.add.at(a, (rows, np.clip(rows - before + np.arange(k), 0, n - 1)), weights)
        return a

    # Columns act from the right, transposed; contiguous (BLAS was 40x
    # slower with a transposed view)
    return matrix(shape[0]), np.ascontiguousarray(matrix(shape[1]).T)


@dataclass(frozen=True)
class _Processing:
    """The full field's model of how the compared patterns were made from
    the simulation ``S``, as a camera records and a user processes them:

    1. ``x = L * (1 + contrast * K)``: ``K`` the pattern standardised, a
       Kikuchi *contrast* on the background *lobe* ``L`` (the smoothed
       static background; flat when unknown);
    2. the detector's point spread, a Gaussian of *psf* px, acting on the
       product: blurring a pattern on a sloping background moves its
       features down the slope, a magnification about the lobe's peak
       that pcz absorbs (measured: 1e-4 on 96 px Ni patterns with a blur
       of 0.6 px);
    3. with *static*, static background removal: divided by the blurred
       lobe, and with *ghost* by the map's mean pattern, bands and all
       (kikuchipy's static background removal with the map's own mean
       holds bands on a map of few grains); without, the lobe stays;
    4. dynamic background removal: divided by its Gaussian low-pass of
       *highpass* px (0: none).

    A *contrast* of 0 is the limit of a faint pattern, where the
    divisions become subtractions (the static background divided out).
    Every step is differentiable, so Jacobian columns go through it with
    the pattern. Fitted as ``a * S + b`` instead (the model family of
    ``degrade_patterns``), processed Ni patterns moved pcz by 5
    standard errors."""

    shape: tuple[int, int]
    psf: float = 0.0
    highpass: float = 0.0
    contrast: float = 0.0
    ghost: bool = False
    static: bool = True
    lobe: np.ndarray | None = field(default=None, compare=False, repr=False)

    def _lowpass(self, planes: np.ndarray) -> np.ndarray:
        r, ct = (
            m.astype(planes.dtype, copy=False)
            for m in _lowpass_matrices(self.shape, self.highpass)
        )
        (rows, cols), m = self.shape, planes.size // (self.shape[0] * self.shape[1])
        t = (planes.reshape(m * rows, cols) @ ct).reshape(m, rows, cols)
        return np.matmul(r, t).reshape(planes.shape)

    def _blur(self, planes: np.ndarray) -> np.ndarray:
        if self.psf < PSF_NEGLIGIBLE:
            return planes
        return _gaussian_blur(planes, self.psf, self.shape)

    def __call__(
        self, s0: np.ndarray, columns: tuple[np.ndarray, ...] = ()
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The model patterns (N, P) of simulated ones *s0* (float32 if
        they are, else float64), and their derivatives (N, K, P) from
        those of *s0*, *columns* (arrays (N, P, k), stacked in their
        order; None without them). The derivatives are processed and
        returned in float32 pattern planes,
        :data:`DERIVATIVE_BLOCK` patterns at a time: a dozen passes over
        them were the full field's largest cost, copying them back to
        float64 (N, P, K) half of what remained, and whole-stack
        temporaries (46 MB at 100 patterns of 120 px) were allocated
        afresh by every pass."""
        n, p = s0.shape
        dtype = np.float32 if s0.dtype == np.float32 else np.float64
        x, kept = self._patterns(np.asarray(s0, dtype=dtype).reshape((n, 1) + self.shape))
        x = np.ascontiguousarray(x[:, 0]).reshape(n, p)
        if not len(columns):
            return x, None
        ks = np.cumsum([0] + [c.shape[2] for c in columns])
        d = np.empty((n, ks[-1]) + self.shape, dtype=np.float32)
        for i in range(0, n, DERIVATIVE_BLOCK):
            block = slice(i, i + DERIVATIVE_BLOCK)
            for c, k0, k1 in zip(columns, ks[:-1], ks[1:]):
                # Cast and transposed in one pass, no stacked float64 copy
                planes = c[block].reshape((-1,) + self.shape + (k1 - k0,))
                d[block, k0:k1] = np.moveaxis(planes, 3, 1)
            # What is per pattern, the block's; what is shared, whole
            part = [a if a is None or len(a) < n else a[block] for a in kept]
            d[block] = self._derivatives(d[block], *part)
        return x, d.reshape(n, d.shape[1], p)

    def _patterns(self, x: np.ndarray, sd: np.ndarray | None = None) -> tuple[np.ndarray, tuple]:
        """The processed pattern planes of simulated ones *x* (N, 1, rows,
        columns; standardised already if their standard deviations *sd*
        are given, :func:`_standardised`, and not written to), and what
        their derivatives need: the standardised pattern (float32), its
        standard deviation, the divisor of the static background removal
        and, with a contrast and a high-pass, the low-pass and the pattern
        divided by it (else None)."""
        x, sd = _standardised(x) if sd is None else (x, sd)
        xs = x.astype(np.float32, copy=False)
        lobe = 1.0 if self.lobe is None else self.lobe.astype(x.dtype)
        c = self.contrast
        low = None
        if c:
            # Step 1 and 2 in counts; 3: the static background divided out,
            # if it was
            raw = x * c
            raw += 1
            raw *= lobe
            den = np.ones((1, 1) + self.shape, dtype=x.dtype)
            if self.static:
                den = self._blur(den * (raw.mean(axis=0, keepdims=True) if self.ghost else lobe))
            x = self._blur(raw)
            x /= den
            if self.highpass:
                low = self._lowpass(x)
                x /= low
        else:
            # The faint-pattern limit of the same: the background's blur
            # divided out of the blurred modulation, the ghost subtracted;
            # in the patterns' type (a float64 divisor made the estimation's
            # float32 candidates float64, their low-pass twice the cost)
            den = self._blur(lobe * np.ones((1, 1) + self.shape, dtype=x.dtype))
            x = self._blur(lobe * x) / den
            if self.ghost:
                x = x - x.mean(axis=0, keepdims=True)
            if self.highpass:
                x = x - self._lowpass(x)
        return x, (xs, sd, den, low, None if low is None else x)

    def _derivatives(self, d, xs, sd, den, low, xh) -> np.ndarray:
        """The steps of :meth:`_patterns` applied to derivatives *d* (m, K,
        rows, columns) of its patterns, in place where they can be, with
        what it kept of them (the ghost held: a pattern moves the map's
        mean by 1 / N of its own change). Divisions are products with
        reciprocals, the projection on the pattern one batched product.

        The ghost is held along the geometry's columns too, though every
        pattern moves it there. Differentiated exactly along them alone,
        the detector angles, which a common rotation of the crystals
        mimics, came out determined to 0.015 deg and 0.7-0.9 deg off on
        two moderate-noise maps of the realistic benchmark: the rotations'
        columns, one pattern each, cannot carry the mean's change."""

        def f32(a):
            return np.asarray(a, dtype=np.float32)

        m, k, p = d.shape[0], d.shape[1], xs.shape[2] * xs.shape[3]
        d -= d.mean(axis=(2, 3), keepdims=True)
        along = (d.reshape(m, k, p) @ xs.reshape(m, p, 1)) / p
        d -= xs * along[..., None]
        d *= f32(1 / sd)
        lobe = 1.0 if self.lobe is None else self.lobe
        d *= f32(self.contrast * lobe if self.contrast else lobe)
        d = self._blur(d)
        d *= f32(1 / den)
        if self.highpass and low is not None:
            low_d = self._lowpass(d)
            low_d *= f32(xh)
            d -= low_d
            d *= f32(1 / low)
        elif self.highpass:
            d -= self._lowpass(d)
        return d


def _standardised(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pattern planes *x* (N, 1, rows, columns) less their means over
    their standard deviations, and those (N, 1, 1, 1)."""
    axes = (2, 3)
    # In place on one copy where a step's input is not kept: the
    # estimation passes 17 stacks through here, and their temporaries
    # were most of its time
    x = x - x.mean(axis=axes, keepdims=True)
    sd = np.sqrt((x**2).mean(axis=axes, keepdims=True))
    x /= sd
    return x, sd


def _ncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """NCC (N,) of the patterns *a* with *b* (N, ...), float64 sums."""
    return _ncc_rows(
        np.ascontiguousarray(a).reshape(len(a), -1), np.ascontiguousarray(b).reshape(len(b), -1)
    )


@nb.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _ncc_rows(a, b):
    # Two passes over each pair of patterns: numpy's centred float64
    # copies, products and sums made ten (17 ms per 100 patterns of 120 px,
    # 1 ms here). Sums reassociated to be vectorised, no other fast math: a
    # constant pattern's NCC stays NaN
    n, p = a.shape
    out = np.empty(n)
    for i in range(n):
        ma = 0.0
        mb = 0.0
        for j in range(p):
            ma += a[i, j]
            mb += b[i, j]
        ma /= p
        mb /= p
        ab = 0.0
        aa = 0.0
        bb = 0.0
        for j in range(p):
            x = a[i, j] - ma
            y = b[i, j] - mb
            ab += x * y
            aa += x * x
            bb += y * y
        out[i] = ab / np.sqrt(aa * bb)
    return out


def _estimate_processing(problem, arrays, geometry, rotations) -> _Processing:
    """The model of what was done to the patterns (:class:`_Processing`)
    that correlates best with them, one property after the other: the
    high-pass (:data:`HIGHPASS_GRID`), the point spread (px; unmodelled,
    a blur of 0.6 px moved pcz by 11 standard errors, band widths being
    what pcz scales), whether the map's mean was divided out, the
    contrast (:data:`CONTRAST_GRID`)."""
    n = len(problem.points)
    shape = tuple(problem.experimental.shape[1:])
    # In float32: the candidates' correlations differ in the fourth
    # decimal, float32 rounds in the seventh, and the passes over the
    # patterns were most of the choice's cost
    e = ori.standardise(problem.experimental.reshape(n, -1).astype(np.float32))
    s0 = problem.simulate(geometry, rotations, arrays).reshape(n, -1).astype(np.float32)
    # The high-pass and the point spread, properties of each pattern, on
    # every k-th pattern; the ghost and the contrast on all of them (on 50
    # of 121 the map's mean pattern was not found)
    few = np.unique(np.linspace(0, n - 1, min(n, ESTIMATION_PATTERNS)).astype(int))
    # Each subset's patterns and simulations (standardised) made once,
    # each model's correlation with them computed once: a step tries
    # again the model an earlier one chose
    subsets = {
        "few": (e[few], *_standardised(s0[few].reshape((-1, 1) + shape))),
        "all": (e, *_standardised(s0.reshape((-1, 1) + shape))),
    }
    nccs = {}

    def ncc(proc, pick):
        key = (proc, id(proc.lobe), pick)
        if key not in nccs:
            e_pick, x, sd = subsets[pick]
            x = proc._patterns(x, sd)[0].reshape(len(x), -1)
            # A constant pattern (NaN) correlates with nothing
            nccs[key] = float(np.nan_to_num(_ncc(x, e_pick)).mean())
        return nccs[key]

    def best(candidates, pick="all"):
        return max(candidates, key=lambda proc: ncc(proc, pick))

    proc = best(
        (_Processing(shape, 2 * PSF_STEP, h * shape[1], lobe=problem.lobe) for h in HIGHPASS_GRID),
        "few",
    )
    sigmas = np.arange(0.0, PSF_MAX + 1e-9, PSF_STEP)
    scores = []
    for sg in sigmas:
        scores.append(ncc(replace(proc, psf=sg), "few"))
        # Past the peak twice in a row: the rest of the grid cannot win
        if len(scores) > 2 and scores[-1] < scores[-2] < max(scores):
            break
    sigmas = sigmas[: len(scores)]
    k = int(np.argmax(scores))
    psf = float(sigmas[k])
    if 0 < k < len(sigmas) - 1:
        # Vertex of the parabola through the best and its neighbours
        a, b, c = scores[k - 1], scores[k], scores[k + 1]
        den = a - 2 * b + c
        if den < 0:
            psf = float(sigmas[k] + PSF_STEP * 0.5 * (a - c) / den)
    proc = replace(proc, psf=psf)
    proc = best(replace(proc, ghost=g) for g in (False, True))
    proc = best(replace(proc, contrast=c) for c in CONTRAST_GRID)
    if proc.lobe is not None and not proc.ghost:
        # The static background left in: the dynamic removal then divides
        # the lobe too, and the contrast weighs the lobe it leaves against
        # the bands, so both are chosen again with it
        left_in = best(
            (
                replace(proc, static=False, contrast=c, highpass=h * shape[1])
                for c in CONTRAST_GRID[1:]
                for h in HIGHPASS_GRID[1:]
            ),
            "few",
        )
        proc = best((proc, left_in))
    if proc.lobe is not None and proc.contrast and problem.background is not None:
        # The lobe fitted again with the patterns' mean bands divided out
        # of the background: on one crystal they are every pattern's, and
        # the fit took them for the lobe (a Si single crystal, 100 um at
        # 20,000 counts/px: pcx 5.4e-4 off from the truth; with a flat
        # lobe, 2e-5)
        mean = ori.standardise(s0).mean(axis=0).reshape(shape)
        for _ in range(2):
            bands = np.clip(1 + proc.contrast * mean, 0.1, None)
            proc = replace(proc, lobe=_fit_lobe(problem.background / bands))
            proc = best(replace(proc, contrast=c) for c in CONTRAST_GRID[1:])
    return proc
