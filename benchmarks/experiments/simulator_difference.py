"""Instrument check (not the package's behaviour): is the difference between
the two BaTiO3 simulators a tone curve or a blur, which a calibration could
model away?

The envelope's domain maps are simulated from ebsdsim's master pattern and
calibrated with de-ebsd's; where they miss PC <= 3e-4 they miss it without
noise too, and not with de-ebsd's own data (benchmarks section 8). Here the
same orientations are projected from both master patterns at the base and
pc-high cells' geometries, and the share of one pattern's variance that the
other explains is printed for: a gain and offset (what the calibration
fits), a quadratic and a cubic in the intensity (a tone curve), and a
Gaussian blur of either pattern before the gain and offset.

Usage::

    python benchmarks/experiments/simulator_difference.py --seed 0 --n 6
"""

from __future__ import annotations

import argparse

import numpy as np
from kikuchipy.detectors import EBSDDetector
from scipy.ndimage import gaussian_filter

from kikuchipy_geomdic.validation import master_patterns
from kikuchipy_geomdic.validation.orientations import _random_rotations

GEOMETRIES = {"base": (0.50, 0.20, 0.70), "pc-high": (0.55, 0.30, 0.90)}
BLURS = (0.3, 0.6, 1.0)


def _explained(x: np.ndarray, y: np.ndarray, degree: int = 1) -> float:
    """Share of the variance of *y* a polynomial of *degree* in *x* explains."""
    z = (x - x.mean()) / x.std()
    basis = np.stack([z**k for k in range(degree + 1)], axis=1)
    coefficients, *_ = np.linalg.lstsq(basis, y, rcond=None)
    return 1 - (y - basis @ coefficients).var() / y.var()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n", type=int, default=6, help="random orientations")
    ap.add_argument("--px", type=int, default=120)
    args = ap.parse_args(argv)
    calibrated = master_patterns.master_pattern("BaTiO3", kind="dynamical")
    data = master_patterns.master_pattern("BaTiO3", kind="ebsdsim")
    rotations = _random_rotations(args.n, np.random.default_rng(args.seed))
    print(
        "share of the data pattern's (ebsdsim) variance explained by the calibration's "
        "(de-ebsd): gain+offset | quadratic | cubic | "
        + " | ".join(
            f"blur {b} px: of de-ebsd explaining ebsdsim / of ebsdsim explaining de-ebsd"
            for b in BLURS
        )
    )
    for cell, pc in GEOMETRIES.items():
        detector = EBSDDetector(
            shape=(args.px, args.px),
            pc=pc,
            tilt=5.0,
            sample_tilt=70.0,
            px_size=70.0 * 480 / args.px,
        )
        kw = dict(energy=20, compute=True, dtype_out="float64", show_progressbar=False)
        model = calibrated.get_patterns(rotations, detector, **kw).data
        patterns = data.get_patterns(rotations, detector, **kw).data
        for i, (m, p) in enumerate(zip(model, patterns)):
            tone = [_explained(m.ravel(), p.ravel(), d) for d in (1, 2, 3)]
            blur = [
                (
                    _explained(gaussian_filter(m, b).ravel(), p.ravel()),
                    _explained(gaussian_filter(p, b).ravel(), m.ravel()),
                )
                for b in BLURS
            ]
            print(
                f"{cell:8} orientation {i}: "
                + " | ".join(f"{t:.4f}" for t in tone)
                + " | "
                + " | ".join(f"{a:.4f} / {b:.4f}" for a, b in blur)
            )


if __name__ == "__main__":
    main()
