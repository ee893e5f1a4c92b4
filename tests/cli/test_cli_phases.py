"""The command line on a map of two phases: ``--master-pattern`` repeated
(a shipped name or NAME=FILE), ``refine`` reporting its points per phase,
``reindex --decide-phase`` putting a mislabelled point right and writing
the phase map figure."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest
from orix import io as orix_io

from kikuchipy_geomdic import cli
from kikuchipy_geomdic.io import conventions as cv

#: Points labelled with the other phase in the start
WRONG = [7, 33]


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def files(two_phase, tmp_path_factory):
    t = two_phase
    d = tmp_path_factory.mktemp("two_phase")
    t.signal.save(d / "map.h5")
    pid = t.start_xmap.phase_id.copy()
    pid[WRONG] = 1 - pid[WRONG]
    with contextlib.redirect_stdout(io.StringIO()):
        orix_io.save(str(d / "map.ang"), t.start_xmap)
        orix_io.save(str(d / "wrong.ang"), t.both(t.ni.start_xmap, t.si.start_xmap, pid))
    cv.save_detector(t.detector, d / "detector.txt", "bruker")
    return d


def test_refine_calibrates_from_both_phases_and_reports_them(files, capsys):
    code, out, err = run(
        ["refine", files / "map.h5", "--orientations", files / "map.ang", "--master-pattern",
         "Ni", "--master-pattern", "Si", "--energy", 20, "--parameters", "pcx", "pcy", "pcz",
         "--points", 36, "--out", files / "cal", "--quiet"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    summary = json.loads((files / "cal" / "summary.json").read_text())
    assert summary["calibration"]["points_per_phase"] == {"Ni": 18, "Si": 18}
    assert summary["inputs"]["master_pattern"] == ["Ni", "Si"]


def test_reindex_decides_the_phases_and_draws_them(files, two_phase, capsys):
    out_dir = files / "reindexed"
    code, out, err = run(
        ["reindex", files / "map.h5", "--orientations", files / "wrong.ang", "--master-pattern",
         "Ni=Ni", "--master-pattern", "Si", "--energy", 20, "--detector",
         files / "detector.txt", "--decide-phase", "--out", out_dir],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert "each point's phase decided" in out and "Points per phase: Ni 18, Si 18" in out
    stats = json.loads((out_dir / "reindex.json").read_text())["result"]
    assert stats["phases"] == {"Ni": 18, "Si": 18}
    assert stats["phase_changed"] == len(WRONG)
    assert stats["phase_not_decided"] == 0
    assert (out_dir / "phases.png").stat().st_size > 0
    back = orix_io.load(out_dir / "xmap_refined.h5")
    np.testing.assert_array_equal(back.prop["phase_changed"].nonzero()[0], WRONG)


def test_decide_phase_and_names_are_checked(files, capsys):
    base = ["reindex", files / "map.h5", "--orientations", files / "map.ang", "--energy", 20,
            "--detector", files / "detector.txt"]  # fmt: skip
    code, _, err = run(
        base + ["--master-pattern", "Ni", "--phase", "Ni", "--decide-phase", "--out",
                files / "x1"], capsys)  # fmt: skip
    assert code != 0 and "--decide-phase needs two --master-pattern" in err
    code, _, err = run(
        base + ["--master-pattern", "Si=Ni", "--master-pattern", "Si", "--out", files / "x2"],
        capsys,
    )
    assert code != 0 and "--master-pattern Si=Ni: its phase 'Ni'" in err
