"""The runs of a perturbation study: their specifications and one run.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

import contextlib
import time
import warnings

import numpy as np

from kikuchipy_geomdic.calibration.refinement import calibration_points, refine_geometry_dic
from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, MapGeometry
from kikuchipy_geomdic.geometry.maps import flat_index
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.scores import (
    _PC,
    _all_points,
    _geometry_errors,
    _misorientation,
    eq2_displacement,
    mean_displacement,
)


def _points(navigation_shape, points) -> np.ndarray:
    """The calibration points (N, 2) of a study: all, a number or given."""
    if points is None:
        return _all_points(navigation_shape)
    if np.ndim(points) == 0:
        return calibration_points(navigation_shape, int(points))
    return np.asarray(points, dtype=int)


def _specs(run: dict, pairs, levels, deltas) -> list[dict]:
    """One specification per run: *run* and a pair's two perturbations."""
    return [
        dict(
            run,
            param1=p1,
            param2=p2,
            level1=float(l1),
            level2=float(l2),
            delta1=float(l1) * deltas[p1],
            delta2=float(l2) * deltas[p2],
        )
        for p1, p2 in pairs
        for l1 in levels
        for l2 in levels
    ]


def _run_all(specs: list[dict], n_workers: int) -> list[dict]:
    """The rows of the runs, in parallel processes when *n_workers* > 1."""
    if n_workers > 1:
        import dask.bag as db

        bag = db.from_sequence(specs, npartitions=len(specs))
        return bag.map(_run_spec).compute(scheduler="processes", num_workers=n_workers)
    return [_run_spec(s) for s in specs]


def _run_spec(spec: dict) -> dict:
    """One run of the study (module level so that Dask can pickle it)."""
    import dask

    t0 = time.perf_counter()
    mp = spec["master_pattern"]
    if isinstance(mp, str):
        mp = master_patterns.master_pattern(mp)
    base: MapGeometry = spec["base_geometry"]
    delta = {spec["param1"]: spec["delta1"]}
    delta[spec["param2"]] = delta.get(spec["param2"], 0.0) + spec["delta2"]
    truth = base.updated(delta)
    row = {
        k: spec[k]
        for k in ("material", "param1", "param2", "level1", "level2", "delta1", "delta2")
    }
    ctx = (
        dask.config.set(scheduler=spec["inner_scheduler"])
        if spec.get("inner_scheduler")
        else contextlib.nullcontext()
    )
    with ctx, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sm = synthetic.synthetic_map(
            mp,
            base.navigation_shape,
            orientations=spec["orientations"],
            geometry=truth,
            perturbation={k: -v for k, v in delta.items()},
            orientation_error=spec["orientation_error"],
            start=spec.get("start", "centred"),
            scatter=spec["scatter"],
            dose=spec["dose"],
            blur=spec["blur"],
            seed=spec["seed"],
        )
        pts = spec["points"]
        row["initial_displacement"] = mean_displacement(sm.start_geometry, truth, pts)
        idx0 = flat_index(pts, base.navigation_shape)
        row["initial_displacement_eq2"] = eq2_displacement(
            sm.master_pattern,
            sm.xmap.rotations[idx0],
            sm.start_geometry,
            truth,
            pts,
            sm.energy,
            tuple(spec["refine_kwargs"].get("rois", (8, 8))),
        )[0]
        kwargs = dict(spec["refine_kwargs"])
        if sm.start == "centred":
            kwargs.setdefault(
                "orientation_prior", synthetic.centred_prior(spec["orientation_error"])
            )
        try:
            res = refine_geometry_dic(
                *sm.start_inputs,
                parameters=spec["parameters"],
                points=pts,
                show_progressbar=False,
                **kwargs,
            )
        except Exception as exc:  # A failed run is a result, not a crash
            row.update(
                error=repr(exc), success=False, success_ncc=False, time=time.perf_counter() - t0
            )
            return row
    idx = flat_index(res.points, sm.geometry.navigation_shape)
    mis = _misorientation(res.xmap.rotations, sm.xmap.rotations[idx])
    err = _geometry_errors(res.geometry, truth)
    scale = spec["scale"]
    row.update(
        initial_displacement_dic=res.history[0]["displacement_before"] if res.history else np.nan,
        final_displacement=res.field_after.mean_displacement,
        final_displacement_model=mean_displacement(res.geometry, truth, res.points),
        initial_ncc=res.history[0]["ncc_before"] if res.history else np.nan,
        final_ncc=float(np.mean(res.xmap.scores)),
        misorientation=float(mis.mean()),
        max_misorientation=float(mis.max()),
        iterations=len(res.history),
        converged=bool(res.converged),
    )
    for k, v in err.items():
        row[f"err_{k}"] = v
    for k in DEFAULT_PARAMETERS:
        row[f"nerr_{k}"] = err[k] * scale[k]
    row["max_pc_error"] = max(abs(err[k]) for k in _PC)
    row["success_ncc"] = bool(row["final_ncc"] > spec["ncc_success"])
    row["success"] = bool(
        row["misorientation"] < spec["misorientation_success"]
        and row["max_pc_error"] < spec["pc_success"]
    )
    row["time"] = time.perf_counter() - t0
    if spec.get("verbose"):
        print(
            f"[{spec['material']}] {spec['param1']}={spec['delta1']:+g} "
            f"{spec['param2']}={spec['delta2']:+g}: d0 {100 * row['initial_displacement']:.2f} %, "
            f"NCC {row['final_ncc']:.4f}, mis {row['misorientation']:.3f} deg, "
            f"PC err {row['max_pc_error']:.1e}, {'ok' if row['success'] else 'FAIL'} "
            f"({row['time']:.1f} s)",
            flush=True,
        )
    return row
