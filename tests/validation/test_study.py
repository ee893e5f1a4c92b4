"""The perturbation study: a small grid scored against the truth.

The grid is one pair (pcz, tilt) x {0, +-d/2} on a 4 x 4 map of 48 x 48
patterns, all six parameters free, so the test runs in well under a
minute; the full 375-run study is ``benchmarks/bench_perturbation.py``.
"""

import matplotlib
import numpy as np
import pytest

from kikuchipy_geomdic.validation import scores, synthetic, tables
from kikuchipy_geomdic.validation import study as st

NAV = (4, 4)
SHAPE = (48, 48)
REFINE = dict(max_iterations=4, refine_kwargs=dict(trust_region=[1, 1, 1]))


@pytest.fixture(scope="module")
def study(si_mp):
    return st.perturbation_study(
        si_mp,
        pairs=[("pcz", "tilt")],
        levels=(-0.5, 0.0, 0.5),
        navigation_shape=NAV,
        shape=SHAPE,
        orientations="random",
        base_geometry=st.paper_geometry(NAV, SHAPE),
        refine_kwargs=REFINE,
    )


def test_study_table(study):
    t = study.table
    assert t.size == 9
    assert set(t["param1"]) == {"pcz"} and set(t["param2"]) == {"tilt"}
    # The paper's d: pcz 0.08, tilt 1 deg; levels +-d/2
    assert sorted(set(np.round(t["delta1"], 6))) == [-0.04, 0.0, 0.04]
    assert sorted(set(np.round(t["delta2"], 6))) == [-0.5, 0.0, 0.5]
    for name in (
        "final_ncc",
        "misorientation",
        "err_pcx",
        "nerr_tilt",
        "initial_displacement",
        "initial_displacement_eq2",
    ):
        assert np.isfinite(t[name]).all(), name


def test_study_success_against_truth(study):
    t = study.table
    # Every run of this grid starts within the paper's 4 % and must succeed
    assert t["initial_displacement"].max() < 0.04
    assert t["success_ncc"].all(), t["final_ncc"]
    assert t["success"].all()
    assert (t["final_ncc"] > 0.99).all()
    assert t["max_pc_error"].max() < 2e-4
    assert np.abs(t["err_tilt_difference"]).max() < 0.05
    assert np.abs(t["err_azimuthal"]).max() < 0.1
    assert t["misorientation"].max() < 0.05
    # The start was really off (so the test could fail)
    off = (t["level1"] != 0) | (t["level2"] != 0)
    assert (t["initial_displacement"][off] > 0.005).all()
    assert t["initial_displacement"][~off].max() < 1e-9
    # Fixed point: the final model displacement is far below the initial one
    assert (t["final_displacement_model"][off] < 0.01 * t["initial_displacement"][off]).all()


def test_normalised_errors(study):
    t = study.table
    for k in ("pcx", "pcz", "tilt", "sample_tilt"):
        np.testing.assert_allclose(t[f"nerr_{k}"], t[f"err_{k}"] * study.scale[k])
    # pcx moves every pixel by its own change; pcz and angles less
    assert study.scale["pcx"] == pytest.approx(1.0, rel=1e-6)
    assert 0 < study.scale["pcz"] < 1
    # tilt and sample_tilt are exactly equivalent (up to the nonlinearity
    # of the +-delta difference)
    np.testing.assert_allclose(study.coupling[3, 5], -1.0, atol=1e-3)


def test_summary_plots_and_csv(study, tmp_path):
    s = study.summary()
    assert s["runs"] == 9 and s["success"] == 9 and s["success_ncc"] == 9
    assert np.isnan(s["min_failed_displacement"])
    assert s["success_below_4%"] == "9/9"
    path = tmp_path / "study.csv"
    study.save(path)
    back = tables.read_table(path)
    assert back.dtype == study.table.dtype
    np.testing.assert_allclose(back["final_ncc"], study.table["final_ncc"], rtol=1e-6)
    assert back["success"].tolist() == study.table["success"].tolist()
    for fig in (
        study.plot_success(),
        study.plot_heatmaps(metric="final_ncc"),
        study.plot_heatmaps(metric="misorientation"),
        study.plot_errors(),
        study.plot_normalised_errors(("pcz", "tilt")),
    ):
        assert isinstance(fig, matplotlib.figure.Figure)
    assert "| runs |" in tables.format_table([s])


def test_model_displacement_matches_measured(si_mp):
    # The paper's axis (the model field averaged over the DIC vectors as in
    # Eq. 2) agrees with what DIC measures between patterns simulated with
    # the true orientations at both geometries; averaging over every
    # pixel (no empty ROIs) gives more
    geo = st.paper_geometry((3, 3), (60, 60))
    other = geo.updated({"pcz": 0.02, "tilt": 0.5})
    sm = synthetic.synthetic_map(
        si_mp, (3, 3), geometry=geo, perturbation={}, orientation_error=0, shape=(60, 60), seed=2
    )
    pts = np.stack([a.ravel() for a in np.indices((3, 3))], axis=1)
    model, measured = scores.eq2_displacement(si_mp, sm.xmap.rotations, geo, other, pts)
    assert model == pytest.approx(measured, rel=0.1)
    assert scores.mean_displacement(geo, other, pts) > model


def test_bad_pair_raises():
    with pytest.raises(ValueError, match="Pair"):
        st.perturbation_study("Si", pairs=[("pcx", "nonsense")])
