"""The method comparison: DIC against kikuchipy's pattern-wise PC
refinement on one small synthetic map, scored against the truth."""

import numpy as np
import pytest

from kikuchipy_geomdic.validation import synthetic
from kikuchipy_geomdic.validation.comparison import compare_methods


def test_compare_methods(si_mp):
    sm = synthetic.synthetic_map(si_mp, (3, 3), orientations="random", shape=(48, 48), seed=3)
    rows = compare_methods(
        sm,
        points=9,
        methods=("dic", "nelder-mead", "differential-evolution"),
        method_points={"differential-evolution": 2},
        de_kwargs=dict(seed=0, maxiter=3, popsize=4),
        refine_kwargs=dict(max_iterations=4),
    )
    by = {r["method"]: r for r in rows}
    assert list(by) == ["dic", "nelder-mead", "differential-evolution"]
    for r in rows:
        for key in (
            "time",
            "time_per_point",
            "time_at_n",
            "max_pc_error",
            "misorientation",
            "disorientation",
            "ncc",
            "err_tilt_difference",
        ):
            assert np.isfinite(r[key]), (r["method"], key)
    assert by["differential-evolution"]["n_points"] == 2
    assert by["differential-evolution"]["extrapolated"]
    assert by["differential-evolution"]["time_at_n"] == pytest.approx(
        by["differential-evolution"]["time_per_point"] * 9
    )
    # Pattern-wise methods cannot change the angles: their angle errors
    # are the start's
    start_err = sm.start_geometry.tilt - sm.geometry.tilt
    assert by["nelder-mead"]["err_tilt"] == pytest.approx(start_err)
    # DIC recovers the geometry against the truth
    assert by["dic"]["max_pc_error"] < 1e-3
    assert abs(by["dic"]["err_tilt_difference"]) < 0.1
    with pytest.raises(ValueError, match="Unknown method"):
        compare_methods(sm, points=9, methods=["powell"])
