"""Speed and accuracy of the DIC displacement measurement.

For each pattern size and DIC backend: patterns per second of
:func:`kikuchipy_geomdic.patterns.displacement.measure_displacements` under two
Dask schedulers, and the RMS error per ROI against the forward
displacement map (averaged over the same vectors as the measurement), on
noise-free patterns and on "experimental" ones (1 px blur, Poisson noise
at 1000 counts of contrast over 500 of background, 5 % Gaussian noise on
the simulated patterns, ``blur=1``).

"sync" is Dask's synchronous scheduler (OpenCV still runs its own threads
inside LK), "threads" the default threaded one; most of the per-pattern
work is small NumPy operations that hold the GIL, so threads add little.

The geometry change is pcx +0.01, pcy +0.01, pcz -0.01, tilt +0.5 deg,
azimuthal +0.5 deg from PC (0.5, 0.3, 0.6), sample tilt 70 deg: 1-3 % of
the detector width. Patterns are simulated from the dynamical Si master
pattern with random orientations. Default settings (8 x 8 ROIs, LK window
11) at every size: at 60 x 60 px the ROIs hold about one vector each and
window 11 was still the best of 5-11; at 240 x 240 px a window of 21
lowers the noisy error from 0.09 to 0.07 px.

Run::

    python benchmarks/bench_displacement.py [--n 32]
"""

import argparse
import os
import time
import warnings

import dask
import numpy as np
from kikuchipy.detectors import EBSDDetector
from orix.quaternion import Rotation
from scipy import ndimage

from kikuchipy_geomdic.geometry import forward_map
from kikuchipy_geomdic.patterns import displacement as dsp
from kikuchipy_geomdic.patterns.roi import roi_average
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation import master_patterns

PC_A, ANGLES_A = (0.5, 0.3, 0.6), (0.0, 0.0, 70.0, 0.0)
PC_B, ANGLES_B = (0.51, 0.31, 0.59), (0.5, 0.5, 70.0, 0.0)
SIZES = (60, 120, 240)


def detector(shape, pc, angles):
    tilt, azimuthal, sample_tilt, twist = angles
    return EBSDDetector(
        shape=shape,
        pc=pc,
        tilt=tilt,
        azimuthal=azimuthal,
        sample_tilt=sample_tilt,
        twist=twist,
    )


def experimental(patterns, seed=2, psf=1.0, dose=1000):
    rng = np.random.default_rng(seed)
    b = ndimage.gaussian_filter(patterns.astype(np.float64), (0, psf, psf))
    lo = b.min(axis=(1, 2), keepdims=True)
    hi = b.max(axis=(1, 2), keepdims=True)
    return rng.poisson(dose * (0.5 + (b - lo) / (hi - lo))).astype(np.float32)


def rms_error(field, shape):
    """RMS per ROI of measured minus forward-map displacement, averaged
    over the same vectors as the measurement."""
    err = []
    for i, v in enumerate(field.vectors):
        xb, yb = forward_map(v[:, 0], v[:, 1], PC_A, ANGLES_A, PC_B, ANGLES_B, shape)
        truth = np.stack([xb - v[:, 0], yb - v[:, 1]], axis=1)
        u, c, _ = roi_average(v[:, :2], v[:, 2:], shape, field.rois, values=truth)
        err.append((field.u[i] - u)[c > 0])
    err = np.concatenate(err)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def rate(a, b, scheduler, repeats=2, **kw):
    """Patterns per second, best of *repeats*."""
    with dask.config.set(scheduler=scheduler):
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            dsp.measure_displacements(a, b, seed=0, **kw)
            best = min(best, time.perf_counter() - t0)
    return len(a) / best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=32, help="patterns per size")
    args = parser.parse_args()

    mp = master_patterns.master_pattern("Si", kind="dynamical")
    q = np.random.default_rng(0).normal(size=(args.n, 4))
    rot = Rotation(q / np.linalg.norm(q, axis=1, keepdims=True))
    print(f"{args.n} patterns per size, {os.cpu_count()} cores")
    head = (
        f"{'size':>9} {'backend':>8} {'pat/s sync':>10} "
        f"{'pat/s threads':>13} {'RMS clean':>9} {'RMS noisy':>9} "
        f"{'vec/ROI':>7} {'|u| RMS':>7}"
    )
    print(head)
    print("-" * len(head))
    for size in SIZES:
        shape = (size, size)
        a = simulate_patterns(mp, rot, detector(shape, PC_A, ANGLES_A), 20)
        b = simulate_patterns(mp, rot, detector(shape, PC_B, ANGLES_B), 20)
        b_noisy = experimental(b)
        for dic in ("opencv", "skimage"):
            kw = dict(dic=dic)
            dsp.measure_displacements(a[:2], b[:2], seed=0, **kw)  # Warm-up
            one = rate(a, b, "synchronous", **kw)
            threads = rate(a, b, "threads", **kw)
            clean = dsp.measure_displacements(a, b, seed=0, keep_vectors=True, **kw)
            noisy = dsp.measure_displacements(
                a, b_noisy, seed=0, keep_vectors=True, noise=0.05, blur=1.0, **kw
            )
            mag = np.sqrt(np.mean(np.sum(clean.mean**2, axis=1)))
            print(
                f"{size:>4} x{size:>3} {dic:>8} {one:>10.1f} {threads:>13.1f} "
                f"{rms_error(clean, shape):>9.3f} {rms_error(noisy, shape):>9.3f} "
                f"{clean.counts.mean():>7.1f} {mag:>7.2f}"
            )


if __name__ == "__main__":
    # The two-pattern warm-up at 60 x 60 px leaves some ROIs empty
    warnings.simplefilter("ignore", UserWarning)
    main()
