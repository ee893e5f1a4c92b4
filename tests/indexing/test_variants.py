"""Tests of :mod:`kikuchipy_geomdic.indexing.variants` (domain maps in the parent
crystal's frame) and of :func:`~kikuchipy_geomdic.plotting.variants.plot_variants`.

The ground truth is a synthetic BaTiO3 stripe map: ``xmap.prop["variant"]``
is each point's true variant index *k* (its orientation is
``variant_operators()[k] * parent`` times a scatter).
"""

from __future__ import annotations

import numpy as np
import pytest
from orix.crystal_map import CrystalMap
from orix.quaternion import Orientation, Rotation, symmetry
from orix.vector import Vector3d

from kikuchipy_geomdic.indexing.variants import (
    VARIANT_NAMES,
    check_pseudo_symmetry,
    domain_labels,
    pseudo_symmetry_operators,
    variant_names,
    variant_operators,
)
from kikuchipy_geomdic.validation import synthetic
from kikuchipy_geomdic.validation.orientations import STRIPE_VARIANTS

OPS = variant_operators()


def _stripes(seed: int, nav=(24, 24), scatter=1.0):
    # Patterns of 20 px: only the orientations matter here
    return synthetic.synthetic_map(
        "BaTiO3", nav, "stripes", shape=(20, 20), scatter=scatter, seed=seed
    )


def _true_parent(sm) -> Rotation:
    """The parent of the truth: the mean of ``~ops[k] * rotation`` (the
    points' scatter averaged out)."""
    q = (~OPS[sm.xmap.prop["variant"]] * sm.xmap.rotations).data
    q = q * np.sign(q @ q[0])[:, None]
    return Rotation(q.mean(axis=0) / np.linalg.norm(q.mean(axis=0)))


def _c_axis_label(rotations: Rotation, parent: Rotation) -> np.ndarray:
    """Independent reference: the crystal's c axis (z) in the parent's
    frame, nearest of the six axes of ``~OPS * z`` (tutorial 03's recipe)."""
    z = Vector3d.zvector()
    c = parent * (~rotations * z)
    return np.argmax(c.dot_outer(~OPS * z), axis=-1).ravel()


