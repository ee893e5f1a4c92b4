"""Figure of a multi-phase reindexing: the phase map, the points not to
trust marked.

Layer 5 (plotting): may import geometry, io, patterns, indexing.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import ListedColormap

__all__ = ["plot_phases"]


def plot_phases(xmap, truth: np.ndarray | None = None):
    """Plot a crystal map's phases with the points not to trust marked.

    Parameters
    ----------
    xmap
        Crystal map, e.g. from :func:`~kikuchipy_geomdic.indexing.reindex.reindex`
        with ``decide_phase=True``: points with ``converged`` 0 (a phase or
        an orientation not decided) are marked with a cross. 1D or 2D. Not
        modified.
    truth
        True phase id per point (synthetic maps); points of another phase
        are then circled and counted.

    Returns
    -------
    figure
        :class:`matplotlib.figure.Figure`.

    Examples
    --------
    >>> import numpy as np
    >>> from orix.crystal_map import CrystalMap, Phase, PhaseList
    >>> from orix.quaternion import Rotation
    >>> phases = PhaseList([Phase("ferrite", point_group="m-3m"),
    ...                     Phase("austenite", point_group="m-3m")])
    >>> xmap = CrystalMap(Rotation.identity((12,)), phase_id=np.arange(12) % 2,
    ...                   phase_list=phases, x=np.arange(12) % 4, y=np.arange(12) // 4,
    ...                   prop={"converged": np.ones(12)})
    >>> fig = plot_phases(xmap)
    >>> len(fig.axes)
    1
    """
    shape = xmap.shape if len(xmap.shape) == 2 else (1, xmap.size)
    ids = [int(i) for i, _ in xmap.phases if i >= 0]
    phase_id = np.asarray(xmap.phase_id)
    index = np.full(xmap.size, np.nan)
    for k, i in enumerate(ids):
        index[phase_id == i] = k
    colours = plt.get_cmap("tab10").colors[: len(ids)]
    fig, ax = plt.subplots(figsize=(6, 6 * shape[0] / max(shape[1], 1) + 0.8))
    ax.imshow(index.reshape(shape), cmap=ListedColormap(colours), vmin=-0.5,
              vmax=len(ids) - 0.5, interpolation="nearest")  # fmt: skip
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in colours]
    labels = [xmap.phases[i].name for i in ids]
    flagged = np.flatnonzero(np.asarray(xmap.prop.get("converged", np.ones(xmap.size))) == 0)
    if flagged.size:
        rows, cols = np.unravel_index(flagged, shape)
        handles.append(ax.scatter(cols, rows, marker="x", c="k", s=30))
        labels.append(f"not to trust ({flagged.size})")
    if truth is not None:
        wrong = np.flatnonzero(np.ravel(truth) != phase_id)
        rows, cols = np.unravel_index(wrong, shape)
        handles.append(ax.scatter(cols, rows, marker="o", facecolors="none", edgecolors="w"))
        labels.append(f"wrong phase ({wrong.size})")
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
    ax.set_title("Phases")
    ax.set_axis_off()
    return fig
