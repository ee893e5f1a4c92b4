"""Benchmark: telling BaTiO3's pseudo-symmetric variants apart.

A BaTiO3 stripe-domain map (``synthetic_map(orientations="stripes")``:
the parent, a 90 deg (+x) and a 180 deg (-z) domain), the start the
parent's variant everywhere, as an indexer that cannot tell the variants
apart returns it, and a starting geometry ``--offset`` off (PC by
``--offset`` in each of pcx, pcy, pcz, tilt 0.5 deg, azimuthal 0.3 deg).
Reindexed with ``reindex(..., pseudo_symmetry_ops=...)`` (this package's
solver: every variant of every point refined, the kept one chosen by
``orientation.compare_variants``).

``picks``
    Against dose: the map calibrated first (``refine_geometry_dic`` with
    the operators, from the start), then reindexed at the calibrated
    detector. Per dose the calibration (largest PC error on the map, each
    PC's error against its standard error) and how often the true variant
    beats its 180 deg partner and its 90 deg ones by NCC (the confidence
    index's pairwise margin ``m_ab`` has the sign of ``NCC_a - NCC_b``:
    the same for both). Per rule the share of points given their true
    variant per domain (base, 180 deg, 90 deg): the confidence index,
    plain NCC (the argmax of ``variant_score_k``) and kikuchipy's
    ``refine_orientation`` with ``pseudo_symmetry_ops`` (best NCC over
    its refined variants; ``--kikuchipy-doses``: where, it is slow); for
    selective use, the smallest value of the rule's confidence measure
    (the cross-variant margin, or the plain NCC gap: best minus
    second-best NCC) above which >= 95 % of the points are right, and the
    share of points it keeps. ``--mismatch`` calibrates and reindexes
    with the coarse ebsdsim master pattern patterns simulated from the
    de-ebsd one.

``detectors``
    The paper's Fig. 7C-D comparison at one dose: reindexed at the
    nominal (start) detector, the DIC-calibrated one, and kikuchipy's
    pattern-wise PC refinement (``refine_orientation_projection_center``
    with the operators, PCs averaged over the points, the start's angles:
    ``comparison.pattern_wise_geometry``) by Nelder-Mead on
    ``--nm-points`` points and by differential evolution on
    ``--de-points`` points with :data:`DE_KWARGS`: largest PC error,
    variant accuracy, mean margin and confidence.

``users``
    Issue 25: starts as users have them (``start="indexed"``: a random
    variant per point, 1 deg scatter, kikuchipy's ``refine_orientation`` at
    the start geometry, ``DEFAULT_PERTURBATION``), realistic patterns
    (``Camera(dose=...)``), 13 x 13 stripe maps of 120 px, data and
    reindex master pattern both de-ebsd. Reindexed with the operators at
    the true detector and at it with 1 and 2 deg of azimuthal or tilt
    error. Per map and detector: share of base (+z), 90 deg (+x) and
    180 deg (-z) points right (the nearest variant of the true parent is
    the true one, and the relative orientation, common rotation removed,
    within 1 deg), and the share with the c axis right (the variant or its
    180 deg partner: what a miss leaves is a polarity error), points wrong
    with ``converged`` = 1 (any and 90 deg), points flagged
    (``converged`` = 0; a variant call within the pattern's noise is one
    reason), the same two with a significance of 3 required, time.
    ``--kikuchipy``: also kikuchipy's ``refine_orientation`` with the
    operators at the true detector, for the speed ratio beside the accuracy.
    ``--oracle``: also reindexed from the true orientations at the true
    detector, the limit the patterns themselves set. ``--calibrate``: also
    calibrated by ``refine_geometry_dic(..., pseudo_symmetry_ops=)`` from
    the start at the start detector (PC errors in standard errors, angles
    kept at the start), then reindexed at the calibrated detector.
    ``--dictionary``: the points a reindex at the true detector leaves
    flagged, dictionary-indexed by kikuchipy (``EBSD.dictionary_indexing``,
    a dictionary over the pseudo-cubic parent's fundamental zone at
    ``--dictionary-resolution`` deg, patterns binned by 2, the map
    centre's PC) and reindexed from there with the operators (neighbour
    reseeding on): the fallback issue 25 asks to measure, as a row
    "true + dictionary" with the dictionary's time.
    ``--no-static``: the user removes only the dynamic background. By
    default the static one is divided out too, with the map's mean as
    kikuchipy users often take it, which on one crystal holds its bands.

Usage::

    python benchmarks/bench_variants.py picks
    python benchmarks/bench_variants.py picks --mismatch --methods geomdic --doses 30 300
    python benchmarks/bench_variants.py detectors
    python benchmarks/bench_variants.py users --seeds 0 1 2 --doses 30 150
    python benchmarks/bench_variants.py users --no-static --calibrate --detectors true
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
import types
import warnings

import numpy as np
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration.refinement import calibration_points, refine_geometry_dic
from kikuchipy_geomdic.geometry import copy_detector
from kikuchipy_geomdic.indexing.reindex import VARIANT_SIGNIFICANCE, reindex
from kikuchipy_geomdic.indexing.variants import VARIANT_NAMES, variant_operators
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.camera import Camera
from kikuchipy_geomdic.validation.comparison import pattern_wise_geometry
from kikuchipy_geomdic.validation.orientations import common_rotation

KINDS = {0: "base", 1: "180 deg", 2: "90 deg"}
#: RMS error (deg) of the starting orientations; the calibration's
#: ``orientation_prior`` matches it (the start is centred)
ORIENTATION_ERROR = 0.3
#: Differential evolution (SciPy) of the ``detectors`` experiment: far
#: fewer generations than SciPy's default, which would take hours
DE_KWARGS = {"seed": 0, "maxiter": 50, "popsize": 15}
_PC = ("pcx", "pcy", "pcz")
DEFAULT_DOSES = [0.3, 1, 3, 10, 30, 100, 300]
T0 = time.perf_counter()


def _map(args, dose, seed):
    off = args.offset
    perturbation = {"pcx": off, "pcy": -off, "pcz": off, "tilt": 0.5, "azimuthal": 0.3}
    return synthetic.synthetic_map(
        "BaTiO3", (args.rows, args.rows), orientations="stripes", shape=(args.size, args.size),
        dose=dose, seed=seed, perturbation=perturbation, orientation_error=ORIENTATION_ERROR,
    )  # fmt: skip


def _quiet():
    stack = contextlib.ExitStack()
    stack.enter_context(contextlib.redirect_stdout(io.StringIO()))
    stack.enter_context(warnings.catch_warnings())
    warnings.simplefilter("ignore")
    return stack


def _calibrate(sm, master_pattern, ops):
    """``refine_geometry_dic`` from the map's start, and its wall time."""
    t0 = time.perf_counter()
    with _quiet():
        res = refine_geometry_dic(
            sm.signal, sm.start_xmap, sm.start_detector, master_pattern, sm.energy,
            pseudo_symmetry_ops=ops, orientation_prior=synthetic.centred_prior(ORIENTATION_ERROR),
            show_progressbar=False,
        )  # fmt: skip
    return res, time.perf_counter() - t0


