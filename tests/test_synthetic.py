import numpy as np
import pytest
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation
from orix.vector import Vector3d

from kikuchipy_geomdic import synthetic
from kikuchipy_geomdic.simulation import simulate_patterns


@pytest.fixture(scope="module")
def clean(si_mp):
    return synthetic.synthetic_map(si_mp, (4, 5), shape=(48, 48), seed=3)


class TestMasterPattern:
    @pytest.mark.parametrize("name", ["Si", "BaTiO3"])
    @pytest.mark.parametrize("kind", ["dynamical", "kinematical"])
    def test_lambert_both(self, name, kind):
        mp = synthetic.master_pattern(name, kind=kind, half_size=40)
        assert mp.projection == "lambert"
        assert mp.hemisphere == "both"
        assert mp.data.shape[0] == 2
        assert kind in mp.metadata.General.title
        assert np.isfinite(mp.data).all() and mp.data.std() > 0

    def test_kinematical_si_has_no_forbidden_200(self):
        # Without sanitise_phase, Si gets a non-zero F(200) (field notes)
        from diffsims.crystallography import ReciprocalLatticeVector

        g = ReciprocalLatticeVector(synthetic.phase("Si"), hkl=[[2, 0, 0], [1, 1, 1]])
        g.sanitise_phase()
        g.calculate_structure_factor()
        f = np.abs(g.structure_factor)
        assert f[0] < 1e-6 * f[1]

    def test_any_phase(self):
        p = synthetic.phase("Si")
        mp = synthetic.master_pattern(p, half_size=30)
        assert mp.phase.point_group.name == "m-3m"
        with pytest.raises(ValueError, match="Dynamical"):
            synthetic.master_pattern(p, kind="dynamical")

    def test_bad_names(self):
        with pytest.raises(ValueError, match="Unknown phase"):
            synthetic.master_pattern("Fe")
        with pytest.raises(ValueError, match="kind"):
            synthetic.master_pattern("Si", kind="hybrid")

    def test_returns_copies(self):
        a = synthetic.master_pattern("Si")
        a.data[:] = 0
        assert synthetic.master_pattern("Si").data.max() > 0


class TestVariants:
    def test_c_axes(self):
        ops = synthetic.variant_operators()
        # The crystal c axis of each variant, in the parent's crystal frame
        c = (~ops * Vector3d.zvector()).data
        expected = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]
        assert np.allclose(c, expected, atol=1e-12)

    def test_variant_map(self, bto_mp):
        sm = synthetic.synthetic_map(
            bto_mp, (6, 7), orientations="variants", shape=(32, 32), scatter=0, seed=2
        )
        v = sm.xmap.prop["variant"]
        assert set(v) == set(range(6))
        parent = sm.xmap.rotations[v == 0][0]
        ops = synthetic.variant_operators()
        for k in range(6):
            expected = ops[k] * parent
            got = sm.xmap.rotations[v == k]
            assert np.allclose(np.abs((got * ~expected).a), 1, atol=1e-9)


class TestSyntheticMap:
    def test_truth_matches_simulation(self, si_mp, clean):
        # Simulating at the true geometry and orientations reproduces the
        # noise-free map exactly
        sim = simulate_patterns(si_mp, clean.xmap.rotations, clean.detector, 20)
        assert np.array_equal(sim, clean.signal.data.reshape(sim.shape))

    def test_pc_field_varies_realistically(self, clean):
        pc = clean.detector.pc
        # About 1.5 % of the detector width across 500 um
        assert 0.01 < np.ptp(pc[..., 0]) < 0.02
        assert np.ptp(pc[..., 2]) > 0.003  # 375 um along the tilted rows

    def test_start_is_perturbed(self, clean):
        d = clean.start_geometry.values() - clean.geometry.values()
        expected = [synthetic.DEFAULT_PERTURBATION.get(n, 0) for n in clean.geometry.as_dict()]
        assert np.allclose(d, expected)
        mis = (clean.start_xmap.rotations * ~clean.xmap.rotations).angle
        rms = np.sqrt(np.mean(np.rad2deg(mis) ** 2))
        assert 0.15 < rms < 0.45  # 0.3 deg RMS requested, 20 samples

    def test_signal_carries_start(self, clean):
        assert np.allclose(clean.signal.detector.pc, clean.start_detector.pc)
        assert clean.signal.xmap.shape == (4, 5)
        assert clean.signal.axes_manager["x"].scale == clean.geometry.step_sizes[1]

    def test_reproducible_and_lazy(self, si_mp):
        kw = dict(navigation_shape=(3, 4), shape=(40, 40), dose=100, blur=0.7, background=0.5)
        a = synthetic.synthetic_map(si_mp, seed=5, **kw)
        b = synthetic.synthetic_map(si_mp, seed=5, lazy=True, **kw)
        c = synthetic.synthetic_map(si_mp, seed=6, **kw)
        assert np.array_equal(a.signal.data, b.signal.data.compute())
        assert not np.array_equal(a.signal.data, c.signal.data)
        assert np.allclose(
            (a.xmap.rotations * ~b.xmap.rotations).angle, 0, atol=1e-12
        )

    def test_noise_at_dose(self, si_mp):
        sm = synthetic.synthetic_map(si_mp, (2, 2), shape=(40, 40), dose=50, seed=0)
        assert np.isclose(sm.signal.data.mean(), 50, rtol=0.05)
        assert np.array_equal(sm.signal.data, np.round(sm.signal.data))

    def test_single_crystal_scatter(self, si_mp):
        sm = synthetic.synthetic_map(
            si_mp, (4, 4), orientations="single", scatter=0.1, shape=(32, 32), seed=0
        )
        r = sm.xmap.rotations
        mis = np.rad2deg((r * ~r[0]).angle)
        assert mis.max() < 1.0 and mis[1:].min() > 0

    def test_bad_input(self, si_mp):
        with pytest.raises(ValueError, match="orientations"):
            synthetic.synthetic_map(si_mp, (2, 2), orientations="textured")
        with pytest.raises(ValueError, match="navigation_shape"):
            synthetic.synthetic_map(si_mp, (2, 2), geometry=synthetic.default_geometry((3, 3)))
        with pytest.raises(ValueError, match="lambert"):
            stereo = EBSDMasterPattern(si_mp.data, projection="stereographic")
            synthetic.synthetic_map(stereo, (2, 2))


def test_degrade_is_identity_when_off():
    p = np.random.default_rng(0).random((2, 8, 8)).astype(np.float32)
    assert np.array_equal(synthetic.degrade_patterns(p), p)


def test_perturb_rotations_rms():
    r = Rotation.identity(4000)
    p = synthetic.perturb_rotations(r, 0.3, 0)
    rms = np.sqrt(np.mean(np.rad2deg(p.angle) ** 2))
    assert abs(rms - 0.3) < 0.01
