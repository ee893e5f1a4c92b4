"""The ``kikuchipy-geomdic`` command line."""

from __future__ import annotations

import argparse
import sys
import time

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    from kikuchipy_geomdic import synthetic
    from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, UNITS

    t0 = time.perf_counter()
    sm = synthetic.synthetic_map(
        "Si",
        navigation_shape=(args.rows, args.cols),
        orientations="random",
        shape=(args.size, args.size),
        seed=args.seed,
    )
    print(
        f"Synthetic silicon map: {args.rows} x {args.cols} patterns of "
        f"{args.size} x {args.size} px ({sm.master_pattern.metadata.General.title}), "
        f"simulated in {time.perf_counter() - t0:.1f} s"
    )
    true = sm.geometry.as_dict()
    start = sm.start_geometry.as_dict()
    print(f"{'parameter':<12} {'start':>10} {'true':>10}  unit")
    for name in DEFAULT_PARAMETERS:
        print(f"{name:<12} {start[name]:>10.4f} {true[name]:>10.4f}  {UNITS[name]}")
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kikuchipy-geomdic",
        description="Global DIC-based EBSD sample-detector geometry calibration.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="calibrate a synthetic silicon map with a known, perturbed geometry",
        description=(
            "Simulate a silicon map with a known geometry, start from a perturbed "
            "one, and print the start and true values."
        ),
    )
    demo.add_argument("--rows", type=int, default=10, help="map rows (default 10)")
    demo.add_argument("--cols", type=int, default=10, help="map columns (default 10)")
    demo.add_argument("--size", type=int, default=120, help="pattern side in px (default 120)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code."""
    args = _parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