def _reindex(sm, detector, master_pattern, ops, **kw):
    """``reindex`` of the map's start at *detector*, and its wall time."""
    t0 = time.perf_counter()
    with _quiet():
        out = reindex(
            sm.signal, sm.start_xmap, detector, master_pattern, sm.energy,
            pseudo_symmetry_ops=ops, show_progressbar=False, **kw,
        )  # fmt: skip
    return out, time.perf_counter() - t0


def max_pc_error(detector, sm) -> float:
    """Largest PC error anywhere on the map."""
    return float(np.abs(detector.pc.reshape(-1, 3) - sm.detector.pc.reshape(-1, 3)).max())


def pc_errors_in_sigma(res, sm) -> np.ndarray:
    """Each calibrated PC's error over its standard error, at the
    calibration's reference position (where the standard errors hold)."""
    ref = np.array([res.geometry.reference])
    err = res.geometry.pc_at(ref)[0] - sm.geometry.pc_at(ref)[0]
    return err / np.array([res.standard_errors[k] for k in _PC])


def threshold(confidence: np.ndarray, right: np.ndarray, share: float = 0.95):
    """The smallest *confidence* above which at least *share* of the
    points are right, and the fraction of points it keeps (NaN, 0 if
    none)."""
    for t in np.sort(confidence):
        keep = confidence >= t
        if right[keep].mean() >= share:
            return float(t), float(keep.mean())
    return float("nan"), 0.0


