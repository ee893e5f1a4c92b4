"""Tests of the shipped and computed master patterns and their phases."""

import numpy as np
import pytest

from kikuchipy_geomdic.validation import master_patterns


class TestMasterPattern:
    @pytest.mark.parametrize("name", ["Si", "BaTiO3", "Ni"])
    @pytest.mark.parametrize("kind", ["dynamical", "kinematical"])
    def test_lambert_both(self, name, kind):
        mp = master_patterns.master_pattern(name, kind=kind, half_size=40)
        assert mp.projection == "lambert"
        assert mp.hemisphere == "both"
        assert mp.data.shape[0] == 2
        assert kind in mp.metadata.General.title
        assert np.isfinite(mp.data).all() and mp.data.std() > 0

    def test_kinematical_si_has_no_forbidden_200(self):
        # Without sanitise_phase, Si gets a non-zero F(200), a reflection the
        # diamond structure forbids
        from diffsims.crystallography import ReciprocalLatticeVector

        g = ReciprocalLatticeVector(master_patterns.phase("Si"), hkl=[[2, 0, 0], [1, 1, 1]])
        g.sanitise_phase()
        g.calculate_structure_factor()
        f = np.abs(g.structure_factor)
        assert f[0] < 1e-6 * f[1]

    def test_any_phase(self):
        p = master_patterns.phase("Si")
        mp = master_patterns.master_pattern(p, half_size=30)
        assert mp.phase.point_group.name == "m-3m"
        with pytest.raises(ValueError, match="Dynamical"):
            master_patterns.master_pattern(p, kind="dynamical")

    def test_bad_names(self):
        with pytest.raises(ValueError, match="Unknown phase"):
            master_patterns.master_pattern("Fe")
        with pytest.raises(ValueError, match="kind"):
            master_patterns.master_pattern("Si", kind="hybrid")
        with pytest.raises(ValueError, match="EMsoft"):
            master_patterns.master_pattern("Si", kind="emsoft")
        with pytest.raises(ValueError, match="20 kV"):
            master_patterns.master_pattern("Ni", kind="emsoft", energy=15)

    def test_batio3_file(self):
        from importlib import resources

        data = resources.files("kikuchipy_geomdic") / "data"
        with resources.as_file(data / "BaTiO3_dynamical.npz") as f:
            npz = np.load(f)
            assert npz["data"].shape == (2, 801, 801) and npz["data"].dtype == np.float16
            assert float(npz["energy"]) == 20
            assert "de-ebsd 0.2.1 (GPL-3.0-or-later)" in str(npz["source"])
            # Simulated from the CIF the package's phase is read from
            assert str(npz["cif"]) == (data / "BaTiO3.cif").read_text()
        mp = master_patterns.master_pattern("BaTiO3")
        assert mp.metadata.General.title == "BaTiO3 dynamical (de-ebsd 0.2.1)"
        assert mp.data.dtype == np.float32
        north, south = mp.data
        # The square's edges are the equator, seen from both hemispheres
        for edge in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1]):
            assert np.array_equal(north[edge], south[edge])
        # 4mm has no inversion: the hemispheres differ inside
        assert np.abs(north - south).mean() > 0.05 * north.std()

    def test_ebsdsim_kind(self):
        other = master_patterns.master_pattern("BaTiO3", kind="ebsdsim")
        assert other.data.shape == (2, 401, 401)
        assert other.metadata.General.title == "BaTiO3 dynamical (ebsdsim 0.2.4)"
        # Si's (and Ni's) dynamical master pattern is ebsdsim's already
        si = master_patterns.master_pattern("Si", kind="ebsdsim")
        assert np.array_equal(si.data, master_patterns.master_pattern("Si").data)
        with pytest.raises(ValueError, match="20 kV"):
            master_patterns.master_pattern("BaTiO3", kind="ebsdsim", energy=15)

    def test_returns_copies(self):
        a = master_patterns.master_pattern("Si")
        a.data[:] = 0
        assert master_patterns.master_pattern("Si").data.max() > 0


