"""Tests of :mod:`kikuchipy_geomdic.cli`: the real-data workflow and its
robustness.

The data are made here: a synthetic silicon map (4 x 5 patterns of 60 x 60
px, known geometry and orientations) written as a kikuchipy h5ebsd file
with its starting detector and orientations, the starting orientations as
``.ang`` and orix h5, and the shipped silicon master pattern written in
EMsoft's master pattern format. Nothing outside the test's temporary
folders is used.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import kikuchipy
import numpy as np
import pytest
from orix import io as orix_io
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic import cli
from kikuchipy_geomdic.indexing.variants import VARIANT_NAMES, variant_operators
from kikuchipy_geomdic.io import conventions as cv
from kikuchipy_geomdic.io import summary as su
from kikuchipy_geomdic.validation import synthetic

NAV = (4, 5)
FAST = ["--points", "20", "--rois", "6", "6", "--quiet"]
NI_MASTER_PATTERN = (
    Path(kikuchipy.__file__).parent
    / "data/emsoft_ebsd_master_pattern/ni_mc_mp_20kv_uint8_gzip_opts9.h5"
)


# --------------------------------------------------------------------- #
# Data
# --------------------------------------------------------------------- #


def write_emsoft_master_pattern(mp, path, energies=(20.0,)):
    """Write a Lambert master pattern in the layout of EMsoft's
    EMEBSDmaster output, as far as kikuchipy's reader needs it."""
    data = np.asarray(mp.data, dtype=np.float32)
    n, ne = data.shape[-1], len(energies)
    lat = np.asarray(mp.phase.structure.lattice.abcABG(), dtype=float)
    with h5py.File(path, "w") as f:
        f["EMheader/EBSDmaster/ProgramName"] = np.array([b"EMEBSDmaster.f90"], dtype="S16")
        cd = f.create_group("CrystalData")
        cd["LatticeParameters"] = np.concatenate([lat[:3] / 10, lat[3:]])  # nm
        cd["SpaceGroupNumber"] = mp.phase.space_group.number
        cd["SpaceGroupSetting"] = 1
        cd["Natomtypes"] = 1
        cd["Atomtypes"] = 14
        cd["AtomData"] = np.array([[0.0], [0.0], [0.0], [1.0], [0.005]], dtype=np.float32)
        em = f.create_group("EMData/EBSDmaster")
        em["EkeVs"] = np.asarray(energies, dtype=np.float32)
        em["numset"] = np.array([1], dtype=np.int32)
        em["mLPNH"] = np.broadcast_to(data[0], (1, ne, n, n)).copy()
        em["mLPSH"] = np.broadcast_to(data[1], (1, ne, n, n)).copy()
        nml = f.create_group("NMLparameters")
        nml["EBSDMasterNameList/npx"] = (n - 1) // 2
        nml["MCCLNameList/Ebinsize"] = 1.0
        nml["MCCLNameList/EkeV"] = float(max(energies))
        nml["MCCLNameList/Ehistmin"] = float(min(energies))
        nml["MCCLNameList/xtalname"] = np.array([b"Si/Si.xtal"])


def _save_ang(path, xmap):
    with contextlib.redirect_stdout(io.StringIO()):
        orix_io.save(str(path), xmap, overwrite=True)


@pytest.fixture(scope="module")
def data(tmp_path_factory, si_mp):
    d = tmp_path_factory.mktemp("cli_data")
    sm = synthetic.synthetic_map(si_mp, NAV, shape=(60, 60), seed=0)
    sm.signal.save(d / "map.h5")
    _save_ang(d / "map.ang", sm.start_xmap)
    orix_io.save(str(d / "map_orix.h5"), sm.start_xmap)
    write_emsoft_master_pattern(si_mp, d / "si_emsoft.h5", energies=(19.0, 20.0))
    return d, sm