def variant_scores(xmap) -> np.ndarray:
    """The NCC of each variant candidate (N, 6) of a reindexed map."""
    k = len(VARIANT_NAMES)
    return np.stack([xmap.prop[f"variant_score_{i}"] for i in range(k)], axis=1)


def ncc_gap(scores: np.ndarray) -> np.ndarray:
    """Best minus second-best NCC of each point."""
    top = np.sort(scores, axis=1)
    return top[:, -1] - top[:, -2]


def pairwise_right(scores: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """The share of points whose true variant has a higher NCC than its
    180 deg partner, and than every one of its 90 deg ones."""
    n = np.arange(truth.size)
    # VARIANT_NAMES pairs +-z, +-x, +-y: the 180 deg partner flips bit 0
    partner = truth ^ 1
    ninety = np.ones_like(scores, dtype=bool)
    ninety[n, truth] = ninety[n, partner] = False
    own = scores[n, truth]
    vs180 = own > scores[n, partner]
    vs90 = own > np.where(ninety, scores, -np.inf).max(axis=1)
    return float(vs180.mean()), float(vs90.mean())


def _accuracy(variant, truth) -> list[float]:
    right = variant == truth
    return [right[truth == k].mean() for k in KINDS]


def picks(args) -> None:
    ops = variant_operators()[1:]
    mp = master_patterns.master_pattern("BaTiO3", kind="ebsdsim") if args.mismatch else None
    kp_doses = args.doses if args.kikuchipy_doses is None else args.kikuchipy_doses
    cal_rows, rule_rows = [], []
    for dose in args.doses:
        sm = _map(args, dose, args.seed)
        truth = sm.xmap.prop["variant"]
        cal = mp or sm.master_pattern
        res, t_cal = _calibrate(sm, cal, ops)
        out, sec = _reindex(sm, res.detector, cal, ops)
        scores = variant_scores(out)
        nsig = pc_errors_in_sigma(res, sm)
        cal_rows.append(
            (dose, max_pc_error(res.detector, sm), *nsig, *pairwise_right(scores, truth), t_cal)
        )
        rules = {
            "confidence index": (out.variant, out.cross_variant_margin, sec),
            "plain NCC": (scores.argmax(axis=1), ncc_gap(scores), sec),
        }
        if "kikuchipy" in args.methods and dose in kp_doses:
            nm, nm_sec = _reindex(sm, res.detector, cal, ops, method="kikuchipy")
            rules["kikuchipy NM (NCC)"] = (nm.pseudo_symmetry_index, None, nm_sec)
        for name, (v, conf, t) in rules.items():
            t95, kept = (np.nan, np.nan) if conf is None else threshold(conf, v == truth)
            rule_rows.append((dose, name, *_accuracy(v, truth), t95, kept, t))
        print(f"dose {dose:g} done ({time.perf_counter() - T0:.0f} s)", file=sys.stderr)
    print(
        f"{'dose':>6s} {'max PC err':>10s} {'pcx/sig':>8s} {'pcy/sig':>8s} {'pcz/sig':>8s} "
        f"{'NCC>180':>8s} {'NCC>90':>7s} {'cal s':>6s}"
    )
    for d, e, sx, sy, sz, p180, p90, t in cal_rows:
        print(f"{d:6g} {e:10.2e} {sx:+8.2f} {sy:+8.2f} {sz:+8.2f} {p180:8.1%} {p90:7.1%} {t:6.0f}")
    print()
    print(
        f"{'dose':>6s} {'rule':<20s} {'base':>6s} {'180deg':>7s} {'90deg':>6s} "
        f"{'t95':>7s} {'kept':>5s} {'time s':>7s}"
    )
    for d, name, a0, a1, a2, t95, kept, t in rule_rows:
        print(f"{d:6g} {name:<20s} {a0:6.1%} {a1:7.1%} {a2:6.1%} {t95:7.3f} {kept:5.0%} {t:7.1f}")
    n = {k: int((sm.xmap.prop["variant"] == k).sum()) for k in KINDS}
    print(
        f"({args.rows} x {args.rows} map, {args.size} px, points per domain "
        f"{', '.join(f'{KINDS[k]} {v}' for k, v in n.items())}; t95: the cross-variant "
        "margin (confidence index), the best-minus-second NCC gap (plain NCC))"
    )


def detectors(args) -> None:
    ops = variant_operators()[1:]
    sm = _map(args, args.doses[0], args.seed)
    truth = sm.xmap.prop["variant"]
    nav = sm.geometry.navigation_shape
    res, t_dic = _calibrate(sm, sm.master_pattern, ops)
    dets = {
        "nominal": (sm.start_detector, 0.0, "-"),
        "DIC-calibrated": (res.detector, t_dic, f"{len(res.points)}"),
    }
    for method, n, kw in (
        ("nelder-mead", args.nm_points, None),
        ("differential-evolution", args.de_points, DE_KWARGS),
    ):
        t0 = time.perf_counter()
        pw = pattern_wise_geometry(
            sm, calibration_points(nav, n), method, de_kwargs=kw, pseudo_symmetry_ops=ops
        )
        name = {"nelder-mead": "kikuchipy NM avg", "differential-evolution": "kikuchipy DE avg"}
        dets[name[method]] = (pw.geometry.detector(), time.perf_counter() - t0, f"{n}")
        print(f"{method} done", file=sys.stderr)
    print(
        f"{'detector':<17s} {'points':>6s} {'cal s':>6s} {'max PC err':>10s} {'base':>6s} "
        f"{'180deg':>7s} {'90deg':>6s} {'margin':>7s} {'confidence':>10s}"
    )
    for name, (det, t, n) in dets.items():
        out, _ = _reindex(sm, det, sm.master_pattern, ops)
        acc = _accuracy(out.variant, truth)
        print(
            f"{name:<17s} {n:>6s} {t:6.0f} {max_pc_error(det, sm):10.2e} {acc[0]:6.1%} "
            f"{acc[1]:7.1%} {acc[2]:6.1%} {out.cross_variant_margin.mean():7.3f} "
            f"{out.confidence.mean():10.3f}"
        )
    nsig = ", ".join(f"{k} {v:+.2f}" for k, v in zip(_PC, pc_errors_in_sigma(res, sm)))
    print(
        f"({args.rows} x {args.rows} map, {args.size} px, dose {args.doses[0]:g}; DIC PC "
        f"errors / sigma: {nsig}; DE: {DE_KWARGS})"
    )


#: A stricter significance the ``users`` experiment reports beside the default
STRICT_SIGNIFICANCE = 3.0

#: Detector errors of the ``users`` experiment: (name, parameter, degrees)
DETECTOR_ERRORS = (
    ("true", None, 0.0),
    ("azimuthal +1", "azimuthal", 1.0),
    ("azimuthal +2", "azimuthal", 2.0),
    ("tilt +1", "tilt", 1.0),
    ("tilt +2", "tilt", 2.0),
    # The PC off as far as a calibration on one pattern leaves it
    ("pc +1e-3", "pc", (1e-3, -1e-3, 1e-3)),
    ("pc +3e-3", "pc", (2.5e-3, 2e-3, 4e-3)),
    ("pc -3e-3", "pc", (-2.5e-3, -2e-3, 3e-3)),
)


def variant_errors(rotations: Rotation, truth) -> tuple[np.ndarray, np.ndarray]:
    """Per point the absolute variant (the nearest, with the crystal's
    proper symmetry, of the six variants of the point's true parent) and
    the misorientation (deg) to that variant with the map's common rotation
    (over the points in their true variant, within 5 deg) removed: a
    detector angle error is a common rotation of every orientation."""
    ops = variant_operators()
    sym = Rotation(truth.phases[0].point_group.proper_subgroup).flatten()
    v = truth.prop["variant"]
    parent = ~ops[v] * truth.rotations.flatten()
    r = Rotation(rotations).flatten()
    ang, closest = np.empty((r.size, 6)), []
    for k in range(6):
        target = ops[k] * parent
        a = np.stack([(~target * (s * r)).angle for s in sym], axis=1)
        ang[:, k] = np.rad2deg(a.min(axis=1))
        closest.append((sym[np.argmin(a, axis=1)] * r).data)
    label = ang.argmin(axis=1)
    n = np.arange(r.size)
    near = Rotation(np.stack(closest, axis=1)[n, label])
    target = ops[label] * parent
    rel = ang[n, label]
    ok = (label == v) & (rel < 5)
    if ok.sum() >= 3:
        c = common_rotation(near[ok], target[ok])
        common = Rotation.from_axes_angles(c.axis, np.deg2rad(c.angle))
        rel = np.rad2deg((~target * (near * ~common)).angle)
    return label, rel


def _start_error(sm) -> np.ndarray:
    """Angle (deg) of each start from the nearest variant of its truth."""
    label, _ = variant_errors(sm.start_xmap.rotations, sm.xmap)
    ops = variant_operators()
    parent = ~ops[sm.xmap.prop["variant"]] * sm.xmap.rotations.flatten()
    sym = Rotation(sm.xmap.phases[0].point_group.proper_subgroup).flatten()
    r = sm.start_xmap.rotations.flatten()
    target = ops[label] * parent
    return np.rad2deg(np.stack([(~target * (s * r)).angle for s in sym], axis=1).min(axis=1))


def users(args) -> None:
    ops = variant_operators()[1:]
    rows = []
    for dose in args.doses:
        for seed in args.seeds:
            t0 = time.perf_counter()
            with _quiet():
                sm = synthetic.synthetic_map(
                    "BaTiO3", (args.rows, args.rows), orientations="stripes",
                    shape=(args.size, args.size), seed=seed,
                    camera=Camera(dose=dose, static=not args.no_static),
                    start="indexed", orientation_error=1.0,
                )  # fmt: skip
            err = _start_error(sm)
            print(
                f"dose {dose:g} seed {seed}: built in {time.perf_counter() - t0:.0f} s; starts "
                f"{np.median(err):.1f} deg (median) from the nearest variant, "
                f"{np.mean(err > 8.7):.0%} beyond 8.7 deg",
                flush=True,
            )
            cases = [
                (name, _detector_off(sm.detector, p, a), "geomdic", sm.start_xmap)
                for name, p, a in DETECTOR_ERRORS
                if (p != "pc" if args.detectors is None else name in args.detectors)
            ]
            if args.oracle:
                cases.append(("true, from truth", sm.detector, "geomdic", sm.xmap))
            if args.kikuchipy:
                cases.append(("true (kikuchipy)", sm.detector, "kikuchipy", sm.start_xmap))
            if args.calibrate:
                t1 = time.perf_counter()
                with _quiet():
                    res = refine_geometry_dic(
                        sm.signal, sm.start_xmap, sm.start_detector, sm.master_pattern,
                        sm.energy, pseudo_symmetry_ops=ops, show_progressbar=False,
                    )  # fmt: skip
                kept = [
                    n
                    for n in ("tilt", "azimuthal")
                    if abs(res.parameters[n] - getattr(sm.start_detector, n)) < 1e-9
                ]
                print(
                    f"  calibrated in {time.perf_counter() - t1:.0f} s: PC error "
                    f"{np.array2string(pc_errors_in_sigma(res, sm), precision=1)} sigma, "
                    f"largest {max_pc_error(res.detector, sm):.1e}; kept at the start: "
                    f"{', '.join(kept) or 'none'}",
                    flush=True,
                )
                cases.append(("calibrated", res.detector, "geomdic", sm.start_xmap))
            for name, det, method, start in cases:
                t1 = time.perf_counter()
                with _quiet():
                    out = reindex(
                        sm.signal, start, det, sm.master_pattern, sm.energy,
                        pseudo_symmetry_ops=ops, show_progressbar=False, method=method,
                    )  # fmt: skip
                sec = time.perf_counter() - t1
                rows.append((dose, seed, name, *_users_scores(out, sm, method), sec))
                print("  " + _users_line(rows[-1]), flush=True)
                if args.dictionary and name == "true" and method == "geomdic":
                    t1 = time.perf_counter()
                    merged, n_flagged, t_di = _dictionary_fallback(
                        sm, out, ops, args.dictionary_resolution
                    )
                    sec = time.perf_counter() - t1
                    rows.append(
                        (dose, seed, "true + dictionary", *_users_scores(merged, sm, method), sec)
                    )
                    print(
                        f"  {n_flagged} flagged points dictionary-indexed in {t_di:.0f} s, "
                        "then reindexed:\n  " + _users_line(rows[-1]),
                        flush=True,
                    )
    print()
    print(
        f"{'dose':>5s} {'seed':>4s} {'detector':<17s} {'base':>6s} {'90deg':>6s} "
        f"{'180deg':>6s} {'ax base':>7s} {'ax 90':>6s} {'ax 180':>6s} {'wrong+conv':>10s} "
        f"{'ax+conv':>7s} {'flagged':>7s} {'wc(z3)':>6s} {'fl(z3)':>6s} {'rel deg':>7s} "
        f"{'time s':>6s}"
    )
    for row in rows:
        print(_users_line(row))
    print(
        f"({args.rows} x {args.rows} stripe maps, {args.size} px, Camera(dose); right: "
        "nearest variant of the true parent and within 1 deg after the common rotation; "
        "ax: the c axis right (the variant or its 180 deg partner), so a miss is a 90 deg "
        "error, the rest of the misses polarity (180 deg) errors; "
        "rel deg: median relative misorientation of the right points; flagged: converged = 0 "
        f"(variant significance below {VARIANT_SIGNIFICANCE:g} among the reasons); wc(z3), "
        f"fl(z3): the same with a significance of {STRICT_SIGNIFICANCE:g} required; "
        "'from truth': reindexed from the true orientations (the pattern's own limit); "
        "kikuchipy: converged not defined, counted as 1)"
    )


def _dictionary_fallback(sm, out, ops, resolution):
    """The points *out* (a reindex at the true detector) flagged,
    dictionary-indexed by kikuchipy and reindexed from there; returns
    *out* with those points replaced (rotations, ``converged``,
    ``variant_significance``), their number and the dictionary's time."""
    import kikuchipy as kp
    from orix.crystal_map import CrystalMap
    from orix.quaternion.symmetry import Oh
    from orix.sampling import get_sample_fundamental

    flagged = ~out.converged.astype(bool)
    shape = sm.signal.axes_manager.signal_shape[::-1]
    t0 = time.perf_counter()
    data = sm.signal.data.reshape((-1,) + shape)[flagged]
    # Binned by 2: the dictionary's memory and time by 4; a start within a
    # few degrees is all the reindex needs
    binned = data.reshape(-1, shape[0] // 2, 2, shape[1] // 2, 2).mean(axis=(2, 4))
    det = sm.detector
    dict_det = kp.detectors.EBSDDetector(
        shape=binned.shape[1:], pc=det.pc_average, tilt=det.tilt, azimuthal=det.azimuthal,
        sample_tilt=det.sample_tilt, binning=det.binning * 2, px_size=det.px_size,
    )  # fmt: skip
    # The pseudo-cubic parent's zone: every variant is one of the operators
    # away from a dictionary entry, and the reindex tries them all
    rot = get_sample_fundamental(resolution=resolution, point_group=Oh)
    with _quiet(), contextlib.redirect_stderr(io.StringIO()):
        sim = sm.master_pattern.get_patterns(
            rot, dict_det, sm.energy, compute=False, dtype_out=np.float32
        )
        di = kp.signals.EBSD(binned.astype(np.float32)).dictionary_indexing(sim, keep_n=1)
    t_di = time.perf_counter() - t0
    start = sm.start_xmap
    q = start.rotations.data.reshape(-1, 4).copy()
    q[flagged] = di.rotations.data.reshape(-1, 4)
    xm = CrystalMap(
        Rotation(q), phase_id=start.phase_id, x=start.x, y=start.y,
        phase_list=start.phases.deepcopy(), scan_unit=start.scan_unit,
    )  # fmt: skip
    with _quiet():
        again = reindex(
            sm.signal, xm, sm.detector, sm.master_pattern, sm.energy,
            pseudo_symmetry_ops=ops, show_progressbar=False,
            navigation_mask=~flagged.reshape(sm.xmap.shape),
        )  # fmt: skip
    r = out.rotations.data.reshape(-1, 4).copy()
    r[flagged] = again.rotations.data.reshape(-1, 4)[flagged]
    conv = out.converged.copy()
    conv[flagged] = again.converged[flagged]
    sig = out.prop["variant_significance"].copy()
    sig[flagged] = again.prop["variant_significance"][flagged]
    merged = types.SimpleNamespace(
        rotations=Rotation(r), converged=conv, prop={"variant_significance": sig}
    )
    return merged, int(flagged.sum()), t_di


def _detector_off(detector, parameter, change):
    """*detector* with *parameter* off by *change* (degrees, or (3,) for
    the PC; itself if None)."""
    if parameter is None:
        return detector
    return copy_detector(
        detector, **{parameter: getattr(detector, parameter) + np.asarray(change)}
    )


def _users_scores(out, sm, method) -> tuple:
    """Accuracy (exact and c axis, per domain), wrong converged points
    (exact and c axis), flagged points (significance 2.5 and 3) and the
    median relative misorientation of the right points."""
    truth = sm.xmap.prop["variant"]
    label, rel = variant_errors(out.rotations, sm.xmap)
    right = (label == truth) & (rel < 1)
    # VARIANT_NAMES pairs +-z, +-x, +-y: partners share label // 2
    axis = (label // 2 == truth // 2) & (rel < 1)
    conv = out.converged.astype(bool) if method == "geomdic" else np.ones_like(right)
    # Stricter than the default: flagged below a significance of 3 too
    sig = out.prop.get("variant_significance", np.full(right.size, np.inf))
    conv3 = conv & (sig >= STRICT_SIGNIFICANCE)
    acc = [right[truth == k].mean() for k in (0, 2, 1)]
    acc += [axis[truth == k].mean() for k in (0, 2, 1)]
    wrong = (int((~right & conv).sum()), int((~axis & conv).sum()), int((~conv).sum()))
    wrong += (int((~right & conv3).sum()), int((~conv3).sum()))
    return (*acc, *wrong, float(np.median(rel[right])))


def _users_line(row) -> str:
    d, seed, name, a0, a2, a1, x0, x2, x1, wc, wx, fl, wc3, fl3, rel, t = row
    return (
        f"{d:5g} {seed:4d} {name:<17s} {a0:6.1%} {a2:6.1%} {a1:6.1%} {x0:7.1%} {x2:6.1%} "
        f"{x1:6.1%} {wc:10d} {wx:7d} {fl:7d} {wc3:6d} {fl3:6d} {rel:7.3f} {t:6.1f}"
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment", choices=["picks", "detectors", "users"])
    p.add_argument("--rows", type=int, default=15)
    p.add_argument("--size", type=int, default=120)
    p.add_argument("--doses", type=float, nargs="+", default=DEFAULT_DOSES)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="users: seeds")
    p.add_argument("--kikuchipy", action="store_true", help="users: kikuchipy's refiner too")
    p.add_argument(
        "--oracle", action="store_true", help="users: reindexed from the true orientations too"
    )
    p.add_argument(
        "--calibrate", action="store_true",
        help="users: calibrated with the operators from the start, then reindexed there",
    )  # fmt: skip
    p.add_argument(
        "--detectors",
        nargs="+",
        help="users: names of DETECTOR_ERRORS to run (default all but the PC's)",
    )
    p.add_argument(
        "--dictionary", action="store_true",
        help="users: the flagged points of the true detector's reindex dictionary-indexed too",
    )  # fmt: skip
    p.add_argument(
        "--dictionary-resolution", type=float, default=3.0, help="users: its resolution (deg)"
    )
    p.add_argument("--no-static", action="store_true", help="users: no static background removal")
    p.add_argument("--offset", type=float, default=0.03, help="PC offset of the start")
    p.add_argument("--mismatch", action="store_true", help="picks: the ebsdsim pattern")
    p.add_argument("--methods", nargs="+", default=["geomdic", "kikuchipy"])
    p.add_argument(
        "--kikuchipy-doses", type=float, nargs="+", help="picks: doses of kikuchipy (all)"
    )
    p.add_argument("--nm-points", type=int, default=25, help="detectors: Nelder-Mead points")
    p.add_argument("--de-points", type=int, default=6, help="detectors: DE points")
    args = p.parse_args(argv)
    if args.experiment == "detectors" and len(args.doses) > 1:
        args.doses = [100.0]
    print(f"command: {' '.join(sys.argv)}")
    if args.experiment == "users" and args.doses == DEFAULT_DOSES:
        args.doses = [30.0, 150.0]
    if args.experiment == "users" and args.rows == 15:
        args.rows = 13
    {"picks": picks, "detectors": detectors, "users": users}[args.experiment](args)


if __name__ == "__main__":
    main()
