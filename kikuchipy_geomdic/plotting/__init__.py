"""Figures: displacement fields, sensitivities, coupling, convergence, and
the perturbation study's (the paper's Figs. 8 and 9).

Every function returns a :class:`matplotlib.figure.Figure` and takes plain
arrays, the package's result objects or a study table
(:attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.table`).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import matplotlib.pyplot as plt
import numpy as np

from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS

__all__ = [
    "plot_displacement_fields",
    "plot_sensitivity",
    "plot_coupling",
    "plot_convergence",
    "plot_success",
    "plot_heatmaps",
    "plot_errors",
    "plot_normalised_errors",
    "plot_variants",
]


def _quiver(ax, field, uv, pattern=None, scale=None, color="C1", title=None):
    ny, nx = field.shape
    if pattern is not None:
        ax.imshow(pattern, cmap="gray")
    else:
        ax.set_xlim(-0.5, nx - 0.5)
        ax.set_ylim(ny - 0.5, -0.5)
    ys, xs = field.edges
    for e in xs[1:-1]:
        ax.axvline(e - 0.5, color="w" if pattern is not None else "0.8", lw=0.5, ls="--")
    for e in ys[1:-1]:
        ax.axhline(e - 0.5, color="w" if pattern is not None else "0.8", lw=0.5, ls="--")
    c = field.centres
    q = ax.quiver(
        c[:, 0],
        c[:, 1],
        uv[:, 0],
        uv[:, 1],
        color=color,
        angles="xy",
        scale_units="xy",
        scale=scale,
        width=0.006,
    )
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=9)
    return q


def plot_displacement_fields(
    fields: Sequence,
    labels: Sequence[str] | None = None,
    pattern: np.ndarray | None = None,
    scale: float | None = None,
):
    """Plot average displacement fields side by side as quivers.

    Parameters
    ----------
    fields
        :class:`~kikuchipy_geomdic.patterns.displacement.DisplacementField` objects
        of one pattern shape and ROI grid.
    labels
        A title per field; the mean magnitude (percent of the detector
        width) is added.
    pattern
        Optional pattern shown underneath.
    scale
        Arrow scale (data units per pixel of displacement); default so the
        largest arrow of the first field spans 80 % of an ROI.

    Returns
    -------
    figure
    """
    labels = labels or [""] * len(fields)
    if scale is None:
        ys, xs = fields[0].edges
        roi = min(np.diff(xs).min(), np.diff(ys).min())
        mx = max(np.abs(fields[0].mean).max(), 1e-9)
        scale = mx / (0.8 * roi)
    fig, axes = plt.subplots(1, len(fields), figsize=(3.2 * len(fields), 3.4))
    axes = np.atleast_1d(axes)
    for ax, f, lab in zip(axes, fields, labels):
        has = f.total_counts > 0
        mag = np.linalg.norm(f.mean[has], axis=1).mean() / f.shape[1] if has.any() else np.nan
        _quiver(ax, f, f.mean, pattern, scale, title=f"{lab}: {100 * mag:.3f} % of width")
    fig.suptitle(f"Average displacement field (arrows x{1 / scale:.3g})", fontsize=10)
    fig.tight_layout()
    return fig


def plot_sensitivity(jacobian, names, field, steps=None, pattern=None):
    """Plot each parameter's sensitivity field (Jacobian column x step).

    Parameters
    ----------
    jacobian
        (2R, K) in pixels per parameter unit.
    names
        K parameter names.
    field
        A :class:`~kikuchipy_geomdic.patterns.displacement.DisplacementField` for
        the ROI grid.
    steps
        ``{name: step}``; each column is shown for a change of one step
        (default 1 unit).
    pattern
        Optional pattern underneath.

    Returns
    -------
    figure
    """
    steps = steps or {}
    k = len(names)
    ncol = min(k, 4)
    nrow = int(np.ceil(k / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3 * ncol, 3.1 * nrow), squeeze=False)
    cols = [jacobian[:, i].reshape(-1, 2) * steps.get(n, 1.0) for i, n in enumerate(names)]
    ys, xs = field.edges
    roi = min(np.diff(xs).min(), np.diff(ys).min())
    mx = max(max(np.abs(c).max() for c in cols), 1e-9)
    scale = mx / (0.8 * roi)
    for ax, c, n in zip(axes.flat, cols, names):
        _quiver(ax, field, c, pattern, scale, color="C0", title=f"{n} (+{steps.get(n, 1.0):g})")
    for ax in list(axes.flat)[k:]:
        ax.axis("off")
    fig.suptitle("Sensitivity fields: change of b per step", fontsize=10)
    fig.tight_layout()
    return fig


def plot_coupling(coupling, names):
    """Plot the normalised coupling matrix (the paper's Fig. 3C).

    Parameters
    ----------
    coupling
        (K, K) values in [-1, 1].
    names
        K parameter names.

    Returns
    -------
    figure
    """
    k = len(names)
    fig, ax = plt.subplots(figsize=(1.0 + 0.7 * k, 0.6 + 0.7 * k))
    im = ax.imshow(coupling, cmap="RdBu_r", vmin=-1, vmax=1)
    for i in range(k):
        for j in range(k):
            ax.text(j, i, f"{coupling[i, j]:.2f}", ha="center", va="center", fontsize=7)
    ax.set_xticks(range(k), names, rotation=45, ha="right")
    ax.set_yticks(range(k), names)
    fig.colorbar(im, ax=ax, shrink=0.8)
    ax.set_title("Coupling of sensitivity fields", fontsize=10)
    fig.tight_layout()
    return fig


def plot_convergence(history):
    """Plot mean NCC and mean displacement per refinement step.

    Parameters
    ----------
    history
        :attr:`GeometryRefinementResult.history`.

    Returns
    -------
    figure
    """
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(7, 3))
    if history:
        x = np.arange(len(history) + 1)
        ncc = [history[0]["ncc_before"]] + [h["ncc_after"] for h in history]
        disp = [history[0]["displacement_before"]] + [h["displacement_after"] for h in history]
        acc = [True] + [h["accepted"] for h in history]
        for ax, y, lab in (
            (a1, ncc, "mean NCC"),
            (a2, 100 * np.array(disp), "displacement (% of width)"),
        ):
            ax.plot(x, y, "-", color="0.6")
            ax.plot(
                x[np.array(acc)], np.array(y)[np.array(acc)], "o", color="C0", label="accepted"
            )
            rej = ~np.array(acc)
            if rej.any():
                ax.plot(x[rej], np.array(y)[rej], "x", color="C3", label="rejected")
            ax.set_xlabel("step")
            ax.set_ylabel(lab)
        a2.set_yscale("log")
        a1.legend(fontsize=8)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------- #
# The perturbation study (kikuchipy_geomdic.validation.study)
# --------------------------------------------------------------------- #


def plot_success(
    table: np.ndarray,
    limit: float = 0.04,
    ax=None,
    axis: str = "initial_displacement",
    ncc_success: float | None = None,
    misorientation_success: float | None = None,
):
    """Plot final NCC and misorientation against the initial displacement
    (the paper's Fig. 8A), strict successes and failures marked.

    Parameters
    ----------
    table
        Study table (:attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.table`
        or :func:`~kikuchipy_geomdic.validation.tables.read_table`).
    limit
        Initial displacement (fraction of the width) drawn as a line: the
        paper's 4 %.
    ax
        Two axes to draw on; default a new figure.
    axis
        Displacement column on the x axis ("initial_displacement" or
        "initial_displacement_eq2", the paper's).
    ncc_success, misorientation_success
        The study's success thresholds, drawn as lines when given
        (:data:`~kikuchipy_geomdic.validation.study.NCC_SUCCESS`,
        :data:`~kikuchipy_geomdic.validation.study.MISORIENTATION_SUCCESS`).

    Returns
    -------
    figure
    """
    if ax is None:
        fig, ax = plt.subplots(1, 2, figsize=(9, 3.6), layout="constrained")
    else:
        fig = ax[0].figure
    d0 = 100 * table[axis]
    ok = table["success"]
    for a, col, lab in (
        (ax[0], "final_ncc", "mean NCC after refinement"),
        (ax[1], "misorientation", "mean misorientation to truth (deg)"),
    ):
        a.scatter(d0[ok], table[col][ok], s=12, c="C0", label="success")
        a.scatter(d0[~ok], table[col][~ok], s=14, c="C3", marker="x", label="failure")
        a.axvline(100 * limit, color="0.5", ls="--", lw=1)
        a.set_xlabel(
            "initial mean displacement (% of width"
            + (", Eq. 2 average)" if axis.endswith("eq2") else ", model)")
        )
        a.set_ylabel(lab)
    if ncc_success is not None:
        ax[0].axhline(ncc_success, color="0.7", ls=":", lw=1)
    ax[1].set_yscale("log")
    if misorientation_success is not None:
        ax[1].axhline(misorientation_success, color="0.7", ls=":", lw=1)
    ax[0].legend(fontsize=8)
    n = table.size
    fig.suptitle(
        f"{int(ok.sum())}/{n} strict successes, {int(table['success_ncc'].sum())}/{n} NCC "
        "successes",
        fontsize=10,
    )
    return fig


def plot_heatmaps(
    table: np.ndarray,
    metric: str = "final_ncc",
    pairs: Sequence[tuple[str, str]] | None = None,
    material: str | None = None,
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: str | None = None,
):
    """Plot a metric over each pair's perturbation grid (Figs. 8C/D).

    The panels sit in the lower triangle of a parameter x parameter grid,
    like the sub-diagonal of the paper's coupling matrix (Fig. 8B). The
    x axis of a panel is the first parameter's perturbation, the y axis
    the second's; a cross marks strict failures.

    Parameters
    ----------
    table
        Study table.
    metric
        Column to show, e.g. "final_ncc", "misorientation",
        "initial_displacement", "max_pc_error".
    pairs
        Pairs to show; default all in the table.
    material
        Show only rows of this material.
    vmin, vmax, cmap
        Colour scale; sensible defaults per metric.

    Returns
    -------
    figure
    """
    if material is not None:
        table = table[table["material"] == material]
    if pairs is None:
        # In order of appearance, as the study ran them
        pairs = dict.fromkeys(zip(map(str, table["param1"]), map(str, table["param2"])))
    pairs = list(pairs)
    names = [n for n in DEFAULT_PARAMETERS if any(n in p for p in pairs)]
    defaults = {
        "final_ncc": (0.0, 1.0, "gray"),
        "misorientation": (0.0, 1.0, "magma_r"),
        "initial_displacement": (0.0, 0.1, "viridis"),
        "max_pc_error": (0.0, 5e-3, "magma_r"),
    }
    dv = defaults.get(metric, (None, None, "viridis"))
    vmin = dv[0] if vmin is None else vmin
    vmax = dv[1] if vmax is None else vmax
    cmap = cmap or dv[2]
    k = len(names)
    full = all((a, b) in pairs or (b, a) in pairs for a, b in itertools.combinations(names, 2))
    if full and k > 2:
        fig, axes = plt.subplots(
            k - 1,
            k - 1,
            figsize=(2.0 * (k - 1), 2.0 * (k - 1)),
            layout="constrained",
            squeeze=False,
        )
        for a in axes.ravel():
            a.set_visible(False)
        where = {}
        for p1, p2 in pairs:
            i, j = sorted((names.index(p1), names.index(p2)))
            where[(p1, p2)] = axes[j - 1, i]
    else:
        fig, axes = plt.subplots(
            1, len(pairs), figsize=(2.4 * len(pairs), 2.4), layout="constrained", squeeze=False
        )
        where = {p: axes[0, i] for i, p in enumerate(pairs)}
    im = None
    for (p1, p2), ax in where.items():
        sel = table[(table["param1"] == p1) & (table["param2"] == p2)]
        if sel.size == 0:
            continue
        ax.set_visible(True)
        l1 = np.unique(sel["level1"])
        l2 = np.unique(sel["level2"])
        grid = np.full((l2.size, l1.size), np.nan)
        fail = np.zeros_like(grid, dtype=bool)
        for r in sel:
            i = np.searchsorted(l1, r["level1"])
            j = np.searchsorted(l2, r["level2"])
            grid[j, i] = r[metric]
            fail[j, i] = not r["success"]
        d1 = sel["delta1"][sel["level1"] != 0]
        d2 = sel["delta2"][sel["level2"] != 0]
        s1 = (np.abs(d1).max() / np.abs(l1).max()) if d1.size else 1.0
        s2 = (np.abs(d2).max() / np.abs(l2).max()) if d2.size else 1.0
        im = ax.imshow(grid, origin="lower", vmin=vmin, vmax=vmax, cmap=cmap, aspect="auto")
        jj, ii = np.nonzero(fail)
        ax.scatter(ii, jj, marker="x", c="C3", s=20)
        ax.set_xticks(range(l1.size), [f"{v * s1:g}" for v in l1], fontsize=6)
        ax.set_yticks(range(l2.size), [f"{v * s2:g}" for v in l2], fontsize=6)
        ax.set_xlabel(f"d {p1}", fontsize=7)
        ax.set_ylabel(f"d {p2}", fontsize=7)
    if im is not None:
        fig.colorbar(im, ax=[a for a in where.values()], shrink=0.6, label=metric)
    return fig


def _status(table, coupling, threshold):
    """Status per run and parameter: active, positive, negative, uncoupled."""
    names = list(DEFAULT_PARAMETERS)
    status = np.empty((table.size, len(names)), dtype="U10")
    for r, row in enumerate(table):
        active = [str(row["param1"]), str(row["param2"])]
        active = [a for a, lev in zip(active, (row["level1"], row["level2"])) if lev != 0] or []
        for k, n in enumerate(names):
            if n in active:
                status[r, k] = "active"
                continue
            c = [coupling[k, names.index(a)] for a in active]
            cmax = max(c, key=abs) if c else 0.0
            if cmax >= threshold:
                status[r, k] = "positive"
            elif cmax <= -threshold:
                status[r, k] = "negative"
            else:
                status[r, k] = "uncoupled"
    return status


def plot_errors(
    table: np.ndarray,
    coupling: np.ndarray,
    threshold: float = 0.3,
    success: str = "success_ncc",
    normalised: bool = False,
):
    """Box plots of absolute parameter errors by the parameter's status in
    the run (the paper's Fig. 9B).

    A parameter is "active" when it was perturbed in the run, "positive"
    or "negative" when its coupling with an active parameter is above
    *threshold* or below ``-threshold``, else "uncoupled".

    Parameters
    ----------
    table
        Study table.
    coupling
        Coupling matrix of the six parameters
        (:attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.coupling`, or
        :func:`~kikuchipy_geomdic.validation.scores.sensitivities`).
    threshold
        Coupling threshold.
    success
        Only runs with this column true are included ("success_ncc" as
        in the paper, or "success").
    normalised
        Plot the normalised errors of Eq. 12 instead.

    Returns
    -------
    figure
    """
    sel = table[table[success]] if success else table
    status = _status(sel, coupling, threshold)
    groups = ("active", "positive", "negative", "uncoupled")
    names = list(DEFAULT_PARAMETERS)
    fig, axes = plt.subplots(1, len(names), figsize=(2.1 * len(names), 3.2), layout="constrained")
    for k, (n, ax) in enumerate(zip(names, axes)):
        col = f"nerr_{n}" if normalised else f"err_{n}"
        data = [np.abs(sel[col][status[:, k] == g]) for g in groups]
        ax.boxplot(
            [d if d.size else [np.nan] for d in data],
            tick_labels=[g[:3] for g in groups],
            showfliers=True,
            flierprops=dict(markersize=2),
        )
        ax.set_yscale("log")
        ax.set_title(n, fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("|normalised error|" if normalised else "|error| (PC fraction / deg)")
    fig.suptitle(f"{sel.size} runs with {success}", fontsize=9)
    return fig


def plot_normalised_errors(table: np.ndarray, pair: tuple[str, str], material: str | None = None):
    """Stacked normalised errors (Eq. 12) of one pair's runs, the final NCC
    below (the paper's Fig. 9A, flattened to 2D).

    Parameters
    ----------
    table
        Study table.
    pair
        The pair (param1, param2).
    material
        Only rows of this material.

    Returns
    -------
    figure
    """
    if material is not None:
        table = table[table["material"] == material]
    sel = table[(table["param1"] == pair[0]) & (table["param2"] == pair[1])]
    fig, (ax, ax2) = plt.subplots(
        2, 1, figsize=(8, 4), sharex=True, layout="constrained", height_ratios=(3, 1)
    )
    x = np.arange(sel.size)
    bottom = np.zeros(sel.size)
    for k, n in enumerate(DEFAULT_PARAMETERS):
        v = np.abs(sel[f"nerr_{n}"])
        ax.bar(x, v, bottom=bottom, label=n, color=f"C{k}")
        bottom += v
    ax.set_yscale("symlog", linthresh=1e-4)
    ax.set_ylabel("|normalised error|")
    ax.legend(fontsize=7, ncol=3)
    ax2.bar(x, sel["final_ncc"], color=np.where(sel["success"], "C0", "C3"))
    ax2.set_ylabel("NCC")
    ax2.set_xticks(
        x, [f"{a:+g}\n{b:+g}" for a, b in zip(sel["delta1"], sel["delta2"])], fontsize=5
    )
    ax2.set_xlabel(f"d {pair[0]} / d {pair[1]}")
    return fig


# --------------------------------------------------------------------- #
# Pseudo-symmetric variants (the paper's Fig. 7)
# --------------------------------------------------------------------- #


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
    >>> from orix.crystal_map import CrystalMap
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.plotting import plot_variants
    >>> prop = {"variant": np.array([3, 5, 2, 1]), "domain": np.array([0, 0, 2, 1]),
    ...         "confidence": np.full(4, 0.8), "converged": np.array([1, 1, 1, 0]),
    ...         "cross_variant_margin": np.array([1.5, 1.6, 1.4, 0.2])}
    >>> xmap = CrystalMap(Rotation.identity(4), x=np.array([0, 1, 0, 1.0]),
    ...                   y=np.array([0, 0, 1, 1.0]), prop=prop)
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

    good = shown & ~flagged
    for ax, values, what in ((ax_conf, conf, "confidence index"), (ax_hist, margin, "margin")):
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
    ax_conf.set_title("confidence index per variant")
    ax_hist.set_title("cross-variant margin per variant")
    return fig
