"""Tests of :mod:`kikuchipy_geomdic.io.conventions`: convention-safe export.

Every PC convention kikuchipy knows is exported and re-imported, as a
record and as a detector file of kikuchipy's text format (the JSON summary:
``test_summary.py``). The truths are kikuchipy's documented conversion examples, the
way kikuchipy's vendor readers build a detector from vendor fields, and
patterns simulated from the original detector.
"""

from __future__ import annotations

import json
import warnings

import kikuchipy
import numpy as np
import pytest
from kikuchipy.detectors import EBSDDetector
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.io import conventions as cv
from kikuchipy_geomdic.patterns import simulation

ROUND_TRIP_TOL = 1e-9
ANGLES = ("tilt", "azimuthal", "twist", "sample_tilt")


@pytest.fixture(scope="module")
def geometry():
    """A non-square, binned detector with all four angles non-zero."""
    return MapGeometry(
        pc=(0.512345678901, 0.2712345, 0.6234567),
        shape=(60, 80),
        px_size=70.0,
        binning=6.0,
        step_sizes=(20.0, 25.0),
        navigation_shape=(3, 4),
        tilt=2.3,
        azimuthal=0.37,
        sample_tilt=69.8,
        twist=0.11,
    )


def assert_same_detector(new: EBSDDetector, old: EBSDDetector, tol=ROUND_TRIP_TOL):
    assert new.shape == old.shape
    assert new.navigation_shape == old.navigation_shape
    assert new.px_size == old.px_size
    assert new._binning == old._binning
    for a in ANGLES:
        assert abs(getattr(new, a) - getattr(old, a)) <= tol, a
    assert np.abs(new.pc - old.pc).max() <= tol


# --------------------------------------------------------------------- #
# Conversions against kikuchipy's documented values
# --------------------------------------------------------------------- #


@pytest.mark.parametrize(
    "convention, expected",
    [
        # The examples in kikuchipy's EBSDDetector.pc_emsoft/pc_tsl docstrings
        ("emsoft5", [64.0, 144.0, 17049.6]),
        ("emsoft", [64.0, 144.0, 17049.6]),
        ("emsoft4", [-64.0, 144.0, 17049.6]),
        # TSL z* is in units of min(width, height), here the height
        ("tsl", [0.4, 0.8, 0.6]),
        ("edax", [0.4, 0.8, 0.6]),
        ("bruker", [0.4, 0.2, 0.6]),
        # Oxford: fractions of the width from the lower left
        ("oxford", [0.4, (1 - 0.2) * 60 / 80, 0.6 * 60 / 80]),
    ],
)
def test_pc_in_convention_matches_kikuchipy_examples(convention, expected):
    det = EBSDDetector((60, 80), pc=(0.4, 0.2, 0.6), px_size=59.2, binning=8)
    np.testing.assert_allclose(cv.pc_in_convention(det, convention)[0], expected, rtol=1e-12)


def test_convention_names():
    assert [cv.convention_name(n) for n in ("Bruker", "EDAX", "amatek", "AZtec", "emsoft")] == [
        "bruker",
        "tsl",
        "tsl",
        "oxford",
        "emsoft5",
    ]
    with pytest.raises(ValueError, match="Unknown PC convention"):
        cv.convention_name("hough")


# --------------------------------------------------------------------- #
# Round trips
# --------------------------------------------------------------------- #


