"""Tests of :mod:`kikuchipy_geomdic.io.summary`: the JSON summary of a
calibration, read back in every PC convention.
"""

from __future__ import annotations

import json

import kikuchipy
import pytest
from test_conventions import ROUND_TRIP_TOL, assert_same_detector

from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
from kikuchipy_geomdic.io import conventions as cv
from kikuchipy_geomdic.io import summary as su
from kikuchipy_geomdic.validation import synthetic


@pytest.fixture(scope="module")
def result(si_mp):
    sm = synthetic.synthetic_map(si_mp, (3, 4), shape=(60, 60), seed=2)
    res = refine_geometry_dic(
        sm.signal,
        sm.start_xmap,
        sm.start_detector,
        sm.master_pattern,
        sm.energy,
        points=12,
        rois=(6, 6),
        max_iterations=1,
        show_progressbar=False,
    )
    return res


def test_summary_round_trip_every_convention(tmp_path, result):
    summary = su.summary_from_result(result, energy_kv=20.0)
    path = su.write_summary(summary, tmp_path / "summary.json")
    back = su.read_summary(path)
    assert back["versions"]["kikuchipy"] == kikuchipy.__version__
    assert back["inputs"] == {"energy_kv": 20.0}
    assert back["refined_parameters"] == list(result.parameter_names)
    assert len(back["history"]) == len(result.history)
    for conv in cv.CONVENTIONS:
        assert back["conventions"][conv]["convention"] == conv
        geo = su.geometry_from_summary(back, conv)
        assert_same_detector(geo.detector(), result.detector)
        for name, value in result.geometry.as_dict().items():
            assert abs(geo.as_dict()[name] - value) <= ROUND_TRIP_TOL


def test_summary_table_lists_every_convention(result):
    summary = su.summary_from_result(result)
    text = su.format_summary(summary)
    for conv in cv.CONVENTIONS:
        rec = summary["conventions"][conv]
        assert f"  {conv:<8} ({', '.join(rec['pc_names'])})" in text
    pcx = result.parameters["pcx"]
    line = next(li for li in text.splitlines() if li.startswith("pcx"))
    assert f"{pcx:.6f}" in line
    assert "twist" in text and "(fixed)" in text


def test_summary_is_strict_json_without_nan(tmp_path, result):
    summary = su.summary_from_result(result, odd=float("nan"))
    path = su.write_summary(summary, tmp_path / "s.json")
    assert json.loads(path.read_text())["inputs"]["odd"] is None
    assert "NaN" not in path.read_text()


def test_read_summary_errors(tmp_path):
    (tmp_path / "other.json").write_text('{"a": 1}')
    with pytest.raises(ValueError, match="calibration summary"):
        su.read_summary(tmp_path / "other.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="not a JSON file"):
        su.read_summary(tmp_path / "bad.json")


def test_summary_keeps_the_standard_errors(tmp_path, result):
    summary = su.summary_from_result(result)
    back = su.read_summary(su.write_summary(summary, tmp_path / "s.json"))
    for name, v in result.standard_errors.items():
        if v < float("inf"):
            assert back["standard_errors"][name] == pytest.approx(v), name
        else:
            assert back["standard_errors"][name] is None, name
    assert back["undetermined"] == list(result.undetermined)
    assert back["adequacy"].get("verdict") == result.adequacy.get("verdict")
    text = su.format_summary(back)
    line = next(li for li in text.splitlines() if li.startswith("pcx"))
    assert f"{result.standard_errors['pcx']:.1e}" in line
    # A summary written before the standard errors were kept still prints
    del back["standard_errors"], back["undetermined"], back["adequacy"]
    assert "pcx" in su.format_summary(back)
