import numpy as np
import pytest
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation
from orix.vector import Vector3d

from kikuchipy_geomdic.geometry import rotation_vectors
from kikuchipy_geomdic.indexing.variants import variant_operators
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.orientations import (
    STRIPE_VARIANTS,
    common_rotation,
    perturb_rotations,
)


@pytest.fixture(scope="module")
def clean(si_mp):
    return synthetic.synthetic_map(si_mp, (4, 5), shape=(48, 48), seed=3)


class TestVariants:
    def test_c_axes(self):
        ops = variant_operators()
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
        ops = variant_operators()
        for k in range(6):
            expected = ops[k] * parent
            got = sm.xmap.rotations[v == k]
            assert np.allclose(np.abs((got * ~expected).a), 1, atol=1e-9)

    @pytest.fixture(scope="class")
    @classmethod
    def stripes(cls, bto_mp):
        return synthetic.synthetic_map(
            bto_mp,
            (6, 7),
            orientations="stripes",
            shape=(32, 32),
            scatter=0.2,
            orientation_error=0.3,
            seed=4,
        )

    def test_stripes_layout(self, stripes):
        v = stripes.xmap.prop["variant"].reshape(6, 7)
        # Along the diagonal the stripes run through STRIPE_VARIANTS in
        # order, each a band of whole diagonals
        diag = np.add.outer(np.arange(6), np.arange(7))
        per_diag = [set(v[diag == d]) for d in range(diag.max() + 1)]
        assert all(len(x) == 1 for x in per_diag)
        runs = [x.pop() for x in per_diag]
        runs = [k for i, k in enumerate(runs) if i == 0 or k != runs[i - 1]]
        assert runs == list(STRIPE_VARIANTS)
        ops = variant_operators()
        # Both kinds of wall: a 90 deg and a 180 deg domain next to the parent
        angles = np.rad2deg(ops[np.unique(v)].angle)
        assert np.allclose(sorted(angles), [0, 90, 180])

    def test_stripes_truth_is_variant_of_parent(self, stripes):
        ops = variant_operators()
        v = stripes.xmap.prop["variant"]
        rot = stripes.xmap.rotations
        # Undoing each point's variant leaves one parent up to the scatter
        # (0.2 deg RMS per point, so pairs differ by about 0.3 deg RMS)
        parent = ~ops[v] * rot
        mis = np.rad2deg((parent * ~parent[0]).angle)
        assert mis.max() < 1.5
        # Without undoing it, the domains are 90 or 180 deg away
        raw = np.rad2deg((rot * ~parent[0]).angle)
        assert np.all(np.abs(raw - np.rad2deg(ops[v].angle)) < 1.5)

    def test_stripes_start_is_one_variant(self, stripes):
        ops = variant_operators()
        v = stripes.xmap.prop["variant"]
        assert not stripes.start_xmap.prop["variant"].any()
        assert np.array_equal(
            stripes.signal.xmap.prop["variant"], stripes.start_xmap.prop["variant"]
        )
        start = stripes.start_xmap.rotations
        # The start is the parent's variant of the truth, 0.3 deg RMS off
        mis = np.rad2deg((start * ~(~ops[v] * stripes.xmap.rotations)).angle)
        assert 0.15 < np.sqrt(np.mean(mis**2)) < 0.45
        # so in the 90 and 180 deg domains it is the wrong variant
        wrong = np.rad2deg((start * ~stripes.xmap.rotations).angle)
        assert np.all(wrong[v != 0] > 89) and np.all(wrong[v == 0] < 1.5)

    def test_stripes_patterns_show_the_variants(self, bto_mp, stripes):
        # The map's patterns are simulated with the true variants: they
        # differ from those of the same orientations in the parent's
        # variant in the 90 deg domain, and a little in the 180 deg one
        ops = variant_operators()
        v = stripes.xmap.prop["variant"]
        data = stripes.signal.data.reshape(v.size, 32, 32)
        det = stripes.detector
        assert np.array_equal(data, simulate_patterns(bto_mp, stripes.xmap.rotations, det, 20))
        one_variant = simulate_patterns(bto_mp, ~ops[v] * stripes.xmap.rotations, det, 20)
        ncc = _ncc(data, one_variant)
        assert np.allclose(ncc[v == 0], 1)
        assert ncc[v == 2].max() < 0.9
        assert ncc[v == 1].max() < 0.999

    def test_batio3_master_pattern_tells_variants_apart(self, bto_mp):
        # 120 px patterns at 10 random orientations, realistic detector:
        # NCC of each variant's pattern with the parent's
        rng = np.random.default_rng(11)
        q = rng.normal(size=(10, 4))
        r = Rotation(q / np.linalg.norm(q, axis=1, keepdims=True))
        from kikuchipy.detectors import EBSDDetector

        det = EBSDDetector((120, 120), pc=(0.5, 0.3, 0.6), sample_tilt=70)
        ops = variant_operators()
        p0 = simulate_patterns(bto_mp, r, det, 20)
        ncc = np.array([_ncc(simulate_patterns(bto_mp, op * r, det, 20), p0) for op in ops[1:]])
        # 90 deg variants (c axis swapped, c/a = 1.011): measured 0.70-0.80
        # (mean 0.74); an earlier, coarse 129 x 129 ebsdsim pattern 0.77-0.80
        assert ncc[1:].max() < 0.85 and ncc[1:].mean() < 0.8
        # 180 deg variant (polarity only, dynamical intensities): measured
        # 0.987-0.994 (mean 0.990; ebsdsim: 0.995). 1 means identical
        # hemispheres (no polarity), far lower a damaged pattern
        assert 0.97 < ncc[0].min() and ncc[0].max() < 0.998


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
        assert np.allclose((a.xmap.rotations * ~b.xmap.rotations).angle, 0, atol=1e-12)

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