@pytest.mark.parametrize("convention", cv.CONVENTIONS)
def test_detector_file_round_trip(tmp_path, geometry, convention):
    det = geometry.detector()
    path = cv.save_detector(det, tmp_path / f"detector_{convention}.txt", convention)
    # The file really is in the convention: its columns are kikuchipy's
    # conversion, and the header records convention and kikuchipy version
    cols = np.loadtxt(path)
    np.testing.assert_allclose(
        cols, cv.pc_in_convention(det, convention).reshape(-1, 3), rtol=1e-15, atol=1e-12
    )
    header = cv.read_detector_header(path)
    assert header["convention"] == convention
    assert header["kikuchipy version"] == kikuchipy.__version__
    assert header["navigation_shape"] == "(3, 4)"
    new = cv.load_detector(path)
    assert_same_detector(new, det)
    # kikuchipy's own reader agrees (the file is plain kikuchipy format)
    assert_same_detector(EBSDDetector.load(path), det)
    # Atomic writing leaves no temporary file behind
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_default_kikuchipy_precision_would_not_round_trip(tmp_path, geometry):
    """Why save_detector writes 17 digits: kikuchipy's "%.7f" rounds a
    Bruker PC by up to 5e-8."""
    det = geometry.detector()
    det.save(tmp_path / "k.txt", convention="bruker")
    lossy = EBSDDetector.load(tmp_path / "k.txt")
    exact = cv.load_detector(cv.save_detector(det, tmp_path / "g.txt", "bruker"))
    assert np.abs(lossy.pc - det.pc).max() > ROUND_TRIP_TOL
    assert np.abs(exact.pc - det.pc).max() < 1e-15


@pytest.mark.parametrize("convention", cv.CONVENTIONS)
def test_record_round_trip_through_json(geometry, convention):
    rec = cv.export_geometry(geometry, convention)
    assert rec["convention"] == convention
    assert rec["kikuchipy_version"] == kikuchipy.__version__
    assert {a: rec[a] for a in ANGLES} == {a: getattr(geometry, a) for a in ANGLES}
    rec = json.loads(json.dumps(rec))
    new = cv.import_geometry(rec)
    assert_same_detector(new, geometry.detector(points=np.array([geometry.reference])))


@pytest.mark.parametrize("convention", cv.CONVENTIONS)
def test_patterns_from_reimported_detector_equal_originals(tmp_path, si_mp, geometry, convention):
    det = geometry.detector()
    rot = _rotations(det.navigation_size)
    before = simulation.simulate_patterns(si_mp, rot, det, 20)
    new = cv.load_detector(cv.save_detector(det, tmp_path / "d.txt", convention))
    after = simulation.simulate_patterns(si_mp, rot, new, 20)
    assert np.abs(after - before).max() <= 1e-6 * np.abs(before).max()
    # And through a record, at the reference PC
    one = geometry.detector(points=np.array([geometry.reference]))
    a = simulation.simulate_patterns(si_mp, rot[:2], one, 20)
    b = simulation.simulate_patterns(
        si_mp, rot[:2], cv.import_geometry(cv.export_geometry(geometry, convention)), 20
    )
    assert np.abs(a - b).max() <= 1e-6 * np.abs(a).max()


def _rotations(n):
    rng = np.random.default_rng(3)
    q = rng.normal(size=(n, 4))
    return Rotation(q / np.linalg.norm(q, axis=1, keepdims=True))


# --------------------------------------------------------------------- #
# Vendor fields, as kikuchipy's readers interpret them
# --------------------------------------------------------------------- #


def _as_kikuchipy_reader_would(conv, f, rec):
    """Build the detector from vendor fields the way kikuchipy 0.13's
    vendor readers do (bruker_h5ebsd, edax_h5ebsd, oxford_h5ebsd,
    emsoft_ebsd _api.py)."""
    shape = tuple(rec["shape"])
    if conv == "bruker":
        return EBSDDetector(
            shape,
            px_size=rec["px_size"],
            binning=rec["binning"],
            tilt=f["CameraTilt"],
            sample_tilt=f["Sample Tilt"],
            pc=(f["PCX"], f["PCY"], f["DD"]),
        )
    if conv == "tsl":
        return EBSDDetector(
            shape,
            px_size=rec["px_size"],
            binning=rec["binning"],
            tilt=f["Camera Elevation Angle"],
            azimuthal=f["Camera Azimuthal Angle"],
            sample_tilt=f["Sample Tilt"],
            pc=(f["x-star"], f["y-star"], f["z-star"]),
            convention="edax",
        )
    if conv == "oxford":
        return EBSDDetector(
            shape,
            px_size=rec["px_size"],
            binning=rec["binning"],
            pc=(f["Pattern Center X"], f["Pattern Center Y"], f["Detector Distance"]),
            sample_tilt=np.rad2deg(f["Tilt Angle (rad)"]),
            tilt=np.rad2deg(f["Detector Orientation Euler Phi (rad)"]) - 90,
            convention="oxford",
        )
    return EBSDDetector(
        (f["numsy"], f["numsx"]),
        px_size=f["delta"],
        binning=f["binning"],
        tilt=f["thetac"],
        pc=(f["xpc"], f["ypc"], f["L"]),
        sample_tilt=rec["sample_tilt"],
        convention=conv,
    )


