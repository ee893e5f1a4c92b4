"""Figures of a calibration: displacement fields, sensitivity fields,
the coupling matrix and the convergence of the refinement.

Layer 5 (plotting): may import geometry, io, patterns, indexing.
"""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib.pyplot as plt
import numpy as np

__all__ = [
    "plot_displacement_fields",
    "plot_sensitivity",
    "plot_coupling",
    "plot_convergence",
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
