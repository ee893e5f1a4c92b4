"""Figures: displacement fields, sensitivities, coupling, convergence, and
the perturbation study's (the paper's Figs. 8 and 9).

Every function returns a :class:`matplotlib.figure.Figure` and takes plain
arrays, the package's result objects or a study table
(:attr:`~kikuchipy_geomdic.validation.study.PerturbationStudy.table`).

:mod:`~kikuchipy_geomdic.plotting.calibration` (a calibration's figures),
:mod:`~kikuchipy_geomdic.plotting.study` (the perturbation study's),
:mod:`~kikuchipy_geomdic.plotting.variants` (a variant-sensitive
reindexing's) and :mod:`~kikuchipy_geomdic.plotting.phases` (a multi-phase
reindexing's); every ``plot_*`` function is exported here.

Layer 5 (plotting): may import geometry, io, patterns, indexing.
"""

from kikuchipy_geomdic.plotting.calibration import (
    plot_convergence,
    plot_coupling,
    plot_displacement_fields,
    plot_sensitivity,
)
from kikuchipy_geomdic.plotting.phases import plot_phases
from kikuchipy_geomdic.plotting.study import (
    plot_errors,
    plot_heatmaps,
    plot_normalised_errors,
    plot_success,
)
from kikuchipy_geomdic.plotting.variants import VARIANT_COLOURS, plot_variants

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
    "plot_phases",
    "VARIANT_COLOURS",
]