@pytest.fixture(scope="module")
def bad_files(data, tmp_path_factory):
    """Broken and mismatched inputs."""
    d, sm = data
    b = tmp_path_factory.mktemp("bad")
    raw = (d / "map.h5").read_bytes()
    (b / "truncated.h5").write_bytes(raw[: len(raw) // 2])
    (b / "corrupt.h5").write_bytes(np.random.default_rng(0).bytes(20000))
    (b / "notes.txt").write_text("not patterns\n")
    (b / "corrupt.ang").write_text("# not an ang file\n1 2 3\n")
    _save_ang(b / "small.ang", sm.start_xmap[:3, :])
    s = sm.signal.deepcopy()
    s.xmap = CrystalMap.empty(shape=NAV, step_sizes=tuple(sm.geometry.step_sizes))
    s.save(b / "no_orientations.h5")
    sm.signal.inav[0, 0].save(b / "single.h5")
    other = synthetic.default_geometry((2, 2), (60, 60)).detector()
    cv.save_detector(other, b / "other_detector.txt")
    return b


def run(argv, capsys):
    """Run the command line in-process; return (code, stdout, stderr)."""
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def digest(folder: Path) -> dict[str, tuple[str, int]]:
    return {
        p.name: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(folder.iterdir())
        if p.is_file()
    }


def misorientation(a, b):
    return np.rad2deg((a.rotations * ~b.rotations).angle)


def _spy_result(store):
    from kikuchipy_geomdic.calibration import refinement

    original = refinement.refine_geometry_dic

    def spy(*args, **kwargs):
        store["result"] = original(*args, **kwargs)
        store["kwargs"] = kwargs
        return store["result"]

    return spy


@pytest.fixture(scope="module")
def refined(data, tmp_path_factory):
    """One `refine` run on the .ang map, with what went in and came out."""
    d, sm = data
    out = tmp_path_factory.mktemp("refine") / "calibration"
    before = digest(d)
    store = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(
            "kikuchipy_geomdic.calibration.refinement.refine_geometry_dic", _spy_result(store)
        )
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = cli.main(
                [
                    "refine",
                    str(d / "map.h5"),
                    "--orientations",
                    str(d / "map.ang"),
                    "--master-pattern",
                    "Si",
                    "--energy",
                    "20",
                    "--points",
                    "20",
                    "--rois",
                    "6",
                    "6",
                    "--max-iterations",
                    "3",
                    # The synthetic start is the paper's: zero-mean 0.3 deg
                    "--orientation-prior",
                    "0.3",
                    "--out",
                    str(out),
                ]
            )
    return dict(
        code=code,
        out=out,
        stdout=stdout.getvalue(),
        stderr=stderr.getvalue(),
        before=before,
        result=store["result"],
        kwargs=store["kwargs"],
    )


# --------------------------------------------------------------------- #
# Help and entry points
# --------------------------------------------------------------------- #


@pytest.mark.parametrize(
    "command, options",
    [
        ([], ["demo", "refine", "reindex"]),
        (["demo"], ["--rows", "--points", "--out"]),
        (
            ["refine"],
            [
                "--orientations",
                "--master-pattern",
                "--energy",
                "--pc",
                "--convention",
                "--tilt",
                "--sample-tilt",
                "--azimuthal",
                "--px-size",
                "--binning",
                "--parameters",
                "--points",
                "--out",
                "--scheduler",
                "--pseudo-symmetry",
            ],
        ),
        (
            ["reindex"],
            [
                "--orientations",
                "--master-pattern",
                "--energy",
                "--detector",
                "--method",
                "--kikuchipy-method",
                "--trust-region",
                "--out",
                "--scheduler",
                "--pseudo-symmetry",
            ],
        ),
    ],
)
def test_help(capsys, command, options):
    with pytest.raises(SystemExit) as e:
        cli.main(command + ["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for o in options:
        assert o in text


def test_entry_points(tmp_path):
    """``python -m kikuchipy_geomdic`` and the console script both run."""
    res = subprocess.run(
        [sys.executable, "-m", "kikuchipy_geomdic", "refine", "--help"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0 and "--master-pattern" in res.stdout
    script = Path(sys.executable).parent / "kikuchipy-geomdic"
    if not script.exists():
        pytest.skip("console script not installed beside the interpreter")
    res = subprocess.run(
        [
            str(script),
            "reindex",
            str(tmp_path / "missing.h5"),
            "--master-pattern",
            "Si",
            "--energy",
            "20",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"kikuchipy-geomdic: error: pattern file '{tmp_path / 'missing.h5'}' does not exist"
    ]


def test_demo_still_runs(tmp_path, capsys):
    code, out, _ = run(
        [
            "demo",
            "--rows",
            "3",
            "--cols",
            "3",
            "--size",
            "60",
            "--points",
            "9",
            "--out",
            tmp_path / "demo",
        ],
        capsys,
    )
    assert code == 0
    assert out.startswith("Synthetic silicon map: 3 x 3 patterns of 60 x 60 px")
    assert "Mean misorientation to the truth, after" in out
    assert (tmp_path / "demo" / "convergence.png").is_file()
    # The printed values, not just a header: the PC is recovered
    import re

    start, after = map(
        float,
        re.search(r"Largest PC error on the map: (\S+) at the start, (\S+) after", out).groups(),
    )
    assert after < start / 10 and after < 2e-3, out
    pcx = re.search(r"^pcx +(\S+) +(\S+) +(\S+) +(\S+) +(\S+)", out, re.M).groups()
    assert abs(float(pcx[4])) <= 3 * float(pcx[2]) + 1e-4, out


# --------------------------------------------------------------------- #
# refine
# --------------------------------------------------------------------- #


def test_refine_writes_complete_results(refined):
    assert refined["code"] == 0, refined["stderr"]
    out = refined["out"]
    assert sorted(p.name for p in out.iterdir()) == sorted(cli.REFINE_OUTPUTS)  # no staging left
    for name in cli.REFINE_OUTPUTS:
        if name.endswith(".png"):
            assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = su.read_summary(out / "summary.json")
    rows = (out / "history.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + len(summary["history"]) >= 2
    assert rows[0].startswith("iteration,accepted,damping,ncc_before")
    assert summary["inputs"]["energy_kv"] == 20.0
    assert summary["inputs"]["orientations"].endswith("map.ang")
    assert summary["versions"]["kikuchipy"] == kikuchipy.__version__


def test_refine_calibrates_towards_the_truth(refined, data):
    _, sm = data
    summary = su.read_summary(refined["out"] / "summary.json")
    true, start = sm.geometry.as_dict(), sm.start_geometry.as_dict()
    got = summary["geometry"]
    for k in ("pcx", "pcy", "pcz"):
        assert abs(start[k] - true[k]) > 5e-3  # the start is off: the test can fail
        assert abs(got[k] - true[k]) < 1e-3, (k, got[k], true[k])
        # ... and the standard errors that say so are written and printed
        se = summary["standard_errors"][k]
        assert se == pytest.approx(refined["result"].standard_errors[k])
        assert abs(got[k] - true[k]) <= 3 * se, (k, got[k] - true[k], se)
        line = next(li for li in refined["stdout"].splitlines() if li.startswith(k))
        assert f"{se:.1e}" in line, line
    assert summary["start_geometry"]["pcx"] == pytest.approx(start["pcx"], abs=1e-12)


def test_refine_detector_files_agree_in_every_convention(refined):
    out = refined["out"]
    geo = su.geometry_from_summary(su.read_summary(out / "summary.json"))
    whole = geo.detector()
    for name, conv in [
        ("detector.txt", "bruker"),
        ("detector_tsl.txt", "tsl"),
        ("detector_oxford.txt", "oxford"),
        ("detector_emsoft4.txt", "emsoft4"),
        ("detector_emsoft5.txt", "emsoft5"),
    ]:
        assert cv.read_detector_header(out / name)["convention"] == conv
        det = cv.load_detector(out / name)
        assert det.navigation_shape == NAV
        assert np.abs(det.pc - whole.pc).max() < 1e-9
        for a in ("tilt", "azimuthal", "twist", "sample_tilt"):
            assert getattr(det, a) == pytest.approx(getattr(whole, a), abs=1e-9)
    np.testing.assert_allclose(whole.pc, refined["result"].detector.pc, atol=1e-12)


def test_refine_prints_a_table(refined):
    text = refined["stdout"]
    for conv in cv.CONVENTIONS:
        assert f"  {conv:<8} (" in text
    assert "parameter" in text and "calibrated" in text
    assert "Results written to" in text
    assert "iteration 0:" in text  # per-step progress


def test_refine_reads_files_only(refined, data):
    d, _ = data
    assert digest(d) == refined["before"]


def test_refine_stored_orientations_and_pc_override(tmp_path, data, capsys):
    d, sm = data
    code, out, err = run(
        [
            "refine",
            d / "map.h5",
            "--master-pattern",
            "Si",
            "--energy",
            "20",
            "--pc",
            "0.52",
            "0.73",
            "0.63",
            "--convention",
            "tsl",
            "--px-size",
            "70",
            "--parameters",
            "pcx",
            "pcy",
            "pcz",
            "--max-iterations",
            "1",
            *FAST,
            "--out",
            tmp_path / "o",
        ],
        capsys,
    )
    assert code == 0, err
    s = su.read_summary(tmp_path / "o" / "summary.json")
    assert s["inputs"]["orientations"] == "pattern file"
    # TSL y* = 1 - Bruker PCy, z* = PCz for a square detector
    assert s["start_geometry"]["pcx"] == pytest.approx(0.52)
    assert s["start_geometry"]["pcy"] == pytest.approx(0.27)
    assert s["start_geometry"]["pcz"] == pytest.approx(0.63)
    # Angles from the file's metadata
    assert s["start_geometry"]["tilt"] == pytest.approx(sm.start_geometry.tilt)
    assert s["refined_parameters"] == ["pcx", "pcy", "pcz"]
    assert s["geometry"]["tilt"] == s["start_geometry"]["tilt"]


def test_dic_only_skips_the_full_field(tmp_path, data, capsys, monkeypatch):
    d, _ = data
    calls = []

    def spy(*args, **kwargs):
        res = real(*args, **kwargs)
        calls.append((kwargs["full_field"], [h.get("stage") for h in res.history]))
        return res

    from kikuchipy_geomdic.calibration import refinement

    real = refinement.refine_geometry_dic
    monkeypatch.setattr(refinement, "refine_geometry_dic", spy)
    for flag in ([], ["--dic-only"]):
        argv = ["refine", d / "map.h5", "--master-pattern", "Si", "--energy", "20"]
        argv += ["--parameters", "pcx", "pcy", "pcz", "--max-iterations", "1", *FAST]
        code, _, err = run([*argv, *flag, "--out", tmp_path / str(len(flag))], capsys)
        assert code == 0, err
    (default, stages), (dic_only, stages_dic) = calls
    assert default is None and "full-field" in stages
    assert dic_only is False and "full-field" not in stages_dic


def test_lattice_tolerance_reaches_the_calibration(tmp_path, data, capsys, monkeypatch):
    d, _ = data
    seen = []

    def spy(*args, **kwargs):
        seen.append(kwargs["lattice_tolerance"])
        raise ValueError("stop here")

    from kikuchipy_geomdic.calibration import refinement

    monkeypatch.setattr(refinement, "refine_geometry_dic", spy)
    argv = ["refine", d / "map.h5", "--master-pattern", "Si", "--energy", "20", *FAST]
    run([*argv, "--lattice-tolerance", "0.004", "--out", tmp_path / "a"], capsys)
    assert seen == [0.004]
    with pytest.raises(SystemExit):
        run([*argv, "--lattice-tolerance", "-1", "--out", tmp_path / "b"], capsys)
    assert "not a fraction >= 0" in capsys.readouterr().err


def test_unusable_points_excluded_from_calibration(tmp_path, data, capsys):
    """NaN patterns, non-indexed points, zero and NaN rotations are not
    used; the user is told fewer points than requested are usable."""
    d, sm = data
    s = sm.signal.deepcopy()
    s.data[0, 0] = np.nan
    s.data[3, 4] = np.nan
    s.save(tmp_path / "nan.h5")
    q = sm.start_xmap.rotations.data.copy()
    q[1] = 0.0
    q[2] = np.nan
    pid = sm.start_xmap.phase_id.copy()
    pid[5] = -1
    xmap = CrystalMap(
        Rotation(q),
        phase_id=pid,
        x=sm.start_xmap.x,
        y=sm.start_xmap.y,
        phase_list=sm.start_xmap.phases,
        scan_unit="um",
    )
    orix_io.save(str(tmp_path / "holes.h5"), xmap)
    code, out, err = run(
        [
            "refine",
            tmp_path / "nan.h5",
            "--orientations",
            tmp_path / "holes.h5",
            "--master-pattern",
            "Si",
            "--energy",
            "20",
            "--parameters",
            "pcx",
            "pcy",
            "pcz",
            "--max-iterations",
            "1",
            *FAST,
            "--out",
            tmp_path / "o",
        ],
        capsys,
    )
    assert code == 0, err
    assert "2 calibration candidate pattern(s) hold NaN or are blank" in err
    assert "only 15 usable point(s) for the 20 requested" in err
    pts = su.read_summary(tmp_path / "o" / "summary.json")["calibration"]["points_row_col"]
    flat = {r * NAV[1] + c for r, c in pts}
    assert len(flat) == 15 and not flat & {0, 1, 2, 5, 19}


def test_no_usable_points(tmp_path, data, capsys):
    d, sm = data
    pid = np.full(20, -1)
    xmap = CrystalMap(
        sm.start_xmap.rotations,
        phase_id=pid,
        x=sm.start_xmap.x,
        y=sm.start_xmap.y,
        phase_list=sm.start_xmap.phases,
        scan_unit="um",
    )
    orix_io.save(str(tmp_path / "none.h5"), xmap)
    code, _, err = run(
        [
            "refine",
            d / "map.h5",
            "--orientations",
            tmp_path / "none.h5",
            "--master-pattern",
            "Si",
            "--energy",
            "20",
            *FAST,
            "--out",
            tmp_path / "o",
        ],
        capsys,
    )
    assert code == 2
    assert err.strip().splitlines()[-1] == (
        "kikuchipy-geomdic: error: The crystal map has no indexed points"
    )
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------- #
# reindex
# --------------------------------------------------------------------- #


def test_reindex_with_calibrated_detector(tmp_path, data, refined, capsys):
    d, sm = data
    before = digest(refined["out"])
    code, out, err = run(
        [
            "reindex",
            d / "map.h5",
            "--orientations",
            d / "map_orix.h5",
            "--master-pattern",
            "Si",
            "--energy",
            "20",
            "--detector",
            refined["out"],
            "--out",
            tmp_path / "r",
        ],
        capsys,
    )
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == sorted(cli.REINDEX_OUTPUTS)
    assert "Refined 20 of 20 points" in out and "0 flagged" in out
    xmap = orix_io.load(str(tmp_path / "r" / "xmap_refined.h5"))
    with contextlib.redirect_stdout(io.StringIO()):
        ang = orix_io.load(str(tmp_path / "r" / "xmap_refined.ang"))
    assert xmap.shape == ang.shape == NAV
    assert misorientation(sm.start_xmap, sm.xmap).mean() > 0.2
    assert misorientation(xmap, sm.xmap).mean() < 0.05
    assert misorientation(ang, xmap).max() < 1e-3
    assert xmap.scores.min() > 0.99
    summary = json.loads((tmp_path / "r" / "reindex.json").read_text())
    assert summary["result"]["refined"] == 20
    assert summary["detector_source"].endswith("detector.txt")
    # The .ang header carries the calibrated PC (EDAX TSL convention)
    tsl = summary["detector_reference_pc"]["tsl"]["pc"]
    header = (tmp_path / "r" / "xmap_refined.ang").read_text().splitlines()[:10]
    assert f"# x-star                 {tsl[0]:.6f}" in header
    assert f"# y-star                 {tsl[1]:.6f}" in header
    assert digest(refined["out"]) == before and digest(d) == refined["before"]

    # The summary gives the same detector as detector.txt
    code, _, err = run(
        [
            "reindex",
            d / "map.h5",
            "--orientations",
            d / "map_orix.h5",
            "--quiet",
            "--master-pattern",
            d / "si_emsoft.h5",
            "--energy",
            "20",
            "--detector",
            refined["out"] / "summary.json",
            "--method",
            "kikuchipy",
            "--out",
            tmp_path / "r2",
        ],
        capsys,
    )
    assert code == 0, err
    again = orix_io.load(str(tmp_path / "r2" / "xmap_refined.h5"))
    # kikuchipy's Nelder-Mead reaches the same optimum
    assert misorientation(again, xmap).max() < 0.02


# --------------------------------------------------------------------- #
# Errors: one line, exit code 2, nothing written
# --------------------------------------------------------------------- #


ERRORS = {
    "missing patterns": (
        ["refine", "{b}/missing.h5"],
        "pattern file '{b}/missing.h5' does not exist",
    ),
    "truncated patterns": (
        ["refine", "{b}/truncated.h5"],
        "cannot read patterns from '{b}/truncated.h5'",
    ),
    "corrupt patterns": (
        ["refine", "{b}/corrupt.h5"],
        "cannot read patterns from '{b}/corrupt.h5'",
    ),
    "unreadable format": (
        ["reindex", "{b}/notes.txt"],
        "cannot read patterns from '{b}/notes.txt'",
    ),
    "single pattern": (["refine", "{b}/single.h5"], "holds a single pattern"),
    "missing map": (
        ["refine", "{d}/map.h5", "--orientations", "{b}/none.ang"],
        "orientation map '{b}/none.ang' does not exist",
    ),
    "corrupt map": (
        ["refine", "{d}/map.h5", "--orientations", "{b}/corrupt.ang"],
        "cannot read orientations from '{b}/corrupt.ang'",
    ),
    "no stored orientations": (
        ["refine", "{b}/no_orientations.h5"],
        "the pattern file holds no orientations",
    ),
    "map size": (
        ["reindex", "{d}/map.h5", "--orientations", "{b}/small.ang"],
        "has shape (3, 5) (15 points), the patterns (4, 5)",
    ),
    "wrong phase (name)": (
        ["refine", "{d}/map.h5", "--master-pattern", "BaTiO3"],
        "The master pattern's phase 'BaTiO3' (4mm",
    ),
    "wrong phase (file)": (
        ["reindex", "{d}/map.h5", "--master-pattern", str(NI_MASTER_PATTERN)],
        "The master pattern's phase 'ni' (m-3m, a b c = 0.3524",
    ),
    "wrong energy (file)": (
        ["refine", "{d}/map.h5", "--master-pattern", "{d}/si_emsoft.h5", "--energy", "30"],
        "was simulated for 19-20 kV, not for 30 kV",
    ),
    "wrong energy (file 2)": (
        ["refine", "{d}/map.h5", "--master-pattern", str(NI_MASTER_PATTERN), "--energy", "15"],
        "was simulated for 20 kV, not for 15 kV",
    ),
    "missing master pattern": (
        ["refine", "{d}/map.h5", "--master-pattern", "{b}/mp.h5"],
        "master pattern '{b}/mp.h5' does not exist",
    ),
    "detector of another map": (
        ["reindex", "{d}/map.h5", "--detector", "{b}/other_detector.txt"],
        "the detector has 4 PCs, the map 20 points",
    ),
    "detector plus override": (
        ["reindex", "{d}/map.h5", "--detector", "{b}/other_detector.txt", "--tilt", "3"],
        "--detector gives the whole geometry",
    ),
    "convention without pc": (
        ["refine", "{d}/map.h5", "--convention", "tsl"],
        "--convention gives the convention of --pc",
    ),
    "bad method kwargs": (
        ["reindex", "{d}/map.h5", "--method", "kikuchipy", "--method-kwargs", "{{nope"],
        "--method-kwargs is not JSON",
    ),
    "kikuchipy options without its method": (
        ["reindex", "{d}/map.h5", "--trust-region", "1", "1", "1"],
        "are options of --method kikuchipy",
    ),
}


@pytest.mark.parametrize("case", list(ERRORS))
def test_errors_are_one_line(case, data, bad_files, tmp_path, capsys):
    d, _ = data
    argv, message = ERRORS[case]
    argv = [a.format(d=d, b=bad_files) for a in argv]
    if "--master-pattern" not in argv:
        argv += ["--master-pattern", "Si"]
    if "--energy" not in argv:
        argv += ["--energy", "20"]
    before = digest(d)
    code, out, err = run(argv + ["--out", tmp_path / "o"], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert lines[-1].startswith("kikuchipy-geomdic: error: "), err
    assert message.format(d=d, b=bad_files) in lines[-1]
    assert "Traceback" not in err and all(li.startswith("kikuchipy-geomdic: ") for li in lines)
    assert not (tmp_path / "o").exists()
    assert digest(d) == before


def test_existing_results_are_not_overwritten(refined, data, capsys):
    d, _ = data
    before = digest(refined["out"])
    code, _, err = run(
        [
            "refine",
            d / "map.h5",
            "--master-pattern",
            "Si",
            "--energy",
            "20",
            "--out",
            refined["out"],
        ],
        capsys,
    )
    assert code == 2 and "already holds results" in err and "--overwrite" in err
    assert digest(refined["out"]) == before


# --------------------------------------------------------------------- #
# Interrupted runs (Ctrl-C)
# --------------------------------------------------------------------- #


def _interrupt_after(n_calls, original):
    calls = {"n": 0}

    def wrapper(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > n_calls:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    return wrapper


def _refine_argv(d, out, *extra):
    return [
        "refine",
        d / "map.h5",
        "--orientations",
        d / "map.ang",
        "--master-pattern",
        "Si",
        "--energy",
        "20",
        *FAST,
        "--out",
        out,
        *extra,
    ]


def test_interrupt_during_calibration_writes_nothing(tmp_path, data, monkeypatch, capsys):
    d, _ = data

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(
        "kikuchipy_geomdic.calibration.refinement.refine_geometry_dic", interrupted
    )
    code, _, err = run(_refine_argv(d, tmp_path / "o"), capsys)
    assert code == 130 and err.strip() == "kikuchipy-geomdic: interrupted"
    assert not (tmp_path / "o").exists()


def test_interrupt_while_writing_leaves_no_file(tmp_path, data, refined, monkeypatch, capsys):
    d, _ = data
    monkeypatch.setattr(
        "kikuchipy_geomdic.calibration.refinement.refine_geometry_dic",
        lambda *a, **k: refined["result"],
    )
    monkeypatch.setattr(cv, "save_detector", _interrupt_after(2, cv.save_detector))
    code, _, _ = run(_refine_argv(d, tmp_path / "o"), capsys)
    assert code == 130
    assert list((tmp_path / "o").iterdir()) == []  # not even the staging folder


def test_interrupt_keeps_previous_results(tmp_path, data, refined, monkeypatch, capsys):
    d, _ = data
    out = tmp_path / "o"
    shutil.copytree(refined["out"], out)
    before = digest(out)
    monkeypatch.setattr(
        "kikuchipy_geomdic.calibration.refinement.refine_geometry_dic",
        lambda *a, **k: refined["result"],
    )
    monkeypatch.setattr(su, "write_summary", _interrupt_after(0, su.write_summary))
    code, _, _ = run(_refine_argv(d, out, "--overwrite"), capsys)
    assert code == 130
    assert digest(out) == before
    assert sorted(p.name for p in out.iterdir()) == sorted(cli.REFINE_OUTPUTS)


def test_ctrl_c_in_a_real_process(tmp_path, data):
    """SIGINT to a running ``python -m kikuchipy_geomdic refine``."""
    d, _ = data
    out = tmp_path / "o"
    argv = [sys.executable, "-u", "-m", "kikuchipy_geomdic", *map(str, _refine_argv(d, out))]
    argv.remove("--quiet")
    argv[argv.index("--points") + 1] = "20"
    # The paper's loop refines orientations with kikuchipy at every step,
    # seconds of work: the joint solver can finish this small map before
    # the signal arrives on an idle machine
    argv += ["--max-iterations", "10", "--solver", "paper"]
    proc = subprocess.Popen(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        # A shell without job control starts background jobs with SIGINT
        # ignored, and the child would inherit that: Python then installs
        # no KeyboardInterrupt handler
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 240
        for line in proc.stdout:
            if line.startswith("Refining the geometry") or time.monotonic() > deadline:
                break
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    # 130, or death by SIGINT after the message (seen once in CI, with
    # the message printed: the interrupt reached Python again while it
    # shut down): a shell reports both as 130
    assert proc.returncode in (130, -signal.SIGINT), err
    assert err.strip().splitlines()[-1] == "kikuchipy-geomdic: interrupted"
    assert not out.exists() or list(out.iterdir()) == []


# --------------------------------------------------------------------- #
# Warnings about step sizes and placeholder geometry
# --------------------------------------------------------------------- #


WARNING = "kikuchipy-geomdic: warning: "
#: All points of the line scan (FAST asks for more)
LINE = ["--points", str(NAV[1])]


def write_emsoft_ebsd(path, patterns, rotations, detector, phase):
    """Write a 1D stack of patterns in the layout of EMsoft's EMEBSD
    output, as far as kikuchipy's reader needs it: its navigation axis is
    in pixels, not micrometres."""
    n, sy, sx = patterns.shape
    lat = np.asarray(phase.structure.lattice.abcABG(), dtype=float)
    pc = detector.pc_emsoft().reshape(-1, 3)[0]
    with h5py.File(path, "w") as f:
        f["EMheader/EBSD/ProgramName"] = np.array([b"EMEBSD.f90"], dtype="S10")
        cd = f.create_group("CrystalData")
        cd["LatticeParameters"] = np.concatenate([lat[:3] / 10, lat[3:]])  # nm
        cd["SpaceGroupNumber"] = phase.space_group.number
        cd["Natomtypes"] = 1
        cd["Atomtypes"] = 14
        cd["AtomData"] = np.array([[0.0], [0.0], [0.0], [1.0], [0.005]], dtype=np.float32)
        em = f.create_group("EMData/EBSD")
        em["EBSDPatterns"] = np.asarray(patterns, dtype=np.float32)
        em["EulerAngles"] = rotations.to_euler().astype(np.float32)
        em["xtalname"] = np.array([b"Si/Si.xtal"])
        nml = f.create_group("NMLparameters/EBSDNameList")
        nml["numsx"], nml["numsy"] = sx, sy
        nml["energymax"] = 20.0
        nml["delta"] = float(detector.px_size)
        nml["binning"] = int(detector.binning)
        nml["thetac"] = float(detector.tilt)
        nml["xpc"], nml["ypc"], nml["L"] = (float(v) for v in pc)


def _stop_at_refinement(monkeypatch):
    """Replace the refinement by a stop (Ctrl-C) that records what the CLI
    passed: the warnings come before it."""
    seen = {}

    def stop(signal, xmap, detector, *args, **kwargs):
        seen.update(signal=signal, xmap=xmap, detector=detector, kwargs=kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr("kikuchipy_geomdic.calibration.refinement.refine_geometry_dic", stop)
    return seen


def _warnings(err):
    return [li[len(WARNING) :] for li in err.splitlines() if li.startswith(WARNING)]


def _refine_files(patterns, orientations, out, *extra):
    return [
        "refine",
        patterns,
        "--orientations",
        orientations,
        "--master-pattern",
        "Si",
        "--energy",
        "20",
        *FAST,
        "--out",
        out,
        *extra,
    ]


@pytest.fixture(scope="module")
def line_files(data, tmp_path_factory):
    """The first row of the map as an EMsoft pattern file (navigation in
    pixels) and its orientations as orix h5 files in um and in px."""
    d, sm = data
    b = tmp_path_factory.mktemp("line")
    n = NAV[1]
    write_emsoft_ebsd(
        b / "line_emsoft.h5",
        np.asarray(sm.signal.data[0]),
        sm.start_xmap.rotations[:n],
        sm.start_detector,
        sm.master_pattern.phase,
    )
    dx = sm.geometry.step_sizes[1]
    for unit, step in (("um", dx), ("px", 1.0)):
        xm = CrystalMap(
            rotations=sm.start_xmap.rotations[:n],
            x=np.arange(n) * step,
            phase_list=sm.start_xmap.phases,
            scan_unit=unit,
        )
        orix_io.save(str(b / f"line_{unit}.h5"), xm)
    return b, dx


def test_placeholder_geometry_warnings(tmp_path, data, monkeypatch, capsys):
    from kikuchipy.detectors import EBSDDetector

    d, sm = data
    s = sm.signal.deepcopy()
    s.detector = EBSDDetector(
        shape=(60, 60), pc=(0.5, 0.5, 0.5), px_size=1.0, tilt=2.0, sample_tilt=70.0
    )
    s.save(tmp_path / "placeholder.h5")
    seen = _stop_at_refinement(monkeypatch)
    argv = _refine_files(tmp_path / "placeholder.h5", d / "map.ang", tmp_path / "o")
    code, _, err = run(argv, capsys)
    assert code == 130, err
    assert _warnings(err) == [
        "the pattern file has kikuchipy's default PC (0.5, 0.5, 0.5), probably no "
        "calibration: pass a starting --pc X Y Z",
        "the detector pixel size is 1 um, kikuchipy's placeholder: the PC field over the "
        "map depends on it, pass --px-size (unbinned, um) and --binning",
    ]
    assert np.allclose(seen["detector"].pc, 0.5)
    # Given on the command line, the placeholders are replaced and not warned about
    code, _, err = run(argv + ["--pc", "0.52", "0.26", "0.64", "--px-size", "70"], capsys)
    assert code == 130, err
    assert _warnings(err) == []
    assert np.allclose(seen["detector"].pc, [0.52, 0.26, 0.64])
    assert seen["detector"].px_size == 70


def test_step_sizes_differ_warning(tmp_path, data, monkeypatch, capsys):
    d, sm = data
    dy, dx = sm.geometry.step_sizes
    xm = CrystalMap(
        rotations=sm.start_xmap.rotations,
        x=sm.start_xmap.x / 2.5,
        y=sm.start_xmap.y / 2.5,
        phase_list=sm.start_xmap.phases,
        scan_unit="um",
    )
    orix_io.save(str(tmp_path / "other_steps.h5"), xm)
    seen = _stop_at_refinement(monkeypatch)
    code, _, err = run(
        _refine_files(d / "map.h5", tmp_path / "other_steps.h5", tmp_path / "o"), capsys
    )
    assert code == 130, err
    assert _warnings(err) == [
        f"step sizes differ: patterns {{'x': {dx}, 'y': {dy}}} um, orientation map "
        f"(x {dx / 2.5}, y {dy / 2.5}) um; using the patterns'"
    ]
    axes = seen["signal"].axes_manager.navigation_axes
    assert [(ax.name, ax.scale, ax.units) for ax in axes] == [("x", dx, "um"), ("y", dy, "um")]


def test_no_step_size_in_micrometres_warning(tmp_path, line_files, monkeypatch, capsys):
    b, dx = line_files
    seen = _stop_at_refinement(monkeypatch)
    code, _, err = run(
        _refine_files(b / "line_emsoft.h5", b / "line_um.h5", tmp_path / "o", *LINE),
        capsys,
    )
    assert code == 130, err
    (warning,) = _warnings(err)
    # A line scan's orientation map has no y step (orix gives 0)
    assert warning.startswith(
        "the pattern file gives no step size in micrometres; using the orientation map's "
        f"(x {dx}, y "
    ) and warning.endswith(" um)"), warning
    # The line scan's patterns now have the orientation map's step
    (ax,) = seen["signal"].axes_manager.navigation_axes
    assert (ax.scale, ax.units) == (dx, "um")


def test_step_sizes_not_micrometres_warning(tmp_path, line_files, monkeypatch, capsys):
    b, _ = line_files
    seen = _stop_at_refinement(monkeypatch)
    code, _, err = run(
        _refine_files(b / "line_emsoft.h5", b / "line_px.h5", tmp_path / "o", *LINE),
        capsys,
    )
    assert code == 130, err
    assert _warnings(err) == [
        "step sizes are in ['px'], not micrometres: the PC field over the map assumes micrometres"
    ]
    (ax,) = seen["signal"].axes_manager.navigation_axes
    assert (ax.scale, ax.units) == (1.0, "px")


# --------------------------------------------------------------------- #
# Pseudo-symmetric variants (--pseudo-symmetry)
# --------------------------------------------------------------------- #

BTO_NAV = (8, 8)


@pytest.fixture(scope="module")
def bto_files(tmp_path_factory, bto_mp):
    """A BaTiO3 stripe-domain map (60 px) as kikuchipy h5ebsd, its starts
    in random variants (what an indexer blind to the variants gives) as
    orix h5, the true detector, and the operators as .npy and .txt."""
    d = tmp_path_factory.mktemp("bto")
    sm = synthetic.synthetic_map(
        bto_mp, BTO_NAV, "stripes", shape=(60, 60), dose=300, seed=1, perturbation={}
    )
    ops = variant_operators()
    k = np.random.default_rng(0).integers(0, 6, sm.xmap.size)
    start = CrystalMap(
        rotations=ops[k] * sm.start_xmap.rotations,
        x=sm.start_xmap.x,
        y=sm.start_xmap.y,
        phase_list=sm.start_xmap.phases,
        scan_unit="um",
    )
    sm.signal.save(d / "bto.h5")
    orix_io.save(str(d / "start.h5"), start)
    cv.save_detector(sm.detector, d / "detector.txt")
    np.save(d / "ops.npy", ops[1:].data)
    np.savetxt(d / "ops.txt", ops[1:].data, header="BaTiO3 variants: a b c d")
    return d, sm


def _bto_argv(command, d, out, *extra):
    return [
        command, d / "bto.h5", "--orientations", d / "start.h5", "--master-pattern", "BaTiO3",
        "--energy", "20", "--quiet", "--out", out, *extra,
    ]  # fmt: skip


def test_reindex_writes_domains(tmp_path, bto_files, capsys):
    """reindex --pseudo-symmetry from random-variant starts: the maps
    written hold each point's variant (relative to its start, scrambled),
    its domain (the truth), confidence and margin; domains.png is drawn."""
    d, sm = bto_files
    truth = sm.xmap.prop["variant"]
    before = digest(d)
    out = tmp_path / "r"
    argv = _bto_argv("reindex", d, out, "--detector", d / "detector.txt")
    code, _, err = run([*argv, "--pseudo-symmetry", "BaTiO3"], capsys)
    assert code == 0, err
    names = [*cli.REINDEX_OUTPUTS[:-1], cli.DOMAIN_FIGURE, cli.REINDEX_OUTPUTS[-1]]
    assert sorted(p.name for p in out.iterdir()) == sorted(names)
    xmap = orix_io.load(str(out / "xmap_refined.h5"))
    # Right points: trusted and at their true orientation (modulo 4mm)
    from orix.quaternion import Orientation

    pg = sm.xmap.phases[0].point_group
    err_deg = Orientation(xmap.rotations, pg).angle_with(Orientation(sm.xmap.rotations, pg))
    right = (xmap.prop["converged"] == 1) & (np.rad2deg(err_deg) < 1)
    assert right.mean() >= 0.95
    np.testing.assert_array_equal(xmap.prop["domain"][right], truth[right])
    assert (xmap.prop["variant"] != truth).mean() > 0.5  # relative to random starts
    for key in ("confidence", "cross_variant_margin"):
        assert np.isfinite(xmap.prop[key]).all() and (xmap.prop[key][right] > 0).all()
    # The .ang file carries the same as extra columns
    with contextlib.redirect_stdout(io.StringIO()):
        ang = orix_io.load(str(out / "xmap_refined.ang"))
    for key in cli.ANG_VARIANT_COLUMNS:
        np.testing.assert_allclose(ang.prop[key], xmap.prop[key], atol=1e-5)
    summary = json.loads((out / "reindex.json").read_text())
    domains = summary["result"]["domains"]
    assert list(domains) == list(VARIANT_NAMES)
    assert sum(domains.values()) == truth.size and domains["+z"] == (truth == 0).sum()
    assert summary["pseudo_symmetry"]["source"] == "BaTiO3"
    import matplotlib.pyplot as plt

    assert plt.imread(out / cli.DOMAIN_FIGURE).shape[0] > 400
    assert digest(d) == before

    # The operators from a file give the same; without them, no domain
    for name in ("ops.npy", "ops.txt"):
        code, _, err = run(
            [*argv[:-2], "--out", tmp_path / name, "--pseudo-symmetry", d / name], capsys
        )
        assert code == 0, err
        again = orix_io.load(str(tmp_path / name / "xmap_refined.h5"))
        np.testing.assert_array_equal(again.prop["domain"], xmap.prop["domain"])
    code, _, err = run([*argv[:-2], "--out", tmp_path / "plain"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "plain").iterdir()) == sorted(cli.REINDEX_OUTPUTS)
    assert "domain" not in orix_io.load(str(tmp_path / "plain" / "xmap_refined.h5")).prop


def test_refine_passes_pseudo_symmetry(tmp_path, bto_files, monkeypatch, capsys):
    d, _ = bto_files
    seen = _stop_at_refinement(monkeypatch)
    ops = variant_operators()[1:]
    for spec in ("batio3", d / "ops.txt"):
        code, _, err = run(
            _bto_argv("refine", d, tmp_path / "o", "--pseudo-symmetry", spec), capsys
        )
        assert code == 130, err
        np.testing.assert_allclose(seen["kwargs"]["pseudo_symmetry_ops"].data, ops.data)
    code, _, err = run(_bto_argv("refine", d, tmp_path / "o"), capsys)
    assert code == 130 and seen["kwargs"]["pseudo_symmetry_ops"] is None


PSEUDO_SYMMETRY_ERRORS = {
    "unknown name": (
        "Quartz",
        "--pseudo-symmetry: pseudo-symmetry 'Quartz' is neither a known material (BaTiO3)",
    ),
    "not quaternions": ("{t}/three.txt", "must hold an (n, 4) array of quaternions"),
    "not unit": ("{t}/long.npy", "quaternion 0 has norm 2, not 1"),
    "identity": ("{t}/identity.npy", "operator 0 is the identity; give the operators"),
    "unreadable": ("{t}/words.txt", "cannot read pseudo-symmetry operators from"),
    "wrong phase": (
        "BaTiO3",
        "--pseudo-symmetry does not fit phase 'Si': pseudo-symmetry operator 0 is the identity",
    ),
}


@pytest.mark.parametrize("case", list(PSEUDO_SYMMETRY_ERRORS))
@pytest.mark.parametrize("command", ["refine", "reindex"])
def test_pseudo_symmetry_errors(case, command, data, tmp_path, capsys):
    d, _ = data
    ops = variant_operators().data
    np.savetxt(tmp_path / "three.txt", ops[1:, :3])
    np.save(tmp_path / "long.npy", 2 * ops[1:])
    np.save(tmp_path / "identity.npy", ops)
    (tmp_path / "words.txt").write_text("one two three four\n")
    spec, message = PSEUDO_SYMMETRY_ERRORS[case]
    argv = [command, d / "map.h5", "--master-pattern", "Si", "--energy", "20"]
    argv += ["--pseudo-symmetry", spec.format(t=tmp_path), "--out", tmp_path / "o"]
    code, _, err = run(argv, capsys)
    assert code == 2
    (line,) = err.strip().splitlines()
    assert line.startswith("kikuchipy-geomdic: error: ") and message in line, line
    assert not (tmp_path / "o").exists()


def test_orientation_model(tmp_path, data, monkeypatch, capsys):
    """--orientation-model reaches the calibration; asked of a polycrystal,
    the crystal model says so and nothing is written."""
    d, _ = data
    code, _, err = run(_refine_argv(d, tmp_path / "o", "--orientation-model", "crystal"), capsys)
    assert code != 0
    assert "not one crystal" in err
    assert not (tmp_path / "o" / "summary.json").exists()
    seen = _stop_at_refinement(monkeypatch)
    code, _, err = run(_refine_argv(d, tmp_path / "p", "--orientation-model", "auto"), capsys)
    assert code == 130, err
    assert seen["kwargs"]["orientation_model"] == "auto"
