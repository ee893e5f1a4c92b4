"""Side-by-side comparison of DIC geometry refinement with kikuchipy's
pattern-wise PC refinement, scored against the truth.

:func:`compare_methods` runs :func:`~kikuchipy_geomdic.refine_geometry_dic`
and kikuchipy's pattern-wise
:meth:`~kikuchipy.signals.EBSD.refine_orientation_projection_center`
(Nelder-Mead and differential evolution, PCs then averaged over the
points, as the paper did in section 3.1) on the same synthetic map
(:mod:`kikuchipy_geomdic.validation.synthetic`) and start, and reports wall time and
errors against the truth side by side. Errors are scored as in
:mod:`kikuchipy_geomdic.validation.study`: PCs at the map centre, and
``err_tilt_difference`` as the meaningful angle error of a tilt and sample
tilt that only count through their difference.

Layer 7 (validation): may import every layer below it.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration.refinement import calibration_points, refine_geometry_dic
from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.geometry.maps import flat_index
from kikuchipy_geomdic.indexing.reindex import quiet, refine_orientations, stack_signal
from kikuchipy_geomdic.validation import synthetic
from kikuchipy_geomdic.validation.scores import (
    _PC,
    _disorientation_from_mean,
    _geometry_errors,
    _misorientation,
)

__all__ = ["PatternWise", "compare_methods", "pattern_wise_geometry"]

#: The paper's trust region of kikuchipy's pattern-wise refinement: 3
#: Euler angles (deg), 3 PC fractions
TRUST_REGION = (3, 3, 3, 0.05, 0.05, 0.05)


def _pattern_wise(
    experimental,
    start_rot,
    phase,
    start_geo,
    points,
    master_pattern,
    energy,
    method,
    method_kwargs,
    trust_region,
    pseudo_symmetry_ops=None,
):
    """kikuchipy's pattern-wise orientation and PC refinement of the points."""
    signal, xmap = stack_signal(experimental, start_rot, phase)
    with quiet(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return signal.refine_orientation_projection_center(
            xmap,
            start_geo.detector(points),
            master_pattern,
            energy,
            pseudo_symmetry_ops=pseudo_symmetry_ops,
            method=method,
            method_kwargs=dict(method_kwargs or {}),
            trust_region=trust_region,
        )


def _point_patterns(sm: synthetic.SyntheticMap, flat: np.ndarray) -> np.ndarray:
    """The patterns (N, rows, columns) of the map's points *flat*."""
    data = sm.signal.data
    if hasattr(data, "compute"):
        data = data.compute()
    nav = sm.geometry.navigation_shape
    data = np.asarray(data).reshape((nav[0] * nav[1],) + tuple(sm.geometry.shape))
    return data[flat].astype(np.float32)


class PatternWise(NamedTuple):
    """What :func:`pattern_wise_geometry` returns."""

    #: The start geometry with its PC replaced by the points' mean PC, at
    #: their mean position (angles unchanged)
    geometry: MapGeometry
    #: Orientations refined with the PCs (of the points, in their order)
    xmap: CrystalMap
    #: Pattern-wise PCs (N, 3)
    pcs: np.ndarray


def pattern_wise_geometry(
    sm: synthetic.SyntheticMap,
    points: np.ndarray,
    method: str = "nelder-mead",
    trust_region: Sequence[float] = TRUST_REGION,
    de_kwargs: Mapping[str, Any] | None = None,
    pseudo_symmetry_ops: Rotation | None = None,
    patterns: np.ndarray | None = None,
) -> PatternWise:
    """Calibrate a map's PC as the paper's section 3.1 did with kikuchipy.

    kikuchipy's
    :meth:`~kikuchipy.signals.EBSD.refine_orientation_projection_center`
    refines orientation and PC of each point from the map's start; the
    PCs are then averaged over the points. These methods cannot refine
    the detector angles: the start's stay.

    Parameters
    ----------
    sm
        Synthetic map (:func:`~kikuchipy_geomdic.validation.synthetic.synthetic_map`).
    points
        Points (N, 2) as (row, column).
    method
        "nelder-mead" or "differential-evolution".
    trust_region
        kikuchipy trust region (3 Euler angles in deg, 3 PC fractions;
        the bounds of differential evolution).
    de_kwargs
        ``method_kwargs`` of differential evolution (SciPy); default
        ``{"seed": 0}``.
    pseudo_symmetry_ops
        Passed to kikuchipy: each point's variants are refined too and the
        best NCC kept, with its PC.
    patterns
        The points' patterns (N, rows, columns), if already read from the
        map; default: read here.

    Returns
    -------
    pattern_wise
        :class:`PatternWise`.
    """
    if method == "nelder-mead":
        m, mkw = "minimize", {"method": "Nelder-Mead"}
    elif method == "differential-evolution":
        m, mkw = "differential_evolution", dict(de_kwargs or {"seed": 0})
    else:
        raise ValueError(
            f"method must be 'nelder-mead' or 'differential-evolution', not {method!r}"
        )
    pts = np.asarray(points, dtype=int)
    flat = flat_index(pts, sm.geometry.navigation_shape)
    phase = sm.start_xmap.phases[sm.start_xmap.phases.ids[-1]].deepcopy()
    start = sm.start_geometry
    xmap_r, det_r = _pattern_wise(
        _point_patterns(sm, flat) if patterns is None else patterns,
        sm.start_xmap.rotations[flat],
        phase,
        start,
        pts,
        sm.master_pattern,
        sm.energy,
        m,
        mkw,
        list(trust_region),
        pseudo_symmetry_ops=pseudo_symmetry_ops,
    )
    pcs = det_r.pc.reshape(-1, 3)
    geometry = replace(start, pc=pcs.mean(axis=0), reference=tuple(pts.mean(axis=0)))
    return PatternWise(geometry, xmap_r, pcs)


def compare_methods(
    sm: synthetic.SyntheticMap,
    points: int | np.ndarray = 100,
    methods: Sequence[str] = ("dic", "nelder-mead", "differential-evolution"),
    method_points: Mapping[str, int] | None = None,
    refine_kwargs: Mapping[str, Any] | None = None,
    dic_configs: Mapping[str, Mapping[str, Any]] | None = None,
    trust_region: Sequence[float] = TRUST_REGION,
    de_kwargs: Mapping[str, Any] | None = None,
    scheduler: str | None = "synchronous",
    verbose: bool = False,
) -> list[dict[str, Any]]:
    """Compare DIC geometry refinement with pattern-wise PC refinement.

    On the same synthetic map, start geometry and start orientations:

    - "dic": :func:`~kikuchipy_geomdic.refine_geometry_dic` (all six
      parameters unless *refine_kwargs* says otherwise);
    - "nelder-mead" and "differential-evolution": kikuchipy's
      :meth:`~kikuchipy.signals.EBSD.refine_orientation_projection_center`
      per pattern (SciPy Nelder-Mead, or differential evolution), with
      the paper's trust region (3 deg, 5 % of the detector); the PCs are
      then averaged over the points (the PC at the mean point position,
      angles unchanged: these methods cannot refine them), as in the
      paper's section 3.1, and the orientations are refined once more at
      that averaged geometry ("re-refined" columns).

    Parameters
    ----------
    sm
        Synthetic map with truth and start
        (:func:`~kikuchipy_geomdic.validation.synthetic.synthetic_map`).
    points
        Number of calibration points (spread evenly) or an (N, 2) array.
    methods
        Any of "dic", "nelder-mead", "differential-evolution".
    method_points
        Fewer points for a slow method, e.g. ``{"differential-evolution":
        20}``: the first points of an even spread of that many; its
        ``time_per_point`` and the extrapolated ``time_at_n`` (time per
        point times the number of points of the others) are reported.
    refine_kwargs
        Further arguments of
        :func:`~kikuchipy_geomdic.refine_geometry_dic` for "dic".
    dic_configs
        More DIC variants to time, ``{name: refine_kwargs}``; a name
        listed in *methods* runs
        :func:`~kikuchipy_geomdic.refine_geometry_dic` with those
        arguments (e.g. ``{"dic-fast": {"max_iterations": 3}}``).
    trust_region
        kikuchipy trust region (3 Euler angles in deg, 3 PC fractions).
    de_kwargs
        ``method_kwargs`` of differential evolution (SciPy); default
        ``{"seed": 0}``.
    scheduler
        Dask scheduler for every method while timed; "synchronous" (the
        default) times all methods on one CPU, as the paper did.
    verbose
        Print one line per method.

    Returns
    -------
    rows
        One dict per method: ``method``, ``n_points``, ``time`` (s, wall),
        ``time_per_point``, ``time_at_n`` (extrapolated to the largest
        number of points when fewer were used, else equal to ``time``),
        ``extrapolated``, ``err_pcx`` ... ``err_sample_tilt``,
        ``err_tilt_difference``, ``max_pc_error`` (at the map centre),
        ``pc_scatter`` (RMS of the pattern-wise PCs about their plane, 0
        for DIC), ``misorientation`` (mean, deg, of the method's own
        orientations to the truth), ``misorientation_rerefined`` and
        ``time_rerefine`` (after re-refining the orientations at the
        averaged geometry; DIC's orientations are already refined at its
        geometry), ``disorientation`` (mean angle to the map-mean
        orientation, the paper's Si metric; meaningful for a single
        crystal), ``ncc`` (mean).

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.validation.comparison import compare_methods
    >>> sm = synthetic.synthetic_map("Si", (4, 4), shape=(60, 60), seed=0)
    >>> rows = compare_methods(sm, 16, methods=["dic", "nelder-mead"])  # doctest: +SKIP
    >>> [r["method"] for r in rows]  # doctest: +SKIP
    ['dic', 'nelder-mead']
    """
    import dask

    nav = sm.geometry.navigation_shape
    if np.ndim(points) == 0:
        pts_all = calibration_points(nav, int(points))
    else:
        pts_all = np.asarray(points, dtype=int)
    truth = sm.geometry
    phase = sm.start_xmap.phases[sm.start_xmap.phases.ids[-1]].deepcopy()
    true_rot_all = sm.xmap.rotations
    method_points = dict(method_points or {})
    configs = {"dic": dict(refine_kwargs or {})}
    if sm.start == "centred":
        # The paper's design: the start's errors are believed to cancel
        configs["dic"].setdefault("orientation_prior", synthetic.centred_prior(0.3))
    configs.update({k: dict(v) for k, v in (dic_configs or {}).items()})
    rows = []
    ctx = dask.config.set(scheduler=scheduler) if scheduler else contextlib.nullcontext()
    with ctx:
        for method in methods:
            n_m = method_points.get(method)
            pts = pts_all if n_m is None else calibration_points(nav, int(n_m))
            flat = flat_index(pts, nav)
            # Read once, outside the timing, as refine_geometry_dic reads its own
            exp = None if method in configs else _point_patterns(sm, flat)
            t0 = time.perf_counter()
            row: dict[str, Any] = {"method": method, "n_points": len(pts)}
            if method in configs:
                geo, rot, ncc = _run_dic(row, sm, pts, configs[method], t0, true_rot_all, flat)
            elif method in ("nelder-mead", "differential-evolution"):
                pw = pattern_wise_geometry(sm, pts, method, trust_region, de_kwargs, patterns=exp)
                geo, rot, ncc = _rerefine(row, sm, pts, pw, t0, exp, phase, true_rot_all, flat)
            else:
                raise ValueError(
                    f"Unknown method {method!r}: use 'nelder-mead', "
                    f"'differential-evolution' or one of {list(configs)}"
                )
            err = _geometry_errors(geo, truth)
            row.update({f"err_{k}": v for k, v in err.items()})
            row["max_pc_error"] = max(abs(err[k]) for k in _PC)
            row["misorientation"] = float(_misorientation(rot, true_rot_all[flat]).mean())
            row["disorientation"] = _disorientation_from_mean(rot)
            row["ncc"] = ncc
            row["time_per_point"] = row["time"] / len(pts)
            if verbose:
                print(
                    f"{method}: {row['time']:.1f} s for {len(pts)} points, PC error "
                    f"{row['max_pc_error']:.1e}, misorientation {row['misorientation']:.3f} deg",
                    flush=True,
                )
            rows.append(row)
    n_max = max(r["n_points"] for r in rows)
    for r in rows:
        r["extrapolated"] = r["n_points"] < n_max
        r["time_at_n"] = r["time_per_point"] * n_max if r["extrapolated"] else r["time"]
    return rows


def _run_dic(row, sm, pts, config, t0, true_rot, flat):
    """Run one DIC configuration, timed from *t0*; fill *row*."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = refine_geometry_dic(*sm.start_inputs, points=pts, show_progressbar=False, **config)
    row["time"] = time.perf_counter() - t0
    rot = res.xmap.rotations
    row["pc_scatter"] = 0.0
    row["misorientation_rerefined"] = float(_misorientation(rot, true_rot[flat]).mean())
    row["time_rerefine"] = 0.0
    row["iterations"] = len(res.history)
    return res.geometry, rot, float(np.mean(res.xmap.scores))


def _rerefine(row, sm, pts, pw, t0, patterns, phase, true_rot, flat):
    """Time a pattern-wise calibration from *t0*, then re-refine its
    orientations at the averaged geometry; fill *row*."""
    row["time"] = time.perf_counter() - t0
    geo, pcs, rot = pw.geometry, pw.pcs, pw.xmap.rotations
    ncc = float(np.mean(pw.xmap.scores))
    # Scatter of pattern-wise PCs about the (true-angle) PC plane
    truth = sm.geometry
    plane = truth.pc_at(pts) - truth.pc_at(pts).mean(axis=0)
    resid = pcs - pcs.mean(axis=0) - plane
    row["pc_scatter"] = float(np.sqrt((resid**2).sum(axis=1).mean()))
    t1 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = refine_orientations(
            patterns, rot, geo.detector(pts), sm.master_pattern, sm.energy, phase
        )
    row["time_rerefine"] = time.perf_counter() - t1
    row["misorientation_rerefined"] = float(_misorientation(ref.rotations, true_rot[flat]).mean())
    row["iterations"] = 1
    return geo, rot, ncc
