"""Check the shipped iron master patterns against each other and the package's conventions.

For each iron phase, patterns projected by kikuchipy from ebsdsim's master
pattern (``kind="dynamical"``) and de-ebsd's (``kind="de-ebsd"``) at the
same random orientations, correlated pattern by pattern (as
``data/README.md`` reports for BaTiO3 and Ni): clean and after a 1 px blur
of both. Conventions:

- hemispheres: both phases here are centrosymmetric, so the north and
  south hemispheres must agree (and the square's edges, the equator,
  always);
- the lattice frame: for the tetragonal martensite the c axis must be the
  crystal z of both files. Rotating one simulator's crystal by 90 deg
  about x (c to y) must lower the correlation with the other's, by as much
  as the tetragonality shows;
- the hard pair: how alike ferrite's and martensite's patterns are at the
  same orientation, in each simulator (what a phase decision must resolve),
  against the two simulators' agreement on one phase.

Usage::

    python benchmarks/check_master_patterns.py --n 40 --size 120
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
from kikuchipy.detectors import EBSDDetector
from orix.quaternion import Rotation
from scipy.ndimage import gaussian_filter

from kikuchipy_geomdic.validation import master_patterns

PHASES = ("Fe_bcc", "Fe_fcc", "Fe_bct")


def patterns(mp, rot, det) -> np.ndarray:
    out = mp.get_patterns(rot, det, energy=20, compute=True, show_progressbar=False)
    return np.asarray(out, dtype=np.float64)


def ncc(a, b, blur=0.0) -> np.ndarray:
    """Per-pattern normalised cross-correlation of two stacks."""
    if blur:
        a = gaussian_filter(a, (0, blur, blur))
        b = gaussian_filter(b, (0, blur, blur))
    a = a - a.mean(axis=(1, 2), keepdims=True)
    b = b - b.mean(axis=(1, 2), keepdims=True)
    return (a * b).sum(axis=(1, 2)) / np.sqrt((a * a).sum(axis=(1, 2)) * (b * b).sum(axis=(1, 2)))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=40, help="random orientations")
    p.add_argument("--size", type=int, default=120, help="pattern side (px)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    q = np.random.default_rng(args.seed).normal(size=(args.n, 4))
    rot = Rotation(q / np.linalg.norm(q, axis=1, keepdims=True))
    det = EBSDDetector((args.size, args.size), pc=(0.5, 0.3, 0.6), sample_tilt=70)
    sim = {}
    for name in PHASES:
        a = master_patterns.master_pattern(name, kind="dynamical")
        b = master_patterns.master_pattern(name, kind="de-ebsd")
        for label, mp in (("ebsdsim", a), ("de-ebsd", b)):
            north, south = mp.data
            edges = all(
                np.array_equal(north[e], south[e])
                for e in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1])
            )
            r_ns = np.corrcoef(north.ravel(), south.ravel())[0, 1]
            print(
                f"{name} {label:<8s} {mp.data.shape[1]} x {mp.data.shape[2]}: north-south "
                f"correlation {r_ns:.6f}, equator edges equal {edges}"
            )
        sim[name] = (patterns(a, rot, det), patterns(b, rot, det))
        r, rb = ncc(*sim[name]), ncc(*sim[name], blur=1.0)
        print(
            f"{name} ebsdsim vs de-ebsd, {args.n} orientations, {args.size} px: NCC mean "
            f"{r.mean():.3f} (min {r.min():.3f}); blurred 1 px {rb.mean():.3f}"
        )
    # The c axis: de-ebsd's crystal turned 90 deg about x (c to y)
    turn = Rotation.from_axes_angles([1, 0, 0], np.pi / 2)
    b = master_patterns.master_pattern("Fe_bct", kind="de-ebsd")
    turned = patterns(b, turn * rot, det)  # a crystal-frame operator acts on the left
    print(
        f"Fe_bct c axis: ebsdsim vs de-ebsd same frame {ncc(*sim['Fe_bct']).mean():.4f}, "
        f"de-ebsd's c turned to y {ncc(sim['Fe_bct'][0], turned).mean():.4f}"
    )
    for i, label in enumerate(("ebsdsim", "de-ebsd")):
        r = ncc(sim["Fe_bcc"][i], sim["Fe_bct"][i])
        print(
            f"hard pair in {label}: ferrite vs martensite at the same orientation NCC mean "
            f"{r.mean():.4f} (min {r.min():.4f})"
        )


if __name__ == "__main__":
    main()
