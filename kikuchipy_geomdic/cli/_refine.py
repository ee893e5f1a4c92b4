"""The ``refine`` command: calibrate the geometry of a measured map and
write the calibrated detector in every PC convention, the summary, the
history and the diagnostic figures.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from kikuchipy_geomdic.calibration.refinement import LATTICE_TOLERANCE
from kikuchipy_geomdic.cli._load import (
    _check_detector,
    _check_pseudo_symmetry,
    _load_map,
    _pseudo_symmetry,
    start_detector,
)
from kikuchipy_geomdic.cli._output import _inputs, _one_or_list, _Staging
from kikuchipy_geomdic.cli._parser import _command_output, _fraction, _positive_int
from kikuchipy_geomdic.cli._run import CLIError, _run_on_map, _warn

#: Files ``refine`` writes, in the order they are moved into place (the
#: summary last: its presence marks a complete run).
REFINE_OUTPUTS = (
    "detector.txt",
    "detector_tsl.txt",
    "detector_oxford.txt",
    "detector_emsoft4.txt",
    "detector_emsoft5.txt",
    "history.csv",
    "displacement_fields.png",
    "convergence.png",
    "sensitivity.png",
    "coupling.png",
    "summary.json",
)


def _calibration_points(signal, xmap, phase_ids: Sequence[int], n: int):
    """About *n* usable points of the phases *phase_ids* spread over the
    map, without NaN or blank patterns (each candidate pattern is read once)."""
    import numpy as np

    from kikuchipy_geomdic.calibration.refinement import calibration_points
    from kikuchipy_geomdic.geometry.maps import flat_index, navigation_shape, usable_points

    nav = navigation_shape(signal)
    usable = np.any([usable_points(xmap, i) for i in phase_ids], axis=0).reshape(nav)
    data = signal.data
    flat = data.reshape((-1,) + tuple(data.shape[-2:]))
    n_blank = 0
    pts = np.zeros((0, 2), dtype=int)
    for _ in range(50):
        pts = calibration_points(nav, n, usable)
        if not len(pts):
            break
        sel = flat[flat_index(pts, nav)]
        sel = np.asarray(sel.compute() if hasattr(sel, "compute") else sel, dtype=np.float32)
        finite = np.isfinite(sel).all(axis=(1, 2))
        ok = finite.copy()
        ok[finite] = sel[finite].std(axis=(1, 2)) > 0
        if ok.all():
            break
        n_blank += int((~ok).sum())
        usable[pts[~ok, 0], pts[~ok, 1]] = False
    return pts, int(usable.sum()), n_blank


def _history_csv(history: list[dict], names: Sequence[str]) -> str:
    from kikuchipy_geomdic.io.files import csv_text

    cols = [
        "iteration",
        "accepted",
        "damping",
        "ncc_before",
        "ncc_after",
        "displacement_before",
        "displacement_after",
    ]
    # accepted as 1 or 0, which every CSV reader takes for a number
    rows = (
        [
            *(int(h[c]) if c == "accepted" else h[c] for c in cols),
            *(h["parameters"][n] for n in names),
        ]
        for h in history
    )
    return csv_text([*cols, *names], rows)


def _refine(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
    from kikuchipy_geomdic.geometry.maps import flat_index, navigation_shape
    from kikuchipy_geomdic.io import conventions as cv
    from kikuchipy_geomdic.io import summary as su

    staging = _Staging(args.out, REFINE_OUTPUTS, args.overwrite)
    say = (lambda *a: None) if args.quiet else print
    ops = _pseudo_symmetry(args)
    signal, xmap, mp, phases = _load_map(args)
    one = phases[0].master_pattern if len(phases) == 1 else None
    if one is not None:
        _check_pseudo_symmetry(ops, one)
    det = start_detector(signal, args)
    _check_detector(det, signal)
    ids = [p.phase_id for p in phases]
    pts, n_usable, n_blank = _calibration_points(signal, xmap, ids, args.points)
    if n_blank:
        _warn(f"{n_blank} calibration candidate pattern(s) hold NaN or are blank: skipped")
    if len(pts) < args.points:
        _warn(
            f"only {len(pts)} usable point(s) for the {args.points} requested (points not "
            "indexed, with invalid rotations, of another phase or with NaN or blank "
            f"patterns are excluded): calibrating with {len(pts)}"
        )
    if not len(pts):
        raise CLIError("no usable calibration point in the map")
    nav = navigation_shape(signal)
    say(
        f"Calibrating the geometry of {str(args.patterns)!r}: map {nav}, patterns "
        f"{tuple(det.shape)} px, {', '.join(p.name for p in phases)}, {args.energy:g} kV, "
        f"{len(pts)} points"
    )
    res, seconds = _run_on_map(
        refine_geometry_dic,
        args,
        (signal, xmap, det, mp),
        parameters=args.parameters,
        points=pts,
        solver=args.solver,
        full_field=False if args.dic_only else None,
        lattice_tolerance=args.lattice_tolerance,
        orientation_prior=args.orientation_prior,
        orientation_model=args.orientation_model,
        rois=tuple(args.rois),
        max_iterations=args.max_iterations,
        phase=ids[0] if one is not None else None,
        seed=args.seed,
        pseudo_symmetry_ops=ops,
    )
    summary = su.summary_from_result(
        res,
        **_inputs(
            args,
            signal,
            mp,
            phase=_one_or_list([p.name for p in phases]),
            pseudo_symmetry=args.pseudo_symmetry,
            points_requested=args.points,
            seconds=round(seconds, 3),
        ),
    )
    if one is None:
        summary["calibration"]["points_per_phase"] = res.points_per_phase
    flat = signal.data.reshape((-1,) + tuple(signal.data.shape[-2:]))
    pattern = flat[int(flat_index(res.points[0], res.geometry.navigation_shape))]
    pattern = np.asarray(pattern.compute() if hasattr(pattern, "compute") else pattern)

    with staging as st:
        cv.save_detector(res.detector, st.path("detector.txt"), "bruker")
        for conv in ("tsl", "oxford", "emsoft4", "emsoft5"):
            cv.save_detector(res.detector, st.path(f"detector_{conv}.txt"), conv)
        st.path("history.csv").write_text(_history_csv(res.history, res.parameter_names))
        figures = {
            "displacement_fields.png": lambda: res.plot_displacement(pattern=pattern),
            "convergence.png": res.plot_convergence,
            "sensitivity.png": lambda: res.plot_sensitivity(pattern=pattern),
            "coupling.png": res.plot_coupling,
        }
        for name, make in figures.items():
            fig = make()
            fig.savefig(st.path(name), dpi=120)
            plt.close(fig)
        su.write_summary(summary, st.path("summary.json"))
        st.commit()
    say(su.format_summary(summary))
    cal = summary["calibration"]
    say(
        f"{cal['iterations']} iteration(s) in {seconds:.1f} s (converged: "
        f"{summary['converged']}); mean NCC {cal['mean_ncc']:.4f} over {cal['points']} points."
    )
    if one is None:
        say("Points per phase: " + ", ".join(f"{k} {v}" for k, v in res.points_per_phase.items()))
    say(f"Results written to {str(staging.out)!r}: {', '.join(REFINE_OUTPUTS)}")
    return 0


def _refine_parser(sub, common: argparse.ArgumentParser) -> None:
    """The ``refine`` command's options."""
    from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, PARAMETERS

    refine = sub.add_parser(
        "refine",
        parents=[common],
        help="calibrate the sample-detector geometry of a map",
        description=(
            "Calibrate PC, detector tilt, azimuthal and sample tilt of an EBSD map by "
            "global DIC. Writes to --out: the calibrated detector in kikuchipy's text "
            "format (detector.txt, Bruker; detector_<convention>.txt for tsl, oxford, "
            "emsoft4 and emsoft5), summary.json (the geometry in every PC convention, "
            "the angles, versions), history.csv and four diagnostic figures."
        ),
        epilog=(
            "example: kikuchipy-geomdic refine map.h5 --orientations map.ang "
            "--master-pattern Si --energy 20 --pc 0.51 0.27 0.62 --px-size 70 "
            "--binning 8 --out calibration"
        ),
    )
    refine.add_argument(
        "--parameters",
        nargs="+",
        choices=PARAMETERS,
        default=list(DEFAULT_PARAMETERS),
        metavar="NAME",
        help=f"parameters to refine (default: {' '.join(DEFAULT_PARAMETERS)}; "
        f"choices: {' '.join(PARAMETERS)})",
    )
    refine.add_argument(
        "--solver",
        choices=("joint", "paper"),
        default="joint",
        help="joint: geometry and one rotation per point from every pattern's field "
        "(default); paper: the paper's averaged-field loop",
    )
    refine.add_argument(
        "--dic-only",
        action="store_true",
        help="skip the full-field stage (Gauss-Newton on the intensities) after the DIC "
        "stage: for a master pattern from another simulator than the one that "
        "describes the patterns, whose intensities differ more than its band positions",
    )
    refine.add_argument(
        "--lattice-tolerance",
        type=_fraction,
        default=LATTICE_TOLERANCE,
        metavar="F",
        help="how far c/a may be from the CIF's, as a fraction: a tetragonal, hexagonal "
        f"or trigonal crystal's c/a is fitted with the geometry (default {LATTICE_TOLERANCE:g}; "
        "0 holds the CIF's)",
    )
    refine.add_argument(
        "--orientation-prior",
        type=float,
        default=None,
        metavar="DEG",
        help="RMS error of the starting orientations, believed independent and "
        "zero-mean (default: none; the angles are then measured from the PC field only)",
    )
    refine.add_argument(
        "--orientation-model",
        choices=("free", "crystal", "auto"),
        default="auto",
        help="free: a rotation per point; crystal: the map is one crystal (a wafer, a domain "
        "map), one parent orientation in each point's variant with a small scatter "
        "(--orientation-prior, default 0.1 deg); auto (default): crystal where 70 %% of the "
        "starting orientations are one crystal, else free",
    )
    refine.add_argument(
        "--points",
        type=_positive_int,
        default=100,
        metavar="N",
        help="calibration points spread over the map (default 100)",
    )
    refine.add_argument(
        "--max-iterations",
        type=_positive_int,
        default=10,
        metavar="N",
        help="upper bound on geometry updates (default 10)",
    )
    refine.add_argument(
        "--rois",
        type=_positive_int,
        nargs=2,
        default=[8, 8],
        metavar=("ROWS", "COLS"),
        help="ROI grid of the displacement field (default 8 8)",
    )
    refine.add_argument("--seed", type=int, default=0, help="seed of the DIC noise (default 0)")
    _command_output(refine, "refine", _refine)