@pytest.mark.parametrize("convention", cv.CONVENTIONS)
def test_vendor_fields_read_back_by_kikuchipy_readers(convention):
    geo = MapGeometry(
        pc=(0.49, 0.31, 0.58),
        shape=(60, 80),
        px_size=59.2,
        binning=8,
        step_sizes=(1, 1),
        navigation_shape=(1, 1),
        tilt=4.5,
        azimuthal=0.0,
        sample_tilt=70.2,
    )
    rec = cv.export_geometry(geo, convention)
    # kikuchipy's EMsoft pattern reader takes no sample tilt
    assert rec["not_in_vendor_fields"] == (["sample_tilt"] if "emsoft" in convention else [])
    det = _as_kikuchipy_reader_would(convention, rec["vendor_fields"], rec)
    assert_same_detector(det, cv.import_geometry(rec), tol=1e-9)


def test_lost_angles_are_listed(geometry):
    lost = {c: cv.export_geometry(geometry, c)["not_in_vendor_fields"] for c in cv.CONVENTIONS}
    assert lost["bruker"] == ["azimuthal", "twist"]
    assert lost["tsl"] == ["twist"]
    assert lost["oxford"] == ["azimuthal", "twist"]
    assert lost["emsoft5"] == ["azimuthal", "twist", "sample_tilt"]


# --------------------------------------------------------------------- #
# kikuchipy < 0.12 wrote the opposite azimuthal sign
# --------------------------------------------------------------------- #


def test_old_kikuchipy_record_flips_azimuthal(geometry):
    rec = cv.export_geometry(geometry, "tsl")
    rec["kikuchipy_version"] = "0.11.5"
    with pytest.warns(UserWarning, match="sign of azimuthal flipped"):
        det = cv.import_geometry(rec)
    assert det.azimuthal == -geometry.azimuthal
    rec["kikuchipy_version"] = "0.13.1"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert cv.import_geometry(rec).azimuthal == geometry.azimuthal


def test_old_kikuchipy_detector_file_flips_azimuthal(tmp_path, geometry):
    path = cv.save_detector(geometry.detector(), tmp_path / "d.txt", "bruker")
    text = path.read_text().replace(
        f"kikuchipy version: {kikuchipy.__version__}", "kikuchipy version: 0.11.5"
    )
    path.write_text(text)
    with pytest.warns(UserWarning, match="0.11.5"):
        det = cv.load_detector(path)
    assert det.azimuthal == -geometry.azimuthal


# --------------------------------------------------------------------- #
# Errors
# --------------------------------------------------------------------- #


def test_errors(tmp_path, geometry):
    with pytest.raises(ValueError, match="12 PCs"):
        cv.export_geometry(geometry.detector(), "bruker")
    with pytest.raises(FileNotFoundError):
        cv.load_detector(tmp_path / "missing.txt")
    (tmp_path / "other.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="not a kikuchipy detector file"):
        cv.load_detector(tmp_path / "other.txt")
    with pytest.raises(ValueError, match="three finite"):
        cv.import_geometry({"convention": "bruker", "pc": [0.5, np.nan, 0.5], "shape": [60, 60]})
