"""Figures of a variant-sensitive reindexing: domain map, cross-variant
margin map and score histograms (the paper's Fig. 7).

Layer 5 (plotting): may import geometry, io, patterns, indexing.
"""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib.pyplot as plt
import numpy as np

__all__ = ["VARIANT_COLOURS", "plot_variants"]


#: Colours of BaTiO3's six variants (:data:`~kikuchipy_geomdic.indexing.variants.VARIANT_NAMES`):
#: a dark and a light shade per c axis (red z, blue x, green y), as tutorial 03.
VARIANT_COLOURS = ("#d62728", "#ff9896", "#1f77b4", "#aec7e8", "#2ca02c", "#98df8a")


def plot_variants(
    xmap,
    truth: np.ndarray | None = None,
    names: Sequence[str] | None = None,
    *,
    relative: bool = False,
):
    """Plot a variant-sensitive reindexing as the paper's Fig. 7: the
    domain map, the cross-variant margin map and the score histograms.

    Parameters
    ----------
    xmap
        Crystal map from :func:`~kikuchipy_geomdic.indexing.reindex.reindex` with
        ``pseudo_symmetry_ops`` (properties ``variant``, ``confidence``,
        ``cross_variant_margin``, and ``domain``: each point's variant in
        the parent crystal's frame,
        :func:`~kikuchipy_geomdic.indexing.variants.domain_labels`), 1D or 2D. Not
        modified.
    truth
        True variant index per point (synthetic maps: ``xmap.prop
        ["variant"]`` of the truth, in the true parent's frame); wrong
        points are then crossed out and counted.
    names
        Variant names by index; default for the domain map
        :data:`~kikuchipy_geomdic.indexing.variants.VARIANT_NAMES` (BaTiO3's c
        axis) when there are at most six variants, else the indices.
    relative
        Map ``variant`` (each point's variant relative to its start, 0:
        as given) instead of ``domain``. A map without ``domain`` is
        always shown this way.

    Returns
    -------
    figure
        Four panels: the domain map (one colour per variant, a legend of
        the names; flagged points, ``converged`` = 0, circled), the
        margin map in grey levels (flagged points circled), and
        histograms of the confidence index and of the margin per variant
        (flagged points apart, in grey). Points not refined (``refined``
        = 0) or not labelled (``domain`` = -1) are left blank.

    Raises
    ------
    ValueError
        If the map lacks the properties of a reindexing with
        ``pseudo_symmetry_ops``, or *truth* has another size.

    Examples
    --------
    >>> import numpy as np
    >>> from orix import crystal_map, quaternion
    >>> from kikuchipy_geomdic.plotting import plot_variants
    >>> xmap = crystal_map.CrystalMap(
    ...     quaternion.Rotation.identity(4),
    ...     x=np.array([0, 1, 0, 1.0]),
    ...     y=np.array([0, 0, 1, 1.0]),
    ...     prop={
    ...         "variant": np.array([3, 5, 2, 1]),
    ...         "domain": np.array([0, 0, 2, 1]),
    ...         "confidence": np.full(4, 0.8),
    ...         "converged": np.array([1, 1, 1, 0]),
    ...         "cross_variant_margin": np.array([1.5, 1.6, 1.4, 0.2]),
    ...     },
    ... )
    >>> fig = plot_variants(xmap, truth=np.array([0, 0, 2, 0]))
    >>> fig.axes[0].get_title()
    'variant: 3/4 right'
    >>> [t.get_text() for t in fig.axes[0].get_legend().get_texts()][:3]
    ['+z', '-z', '+x']
    """
    from matplotlib.colors import ListedColormap
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    missing = [k for k in ("variant", "confidence", "cross_variant_margin") if k not in xmap.prop]
    if missing:
        raise ValueError(
            f"The crystal map has no {', '.join(missing)}: reindex it with pseudo_symmetry_ops"
        )
    relative = relative or "domain" not in xmap.prop
    key = "variant" if relative else "domain"
    shape = tuple(xmap.shape) if len(xmap.shape) == 2 else (1, xmap.size)
    n = int(np.prod(shape))
    label = np.asarray(xmap.prop[key]).astype(np.int64).ravel()
    prop = xmap.prop
    shown = label >= 0
    if "refined" in prop:
        shown &= np.asarray(prop["refined"]).ravel() != 0
    flagged = shown & (np.asarray(prop.get("converged", np.ones(n))).ravel() == 0)
    conf = np.asarray(prop["confidence"], dtype=float).ravel()
    margin = np.asarray(prop["cross_variant_margin"], dtype=float).ravel()
    if truth is not None:
        truth = np.asarray(truth).ravel()
        if truth.size != n:
            raise ValueError(f"truth has {truth.size} points, the map {n}")
    k, names, colours = _legend(label, truth, names, relative)
    cmap = ListedColormap(colours).with_extremes(bad="white")

    fig, axes = plt.subplots(2, 2, figsize=(10, 7.2), layout="constrained")
    ax_map, ax_margin, ax_conf, ax_hist = axes.ravel()
    img = np.ma.masked_array(label.astype(float), ~shown).reshape(shape)
    ax_map.imshow(img, cmap=cmap, vmin=-0.5, vmax=k - 0.5, interpolation="nearest")
    rows, cols = np.divmod(np.arange(n), shape[1])
    handles = [Patch(color=colours[i], label=names[i]) for i in range(k)]
    title = "variant" + (" (relative to the start)" if relative else " (parent frame)")
    if truth is not None:
        wrong = shown & (truth != label)
        ax_map.plot(cols[wrong], rows[wrong], "kx", ms=5)
        handles.append(Line2D([], [], color="k", marker="x", ls="", label="wrong"))
        right = int((shown & ~wrong).sum())
        title = f"variant: {right}/{n} right"
    for ax in (ax_map, ax_margin):
        ax.plot(cols[flagged], rows[flagged], "o", mfc="none", mec="k", ms=7, mew=1)
        ax.set_xticks([])
        ax.set_yticks([])
    if flagged.any():
        handles.append(Line2D([], [], color="k", marker="o", mfc="none", ls="", label="flagged"))
    ax_map.set_title(title)
    ax_map.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1), fontsize=8,
        title="c axis" if not relative and k <= 6 else None, title_fontsize=8,
    )  # fmt: skip
    im = ax_margin.imshow(
        np.ma.masked_array(margin, ~shown).reshape(shape), cmap="gray", interpolation="nearest"
    )
    fig.colorbar(im, ax=ax_margin, shrink=0.8)
    ax_margin.set_title("cross-variant margin")

    for ax, values, what in ((ax_conf, conf, "confidence index"), (ax_hist, margin, "margin")):
        _histograms(ax, values, what, label, shown, flagged, names, colours)
    ax_conf.set_title("confidence index per variant")
    ax_hist.set_title("cross-variant margin per variant")
    return fig