def test_stretched_master_pattern_moves_the_bands_with_the_c_axis():
    from kikuchipy_geomdic.indexing import orientation as ori

    mp = master_patterns.master_pattern("BaTiO3", kind="ebsdsim")
    same = master_patterns.stretched(mp, 1.0)
    assert np.corrcoef(same.data.ravel(), mp.data.ravel())[0, 1] > 0.9999
    flat = master_patterns.stretched(mp, 0.99)
    assert flat.phase.structure.lattice.c == pytest.approx(0.99 * mp.phase.structure.lattice.c)
    assert mp.phase.structure.lattice.c == pytest.approx(4.0365)  # not mutated
    # Patterns of the stretched crystal are those projected at the stretch
    from kikuchipy.detectors import EBSDDetector
    from orix.quaternion import Rotation

    q = Rotation.from_euler(np.deg2rad([[10, 35, 60]])).data
    pc, om = np.array([[0.5, 0.3, 0.6]]), ori.detector_matrix(EBSDDetector(sample_tilt=70))
    arrays = ori.master_pattern_arrays(mp, 20)
    at = ori.project_arrays(
        q, pc, om, ori.MasterPatternArrays(arrays.upper, arrays.lower, stretch=0.99), (60, 60)
    )
    of = ori.project_arrays(q, pc, om, ori.master_pattern_arrays(flat, 20), (60, 60))
    cif = ori.project_arrays(q, pc, om, arrays, (60, 60))
    # (resampled twice, the bands a little smoothed: 0.97)
    assert np.corrcoef(at.ravel(), of.ravel())[0, 1] > 0.95
    assert (
        np.corrcoef(cif.ravel(), of.ravel())[0, 1]
        < np.corrcoef(at.ravel(), of.ravel())[0, 1] - 0.03
    )
    with pytest.raises(ValueError, match="stretch"):
        master_patterns.stretched(mp, 0)


class TestIron:
    """Ferrite, austenite and bct martensite: ebsdsim's (the calibration's)
    and de-ebsd's (the other simulator of test data) master patterns."""

    @pytest.mark.parametrize(
        "name, alias, point_group, c",
        [
            ("Fe_bcc", "ferrite", "m-3m", 2.8665),
            ("Fe_fcc", "austenite", "m-3m", 3.60),
            ("Fe_bct", "martensite", "4/mmm", 2.92125),
        ],
    )
    def test_phases(self, name, alias, point_group, c):
        p = master_patterns.phase(alias)
        assert p.name == name == master_patterns.phase(name.upper()).name
        assert p.point_group.name == point_group
        assert p.structure.lattice.c == pytest.approx(c)

    @pytest.mark.parametrize("name", ["Fe_bcc", "Fe_fcc", "Fe_bct"])
    def test_files_and_projection(self, name):
        from importlib import resources

        from kikuchipy.detectors import EBSDDetector
        from orix.quaternion import Rotation

        data = resources.files("kikuchipy_geomdic") / "data"
        cif = (data / f"{name}.cif").read_text()
        det = EBSDDetector((40, 40), pc=(0.5, 0.3, 0.6), sample_tilt=70)
        rot = Rotation.from_euler(np.deg2rad([[10, 35, 60], [200, 80, 5]]))
        projected = []
        for kind, simulator in (("dynamical", "ebsdsim 0.2.4"), ("de-ebsd", "de-ebsd 0.2.1")):
            mp = master_patterns.master_pattern(name, kind=kind)
            assert mp.metadata.General.title == f"{name} dynamical ({simulator})"
            assert mp.phase.name == name and mp.data.dtype == np.float32
            assert mp.projection == "lambert" and mp.hemisphere == "both"
            # Centrosymmetric: both hemispheres alike
            assert np.allclose(mp.data[0], mp.data[1], rtol=1e-3)
            stem = "dynamical" if kind == "dynamical" else "deebsd"
            with resources.as_file(data / f"{name}_{stem}.npz") as f:
                npz = np.load(f)
                assert str(npz["cif"]) == cif and float(npz["energy"]) == 20
                assert simulator.split()[0] in str(npz["source"])
            p = mp.get_patterns(rot, det, energy=20, compute=True, show_progressbar=False)
            projected.append(np.asarray(p, dtype=float).reshape(2, -1))
        # The two simulators show the same bands at the same orientation
        for a, b in zip(*projected, strict=True):
            assert np.corrcoef(a, b)[0, 1] > 0.6

    def test_kinds(self):
        a = master_patterns.master_pattern("ferrite")
        assert np.array_equal(
            a.data, master_patterns.master_pattern("Fe_bcc", kind="ebsdsim").data
        )
        bto = master_patterns.master_pattern("BaTiO3", kind="de-ebsd")
        assert np.array_equal(bto.data, master_patterns.master_pattern("BaTiO3").data)
        with pytest.raises(ValueError, match="de-ebsd"):
            master_patterns.master_pattern("Ni", kind="de-ebsd")
        with pytest.raises(ValueError, match="20 kV"):
            master_patterns.master_pattern("Fe_bct", kind="de-ebsd", energy=15)
        kin = master_patterns.master_pattern("Fe_bct", kind="kinematical", half_size=30)
        assert kin.phase.point_group.name == "4/mmm"
