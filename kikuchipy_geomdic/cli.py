"""The ``kikuchipy-geomdic`` command line."""

from __future__ import annotations

import argparse
import sys
import time

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import numpy as np

    from kikuchipy_geomdic import synthetic
    from kikuchipy_geomdic.refinement import refine_geometry_dic

    t0 = time.perf_counter()
    sm = synthetic.synthetic_map(
        "Si",
        navigation_shape=(args.rows, args.cols),
        orientations="random",
        shape=(args.size, args.size),
        dose=args.dose,
        blur=0.5 if args.dose else 0.0,
        seed=args.seed,
    )
    print(
        f"Synthetic silicon map: {args.rows} x {args.cols} patterns of {args.size} x "
        f"{args.size} px ({sm.master_pattern.metadata.General.title}"
        f"{f', {args.dose:g} counts/px' if args.dose else ', noise-free'}), "
        f"simulated in {time.perf_counter() - t0:.1f} s. Start: true geometry plus a "
        "known perturbation, orientations with 0.3 deg scatter."
    )
    t1 = time.perf_counter()
    res = refine_geometry_dic(
        sm.signal,
        sm.start_xmap,
        sm.start_detector,
        sm.master_pattern,
        sm.energy,
        points=args.points,
        seed=args.seed,
        show_progressbar=True,
    )
    t_ref = time.perf_counter() - t1
    print(_table(sm, res))
    nav = sm.geometry.navigation_shape
    idx = res.points[:, 0] * nav[1] + res.points[:, 1]
    mis0 = np.rad2deg((sm.start_xmap.rotations[idx] * ~sm.xmap.rotations[idx]).angle)
    mis = np.rad2deg((res.xmap.rotations * ~sm.xmap.rotations[idx]).angle)
    print(
        f"Mean misorientation to the true orientations: {mis0.mean():.3f} deg at the "
        f"start, {mis.mean():.4f} deg after ({len(res.points)} points, mean NCC "
        f"{res.xmap.scores.mean():.4f})."
    )
    if res.degenerate:
        combos = ", ".join(" ".join(f"{c:+.2f} {n}" for n, c in d.items()) for d in res.degenerate)
        print(
            f"Not determined by the data (minimum-norm split): {combos}; "
            "tilt - sample_tilt is."
        )
    print(f"Refinement: {len(res.history)} steps in {t_ref:.1f} s (converged: {res.converged}).")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pattern = sm.signal.inav[0, 0].data
    res.plot_displacement(pattern=pattern).savefig(out / "displacement_fields.png", dpi=120)
    res.plot_convergence().savefig(out / "convergence.png", dpi=120)
    res.plot_sensitivity(pattern=pattern).savefig(out / "sensitivity.png", dpi=120)
    res.plot_coupling().savefig(out / "coupling.png", dpi=120)
    print(f"Figures written to {out}/")
    return 0


def _table(sm, res) -> str:
    from kikuchipy_geomdic.geometry import UNITS

    true = sm.geometry.as_dict()
    start = sm.start_geometry.as_dict()
    rows = [f"{'parameter':<13}{'start':>11}{'refined':>11}{'true':>11}{'error':>11}  unit"]
    for name in res.parameter_names:
        unit = "deg" if UNITS[name] == "deg" else "PC"
        d = 4 if unit == "deg" else 6
        r = res.parameters[name]
        rows.append(
            f"{name:<13}{start[name]:>11.{d}f}{r:>11.{d}f}{true[name]:>11.{d}f}"
            f"{r - true[name]:>+11.{d}f}  {unit}"
        )
    if {"tilt", "sample_tilt"} <= set(res.parameter_names):
        comb = {k: v["tilt"] - v["sample_tilt"] for k, v in (("s", start), ("t", true))}
        r = res.parameters["tilt"] - res.parameters["sample_tilt"]
        rows.append(
            f"{'tilt-s_tilt':<13}{comb['s']:>11.4f}{r:>11.4f}{comb['t']:>11.4f}"
            f"{r - comb['t']:>+11.4f}  deg"
        )
    return "\n".join(rows)


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
            "one, calibrate it, and print start, refined and true values."
        ),
    )
    demo.add_argument("--rows", type=int, default=10, help="map rows (default 10)")
    demo.add_argument("--cols", type=int, default=10, help="map columns (default 10)")
    demo.add_argument("--size", type=int, default=120, help="pattern side in px (default 120)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument(
        "--points", type=int, default=100, help="calibration points (default 100)"
    )
    demo.add_argument(
        "--dose", type=float, default=None,
        help="shot noise, mean counts per pixel (default: noise-free)",
    )
    demo.add_argument(
        "--out", default="geomdic-demo", help="folder for the figures (default geomdic-demo)"
    )
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code."""
    args = _parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
