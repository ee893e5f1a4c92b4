"""The ``demo`` command: calibrate a synthetic silicon map with a known,
perturbed geometry and print the recovered values against the truth.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse
import time

#: A calibration point whose DIC residual exceeds this many times the
#: median failed (its start orientation is far off); the demo reports it.
FAILED_POINT_FACTOR = 5


def _demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import numpy as np

    from kikuchipy_geomdic.geometry import rotation_vectors
    from kikuchipy_geomdic.geometry.maps import flat_index
    from kikuchipy_geomdic.validation import synthetic
    from kikuchipy_geomdic.validation.camera import Camera

    dose = None if args.paper or not args.dose else args.dose
    start = "centred" if args.paper else "indexed"
    error = 0.3 if args.paper else 1.0
    t0 = time.perf_counter()
    # A user's map is recorded by a camera and processed (background lobe,
    # blur, shot noise, static and dynamic background removal); the
    # paper's study is noise-free
    noise = dict(camera=Camera(dose=dose)) if dose else {}
    sm = synthetic.synthetic_map(
        "Si",
        navigation_shape=(args.rows, args.cols),
        orientations="random",
        shape=(args.size, args.size),
        orientation_error=error,
        start=start,
        seed=args.seed,
        **noise,
    )
    how = (
        "orientations = truth with a zero-mean 0.3 deg scatter (the paper's study), "
        "orientation_prior 0.3 deg"
        if args.paper
        else "orientations indexed by kikuchipy at that geometry (as a user has them), "
        "no orientation prior"
    )
    print(
        f"Synthetic silicon map: {args.rows} x {args.cols} patterns of {args.size} x "
        f"{args.size} px over {sm.geometry.step_sizes[1] * (args.cols - 1):.0f} um "
        f"({sm.master_pattern.metadata.General.title}, "
        f"{f'camera patterns, {dose:g} counts/px, backgrounds removed' if dose else 'noise-free'}"
        "), made in "
        f"{time.perf_counter() - t0:.1f} s.\nStart: true geometry plus a known "
        f"perturbation; {how}."
    )
    t1 = time.perf_counter()
    from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic

    res = refine_geometry_dic(
        *sm.start_inputs,
        points=args.points,
        orientation_prior=synthetic.centred_prior(error) if args.paper else None,
        seed=args.seed,
        show_progressbar=True,
    )
    t_ref = time.perf_counter() - t1
    print(res.table(sm.geometry))
    if res.undetermined:
        print(
            f"Poorly determined by this map: {', '.join(res.undetermined)} (standard "
            "errors above DETERMINACY_LIMITS): they leave their start only by a significant "
            "step. A wider field of view, more points or an orientation prior determine them "
            "better."
        )
    idx = flat_index(res.points, sm.geometry.navigation_shape)
    truth = sm.xmap.rotations[idx]
    # A start the indexing got wrong is a failed point, not a precision
    rms = res.xmap.prop["dic_rms"]
    ok = rms <= FAILED_POINT_FACTOR * np.median(rms)
    for label, rot in (("start", sm.start_xmap.rotations[idx]), ("after", res.xmap.rotations)):
        dev = rotation_vectors(~truth[ok] * rot[ok])
        absolute = np.rad2deg(np.linalg.norm(dev, axis=1)).mean()
        relative = np.rad2deg(np.linalg.norm(dev - dev.mean(axis=0), axis=1)).mean()
        print(
            f"Mean misorientation to the truth, {label}: {absolute:.4f} deg, "
            f"{relative:.4f} deg with the common rotation removed"
        )
    if not ok.all():
        print(
            f"({(~ok).sum()} point(s) left out above: their DIC residual is over "
            f"{FAILED_POINT_FACTOR}x the median, a start the indexing got wrong.)"
        )
    pc = np.abs(res.detector.pc - sm.detector.pc).max()
    pc0 = np.abs(sm.start_detector.pc - sm.detector.pc).max()
    print(f"Largest PC error on the map: {pc0:.2e} at the start, {pc:.2e} after.")
    print(
        f"Refinement: {len(res.history)} steps in {t_ref:.1f} s (converged: {res.converged}, "
        f"DIC backend: {res.field_after.backend})."
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pattern = sm.signal.inav[0, 0].data
    res.plot_displacement(pattern=pattern).savefig(out / "displacement_fields.png", dpi=120)
    res.plot_convergence().savefig(out / "convergence.png", dpi=120)
    res.plot_sensitivity(pattern=pattern).savefig(out / "sensitivity.png", dpi=120)
    res.plot_coupling().savefig(out / "coupling.png", dpi=120)
    print(f"Figures written to {out}/")
    return 0


def _demo_parser(sub) -> None:
    """The ``demo`` command's options."""
    demo = sub.add_parser(
        "demo",
        help="calibrate a synthetic silicon map with a known, perturbed geometry",
        description=(
            "Simulate a silicon map with a known geometry, start from a perturbed "
            "one with orientations indexed at it, calibrate, and print start, "
            "refined and true values with standard errors."
        ),
    )
    demo.add_argument("--rows", type=int, default=10, help="map rows (default 10)")
    demo.add_argument("--cols", type=int, default=10, help="map columns (default 10)")
    demo.add_argument("--size", type=int, default=120, help="pattern side in px (default 120)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--points", type=int, default=100, help="calibration points (default 100)")
    demo.add_argument(
        "--dose",
        type=float,
        default=150,
        help="mean counts per pixel of the camera patterns (background lobe, blur, shot "
        "noise, static and dynamic background removal; default 150; 0: noise-free, "
        "unprocessed)",
    )
    demo.add_argument(
        "--paper",
        action="store_true",
        help="the paper's idealised start instead: noise-free, orientations = truth "
        "with zero-mean scatter, and the matching orientation prior",
    )
    demo.add_argument(
        "--out", default="geomdic-demo", help="folder for the figures (default geomdic-demo)"
    )
    demo.set_defaults(func=_demo)