# --------------------------------------------------------------------- #
# Start models
# --------------------------------------------------------------------- #

S = 0.3  # orientation_error, deg
NAV = (7, 7)
N = NAV[0] * NAV[1]


def _start_map(si_mp, start, seed=4, **kw):
    return synthetic.synthetic_map(
        si_mp, NAV, shape=(60, 60), orientation_error=S, start=start, seed=seed, **kw
    )


@pytest.fixture(scope="module")
def starts(si_mp):
    return {start: _start_map(si_mp, start) for start in synthetic.START_MODELS}


def _ncc(a, b):
    a = a - a.mean(axis=(1, 2), keepdims=True)
    b = b - b.mean(axis=(1, 2), keepdims=True)
    return (a * b).sum(axis=(1, 2)) / np.sqrt((a * a).sum(axis=(1, 2)) * (b * b).sum(axis=(1, 2)))


class TestStartModels:
    def test_same_truth_and_patterns(self, starts):
        ref = starts["centred"]
        for start, sm in starts.items():
            assert sm.start == start
            assert np.array_equal(sm.signal.data, ref.signal.data)
            assert np.allclose(sm.xmap.rotations.data, ref.xmap.rotations.data, atol=0)
            assert np.allclose(sm.signal.xmap.rotations.data, sm.start_xmap.rotations.data)
            assert sm.start_xmap.phases[0].name == "Si"

    def test_centred_has_no_common_rotation(self, starts):
        sm = starts["centred"]
        angle, axis = common_rotation(sm.start_xmap, sm.xmap)
        assert angle < 1e-9
        mis = np.rad2deg(sm.start_xmap.rotations.angle)
        assert mis.size == N

    def test_uncentred_common_part_is_random_mean(self, starts):
        sm = starts["uncentred"]
        angle, _ = common_rotation(sm.start_xmap, sm.xmap)
        # One draw of |mean| of N vectors of RMS length S: about S / sqrt(N)
        assert 0.1 * S / np.sqrt(N) < angle < 4 * S / np.sqrt(N)
        # The same draws as "centred", not centred
        c = starts["centred"]
        v_c = rotation_vectors(~c.xmap.rotations * c.start_xmap.rotations)
        v_u = rotation_vectors(~sm.xmap.rotations * sm.start_xmap.rotations)
        assert np.allclose(v_u - v_u.mean(axis=0), v_c, atol=1e-12)

    def test_uncentred_common_part_statistics(self):
        # RMS of the common angle over many draws is S / sqrt(N)
        truth = Rotation.identity(N)
        rng = np.random.default_rng(0)
        angles = [
            common_rotation(perturb_rotations(truth, S, rng, centred=False), truth).angle
            for _ in range(400)
        ]
        rms = np.sqrt(np.mean(np.square(angles)))
        assert abs(rms / (S / np.sqrt(N)) - 1) < 0.12

    def test_indexed_absorbs_the_geometry_error(self, si_mp, starts):
        sm = starts["indexed"]
        biased = common_rotation(sm.start_xmap, sm.xmap).angle
        assert biased > 3 * S / np.sqrt(N)
        # At the true geometry, refinement removes the common part instead
        at_truth = _start_map(si_mp, "indexed", perturbation={})
        unbiased = common_rotation(at_truth.start_xmap, at_truth.xmap).angle
        assert unbiased < 0.1 * S / np.sqrt(N)
        assert unbiased < 0.05 * biased
        assert np.allclose(at_truth.start_detector.pc, at_truth.detector.pc)

    def test_indexed_is_refined(self, si_mp, starts):
        # The indexed orientations fit the patterns at the starting detector
        # better than the "uncentred" start they were refined from
        exp = starts["indexed"].signal.data.reshape(N, 60, 60)
        det = starts["indexed"].start_detector
        ncc = {}
        for start in ("uncentred", "indexed"):
            sim = simulate_patterns(si_mp, starts[start].start_xmap.rotations, det, 20)
            ncc[start] = _ncc(sim, exp)
        assert np.all(ncc["indexed"] >= ncc["uncentred"] - 1e-6)
        assert ncc["indexed"].mean() > ncc["uncentred"].mean() + 0.05

    @pytest.mark.parametrize("start", synthetic.START_MODELS)
    def test_seeded(self, si_mp, starts, start):
        first = starts[start].start_xmap.rotations.data
        again = _start_map(si_mp, start)
        assert np.array_equal(again.start_xmap.rotations.data, first)
        other = _start_map(si_mp, start, seed=5)
        assert not np.allclose(other.start_xmap.rotations.data, first)

    def test_indexed_lazy_and_noisy(self, si_mp):
        kw = dict(navigation_shape=(3, 4), shape=(40, 40), dose=200, start="indexed", seed=1)
        a = synthetic.synthetic_map(si_mp, **kw)
        b = synthetic.synthetic_map(si_mp, lazy=True, **kw)
        assert b.signal._lazy
        assert np.array_equal(a.start_xmap.rotations.data, b.start_xmap.rotations.data)
        assert common_rotation(a.start_xmap, a.xmap).angle > 0.3

    def test_bad_start(self, si_mp):
        with pytest.raises(ValueError, match="start"):
            synthetic.synthetic_map(si_mp, (2, 2), start="indexd")


