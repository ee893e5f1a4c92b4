"""Figures of the perturbation study
(:mod:`kikuchipy_geomdic.validation.study`): successes, heat maps over
each pair's perturbation grid (the paper's Fig. 8) and parameter errors
(Fig. 9). Each takes a study table
(:attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.table`).

Layer 5 (plotting): may import geometry, io, patterns, indexing.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import matplotlib.pyplot as plt
import numpy as np

from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS

__all__ = ["plot_success", "plot_heatmaps", "plot_errors", "plot_normalised_errors"]


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