def _legend(label, truth, names, relative) -> tuple[int, list[str], list]:
    """The number of variants to show, a name and a colour per variant."""
    k = int(max(label.max(initial=0), -1 if truth is None else truth.max())) + 1
    if names is None:
        if not relative and k <= 6:
            from kikuchipy_geomdic.indexing.variants import VARIANT_NAMES

            names = VARIANT_NAMES
        else:
            names = [str(i) for i in range(k)]
    names = [str(x) for x in names]
    k = max(k, len(names))
    names += [str(i) for i in range(len(names), k)]
    colours = (
        list(VARIANT_COLOURS[:k]) if k <= 6 else [plt.get_cmap("tab20")(i % 20) for i in range(k)]
    )
    return k, names, colours


def _histograms(ax, values, what, label, shown, flagged, names, colours) -> None:
    """Histograms of *values* per variant, flagged points apart in grey."""
    k = len(names)
    good = shown & ~flagged
    v = values[shown & np.isfinite(values)]
    lo, hi = (v.min(), v.max()) if v.size else (0.0, 1.0)
    pad = 0.05 * (hi - lo) if hi > lo else 0.5
    bins = np.linspace(lo - pad, hi + pad, 31)
    for i in range(k):
        sel = good & (label == i) & np.isfinite(values)
        if sel.any():
            ax.hist(values[sel], bins=bins, histtype="step", lw=1.5, color=colours[i],
                    label=names[i])  # fmt: skip
    sel = flagged & np.isfinite(values)
    if sel.any():
        ax.hist(values[sel], bins=bins, color="0.6", alpha=0.6, label="flagged")
    ax.set_xlabel(what)
    ax.set_ylabel("points")
    ax.legend(fontsize=7)