def _map_like(xmap: CrystalMap, rotations: Rotation, **kw) -> CrystalMap:
    return CrystalMap(
        rotations=rotations.flatten(), x=xmap.x, y=xmap.y, phase_list=xmap.phases, **kw
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_labels_of_the_truth(seed):
    """True orientations with 1 deg scatter, each replaced by a random
    4mm equivalent and all rotated by one random 1-3 deg rotation: the
    labels are the truth's, from a Rotation, an Orientation and a map."""
    sm = _stripes(seed)
    truth = sm.xmap.prop["variant"]
    assert set(truth.tolist()) == {0, 1, 2}
    pg = sm.xmap.phases[0].point_group
    rng = np.random.default_rng(seed)
    s = Rotation(pg.proper_subgroup)[rng.integers(0, 4, truth.size)]
    common = Rotation.from_axes_angles(rng.normal(size=3), np.deg2rad(rng.uniform(1, 3)))
    rot = s * sm.xmap.rotations * common
    # The equivalents really differ from the truth (not a no-op)
    assert (rot.angle_with(sm.xmap.rotations) > np.deg2rad(45)).mean() > 0.5

    lab = domain_labels(rot, symmetry=pg)
    np.testing.assert_array_equal(lab.label, truth)
    assert lab.chosen and lab.names == VARIANT_NAMES
    np.testing.assert_array_equal(domain_labels(Orientation(rot, symmetry=pg)).label, truth)
    xmap = _map_like(sm.xmap, rot)
    lab_map = domain_labels(xmap)
    np.testing.assert_array_equal(lab_map.label, truth)
    # The parent found is the true one up to the crystal symmetry and the
    # common rotation; the deviations are the scatter
    parent = Orientation(lab.parent, symmetry=pg)
    true_parent = Orientation(_true_parent(sm) * common, symmetry=pg)
    assert parent.angle_with(true_parent, degrees=True)[0] < 0.2
    assert np.nanmax(lab.deviation) < 4  # 1 deg RMS scatter
    assert lab.counts == {n: int((truth == k).sum()) for k, n in enumerate(VARIANT_NAMES)}


@pytest.mark.parametrize("seed", [0, 3])
def test_labels_of_random_variant_starts(seed):
    """Starts in random variants, ``ops[k] * truth``: with the true parent
    given, each point's label is the variant it is in (the c axis of
    ``ops[k] * ops[v] * parent`` in the parent's frame); with the parent
    chosen from the map, the same partition up to one relabelling of the
    whole map."""
    sm = _stripes(seed)
    pg = sm.xmap.phases[0].point_group
    rng = np.random.default_rng(10 + seed)
    k = rng.integers(0, 6, sm.xmap.size)
    start = OPS[k] * sm.xmap.rotations
    expected = _c_axis_label(start, _true_parent(sm))
    assert (expected != sm.xmap.prop["variant"]).mean() > 0.5  # truly scrambled
    assert set(expected.tolist()) == set(range(6))

    lab = domain_labels(start, symmetry=pg, parent=_true_parent(sm))
    np.testing.assert_array_equal(lab.label, expected)
    assert not lab.chosen
    # The same with 4mm equivalents at every point
    s = Rotation(pg.proper_subgroup)[rng.integers(0, 4, k.size)]
    np.testing.assert_array_equal(
        domain_labels(s * start, symmetry=pg, parent=_true_parent(sm)).label, expected
    )
    # A given parent's own 4mm equivalent fixes which in-plane axis is x:
    # 90 deg about c turns +x into +y
    parent = Rotation(pg.proper_subgroup)[1] * _true_parent(sm)
    turned = domain_labels(s * start, symmetry=pg, parent=parent).label
    np.testing.assert_array_equal(turned, _c_axis_label(start, parent))
    np.testing.assert_array_equal(turned, np.array([0, 1, 4, 5, 3, 2])[expected])
    # From the map alone: a bijection between the two labellings
    free = domain_labels(s * start, symmetry=pg).label
    pairs = set(zip(expected.tolist(), free.tolist()))
    assert len(pairs) == 6 and len({a for a, _ in pairs}) == len({b for _, b in pairs}) == 6


def test_polarity_and_crystal_symmetry():
    """+z and -z differ (4mm has no inversion); 4mm equivalents share a
    label; a centrosymmetric or cubic point group is refused."""
    parent = Rotation.from_axes_angles([1, 2, 3], 0.7)
    rot = OPS * parent
    lab = domain_labels(rot, symmetry=symmetry.C4v, parent=parent)
    np.testing.assert_array_equal(lab.label, np.arange(6))
    four = Rotation(symmetry.C4).flatten()
    for s in four:
        np.testing.assert_array_equal(
            domain_labels(s * rot, symmetry=symmetry.C4v, parent=parent).label, np.arange(6)
        )
    # The -z variant is 180 deg from +z about x: with a 4/mmm crystal it is
    # a symmetry, and the label could not show polarity
    with pytest.raises(ValueError, match="operator 0 is the identity times a rotation of "):
        domain_labels(rot, symmetry=symmetry.D4h)
    with pytest.raises(ValueError, match="point group m-3m"):
        check_pseudo_symmetry("BaTiO3", symmetry.Oh)
    with pytest.raises(ValueError, match="The crystal symmetry is needed"):
        domain_labels(rot)
    # Only the 90 deg operator: with 4mm's rotations no group
    with pytest.raises(ValueError, match="do not form a group"):
        domain_labels(rot, OPS[2:3], symmetry=symmetry.C4v)


def test_unusable_points_and_parent_points():
    """Not-indexed points and invalid rotations get -1; *points* restricts
    the parent's choice; the inputs are not modified."""
    sm = _stripes(1, nav=(12, 12))
    truth = sm.xmap.prop["variant"]
    q = sm.xmap.rotations.data.copy()
    q[5] = np.nan
    q[7] = 0
    pid = np.zeros(truth.size, dtype=int)
    pid[9] = -1
    xmap = CrystalMap(
        Rotation(q), phase_id=pid, x=sm.xmap.x, y=sm.xmap.y, phase_list=sm.xmap.phases,
        prop={"variant": truth.copy()},
    )  # fmt: skip
    before = (xmap.rotations.data.copy(), xmap.phase_id.copy(), truth.copy())
    lab = domain_labels(xmap)
    bad = np.zeros(truth.size, dtype=bool)
    bad[[5, 7, 9]] = True
    assert (lab.label[bad] == -1).all() and np.isnan(lab.deviation[bad]).all()
    np.testing.assert_array_equal(lab.label[~bad], truth[~bad])
    np.testing.assert_array_equal(xmap.rotations.data, before[0])
    np.testing.assert_array_equal(xmap.phase_id, before[1])
    np.testing.assert_array_equal(xmap.prop["variant"], before[2])
    # Choosing the parent from the -z domain only makes -z the parent's +z
    minus = domain_labels(xmap, points=truth == 1).label
    assert (minus[~bad & (truth == 1)] == 0).all() and (minus[~bad & (truth == 0)] == 1).all()
    with pytest.raises(ValueError, match="No point to choose the parent from"):
        domain_labels(xmap, points=np.zeros(truth.size, dtype=bool))


def test_pseudo_symmetry_operators(tmp_path):
    ops = OPS[1:]
    for spec in ("BaTiO3", "batio3", ops, ops.data):
        np.testing.assert_allclose(pseudo_symmetry_operators(spec).data, ops.data)
    np.save(tmp_path / "ops.npy", ops.data)
    np.savetxt(tmp_path / "ops.txt", ops.data, header="a b c d")
    (tmp_path / "ops.csv").write_text("\n".join(",".join(map(str, r)) for r in ops.data))
    for name in ("ops.npy", "ops.txt", "ops.csv"):
        np.testing.assert_allclose(pseudo_symmetry_operators(tmp_path / name).data, ops.data)
    assert variant_names(tmp_path / "ops.npy") == VARIANT_NAMES
    assert variant_names(ops[:2]) == ("0", "1", "2")

    np.save(tmp_path / "three.npy", ops.data[:, :3])
    np.save(tmp_path / "long.npy", 2 * ops.data)
    np.save(tmp_path / "ident.npy", OPS.data)
    (tmp_path / "text.txt").write_text("a b c d\n")
    cases = {
        "Quartz": "neither a known material (BaTiO3) nor an existing",
        tmp_path / "three.npy": "not an array of shape (5, 3)",
        tmp_path / "long.npy": "quaternion 0 has norm 2, not 1",
        tmp_path / "ident.npy": "operator 0 is the identity",
        tmp_path / "text.txt": "cannot read pseudo-symmetry operators from",
    }
    for spec, message in cases.items():
        with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
            pseudo_symmetry_operators(spec)


def test_reindex_labels_random_variant_starts(bto_mp):
    """reindex from starts in random variants (the indexer cannot tell
    them): its ``variant`` (relative to each start) is scrambled, its
    ``domain`` is the truth."""
    from kikuchipy_geomdic.indexing.reindex import reindex

    sm = synthetic.synthetic_map(
        bto_mp, (8, 8), "stripes", shape=(60, 60), dose=300, seed=1, perturbation={}
    )
    truth = sm.xmap.prop["variant"]
    k = np.random.default_rng(0).integers(0, 6, truth.size)
    start = _map_like(sm.start_xmap, OPS[k] * sm.start_xmap.rotations)
    before = start.rotations.data.copy()
    out = reindex(
        sm.signal, start, sm.detector, bto_mp, 20, pseudo_symmetry_ops=OPS[1:],
        show_progressbar=False,
    )  # fmt: skip
    np.testing.assert_array_equal(start.rotations.data, before)
    assert (out.variant != truth).mean() > 0.5
    np.testing.assert_array_equal(out.prop["domain"], truth)
    assert out.converged.all()
    # Without operators, no variant and no domain
    plain = reindex(sm.signal, sm.start_xmap, sm.detector, bto_mp, 20, show_progressbar=False)
    assert "domain" not in plain.prop and "confidence" not in plain.prop
    # Operators that are not a whole set of variants: no domain, a warning
    mask = np.ones((8, 8), dtype=bool)
    mask[:2, :2] = False  # refine four points only
    with pytest.warns(UserWarning, match="No domain labels: the 1 pseudo-symmetry operators"):
        part = reindex(
            sm.signal, sm.start_xmap, sm.detector, bto_mp, 20, navigation_mask=mask,
            pseudo_symmetry_ops=OPS[2:3], show_progressbar=False,
        )  # fmt: skip
    assert "domain" not in part.prop and "variant" in part.prop


# --------------------------------------------------------------------- #
# plot_variants
# --------------------------------------------------------------------- #


def _reindexed_like(nav=(6, 8)):
    """A crystal map with the properties of a reindexing with operators:
    domains in stripes, random relative variants, two flagged points."""
    n = nav[0] * nav[1]
    rng = np.random.default_rng(0)
    domain = np.array(STRIPE_VARIANTS)[(np.indices(nav).sum(axis=0) % 4).ravel()]
    converged = np.ones(n, dtype=np.int8)
    converged[[3, 17]] = 0
    prop = {
        "variant": rng.integers(0, 6, n),
        "domain": domain,
        "confidence": rng.uniform(0.6, 0.9, n),
        "cross_variant_margin": rng.uniform(0.5, 1.5, n),
        "converged": converged,
        "refined": np.ones(n, dtype=np.int8),
        "scores": rng.uniform(0.8, 0.9, n),
    }
    rows, cols = np.indices(nav)
    return CrystalMap(Rotation.identity(n), x=cols.ravel() * 1.0, y=rows.ravel() * 1.0, prop=prop)


def test_plot_variants_draws_the_domains():
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_hex

    from kikuchipy_geomdic.plotting import VARIANT_COLOURS, plot_variants

    xmap = _reindexed_like()
    before = {k: np.array(v, copy=True) for k, v in xmap.prop.items()}
    q = xmap.rotations.data.copy()
    truth = xmap.prop["domain"].copy()
    truth[[0, 1]] = 3
    fig = plot_variants(xmap, truth=truth)
    ax_map, ax_margin, ax_conf, ax_hist = fig.axes[:4]
    assert len(fig.axes) == 5  # and the margin's colour bar
    n = xmap.size
    assert ax_map.get_title() == f"variant: {n - 2}/{n} right"
    assert ax_margin.get_title() == "cross-variant margin"
    assert "confidence" in ax_conf.get_title() and "margin" in ax_hist.get_title()
    legend = [t.get_text() for t in ax_map.get_legend().get_texts()]
    assert legend == [*VARIANT_NAMES, "wrong", "flagged"]
    assert ax_map.get_legend().get_title().get_text() == "c axis"
    # The map shows the absolute domains in the variants' colours
    img = ax_map.get_images()[0]
    np.testing.assert_array_equal(img.get_array().reshape(-1), xmap.prop["domain"])
    assert to_hex(img.cmap(img.norm(2))) == VARIANT_COLOURS[2]
    # Wrong points crossed, flagged points circled on both maps
    (cross,) = [ln for ln in ax_map.get_lines() if ln.get_marker() == "x"]
    assert sorted(zip(cross.get_ydata(), cross.get_xdata())) == [(0, 0), (0, 1)]
    for ax in (ax_map, ax_margin):
        (ring,) = [ln for ln in ax.get_lines() if ln.get_marker() == "o"]
        assert sorted(zip(ring.get_ydata(), ring.get_xdata())) == [(0, 3), (2, 1)]
    # Histograms: one per variant present, flagged points apart
    labels = [t.get_text() for t in ax_conf.get_legend().get_texts()]
    assert labels == ["+z", "-z", "+x", "flagged"]
    from matplotlib.patches import Rectangle

    for ax in (ax_conf, ax_hist):  # the flagged points are the bars
        assert sum(p.get_height() for p in ax.patches if isinstance(p, Rectangle)) == 2
    # The map is not modified
    for k, v in before.items():
        np.testing.assert_array_equal(xmap.prop[k], v)
    np.testing.assert_array_equal(xmap.rotations.data, q)
    plt.close(fig)

    # The per-start variant on request, or when the map has no domain
    fig = plot_variants(xmap, relative=True)
    assert fig.axes[0].get_title() == "variant (relative to the start)"
    np.testing.assert_array_equal(
        fig.axes[0].get_images()[0].get_array().reshape(-1), xmap.prop["variant"]
    )
    plt.close(fig)
    with pytest.raises(ValueError, match="truth has 3 points, the map 48"):
        plot_variants(xmap, truth=[0, 1, 2])