# --------------------------------------------------------------------- #
# Nickel: two simulators
# --------------------------------------------------------------------- #


class TestNickel:
    def test_phase(self):
        p = master_patterns.phase("nickel")
        assert p.name == "Ni" and p.point_group.name == "m-3m"
        assert np.allclose(p.structure.lattice.abcABG(), [3.524] * 3 + [90] * 3)

    def test_dynamical_file(self):
        from importlib import resources

        path = resources.files("kikuchipy_geomdic") / "data" / "Ni_dynamical.npz"
        with resources.as_file(path) as f:
            npz = np.load(f)
            assert npz["data"].shape == (2, 201, 201)
            assert float(npz["energy"]) == 20
            assert "ebsdsim 0.2.4" in str(npz["source"])
            # The CIF the simulation used: the package's, nickel's lattice
            assert "a = 3.524" in str(npz["cif"])
        mp = master_patterns.master_pattern("Ni")
        assert mp.metadata.General.title == "Ni dynamical (ebsdsim 0.2.4)"
        # Centrosymmetric: both hemispheres equal
        assert np.array_equal(mp.data[0], mp.data[1])

    def test_emsoft_master_pattern(self):
        mp = master_patterns.master_pattern("Ni", kind="emsoft")
        assert (mp.projection, mp.hemisphere) == ("lambert", "both")
        assert mp.data.shape == (2, 401, 401) and mp.data.dtype == np.float32
        assert "EMsoft" in mp.metadata.General.title
        # The package's phase (angstrom), not kikuchipy's (nm)
        assert mp.phase.structure.lattice.a == 3.524
        mp.data[:] = 0
        assert master_patterns.master_pattern("Ni", kind="emsoft").data.max() > 0

    def test_simulators_agree_but_differ(self):
        emsoft = master_patterns.master_pattern("Ni", kind="emsoft")
        ebsdsim = master_patterns.master_pattern("Ni")
        sm = synthetic.synthetic_map(emsoft, (2, 3), shape=(60, 60), seed=7)
        assert sm.xmap.phases[0].point_group.name == ebsdsim.phase.point_group.name == "m-3m"
        other = simulate_patterns(ebsdsim, sm.xmap.rotations, sm.detector, 20)
        ncc = _ncc(other, sm.signal.data.reshape(other.shape))
        assert np.all(ncc > 0.5)
        assert np.all(ncc < 0.99)
        # Unrelated orientations do not correlate
        rnd = simulate_patterns(ebsdsim, Rotation.random(6), sm.detector, 20)
        assert np.all(np.abs(_ncc(rnd, sm.signal.data.reshape(other.shape))) < 0.3)

    def test_kikuchipy_refines_across_simulators(self):
        # A map simulated from the EMsoft pattern refines with kikuchipy
        # against the ebsdsim one: the phases are identical to kikuchipy
        import contextlib
        import io

        emsoft = master_patterns.master_pattern("Ni", kind="emsoft")
        ebsdsim = master_patterns.master_pattern("Ni")
        sm = synthetic.synthetic_map(emsoft, (2, 2), shape=(60, 60), perturbation={}, seed=3)
        with contextlib.redirect_stdout(io.StringIO()):
            ref = sm.signal.refine_orientation(sm.start_xmap, sm.detector, ebsdsim, 20)
        assert np.all(ref.scores > 0.8)
        err = np.rad2deg((ref.rotations * ~sm.xmap.rotations).angle)
        start_err = np.rad2deg((sm.start_xmap.rotations * ~sm.xmap.rotations).angle)
        assert err.mean() < start_err.mean()
