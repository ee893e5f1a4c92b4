"""The paper's perturbation study on synthetic maps scored against the truth.

Section 4.1 of Griesbach & Kochmann: for chosen parameter pairs, a grid of
perturbations ``{0, +-d/2, +-d}`` of the two parameters with the paper's
``d`` (:data:`PAPER_DELTAS`), every run refining all six parameters from
the same starting geometry, with the *true* orientations as the start (as
in the paper, where the base and "experimental" data sets share their
orientations). :func:`perturbation_study` returns a
:class:`PerturbationStudy`: a table with one row per run and the figures
of the paper's Figs. 8 and 9 (drawn by :mod:`kikuchipy_geomdic.plotting`).
The maps come from :mod:`kikuchipy_geomdic.validation.synthetic`, so that every run
can be scored against the truth.

Success criteria
----------------
A run succeeds in the paper's sense (``success_ncc``) when the mean NCC
of the refined orientations at the refined geometry exceeds
:data:`NCC_SUCCESS` (0.9). NCC barely tells a right geometry from one
whose error was absorbed by the orientations: pattern-wise refinements
whose orientations ended 0.3-1.3 deg from the truth scored within 2e-3 of
the NCC at the true geometry. A stricter criterion (``success``) is
therefore used as well: the mean misorientation of the refined
orientations to the truth is below :data:`MISORIENTATION_SUCCESS`
(0.1 deg) *and* the largest PC error is below :data:`PC_SUCCESS` (1e-3,
0.1 % of the detector). PC errors are compared at the map centre (the
reference of the PC field).

The displacements and errors a run is scored by are in
:mod:`~kikuchipy_geomdic.validation.scores`, the table of runs in
:mod:`~kikuchipy_geomdic.validation.tables`.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from kikuchipy.signals import EBSDMasterPattern

from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, MapGeometry
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation._study_runs import _points, _run_all, _specs
from kikuchipy_geomdic.validation.scores import sensitivities
from kikuchipy_geomdic.validation.tables import _STUDY_COLUMNS, _to_table, summarise, write_table

__all__ = [
    "PAPER_DELTAS",
    "PAPER_LEVELS",
    "PAPER_PAIRS",
    "NCC_SUCCESS",
    "MISORIENTATION_SUCCESS",
    "PC_SUCCESS",
    "paper_geometry",
    "PerturbationStudy",
    "perturbation_study",
]


#: The paper's maximum perturbation ``d`` per parameter (section 4.1):
#: PC fractions and degrees.
PAPER_DELTAS = {
    "pcx": 0.05,
    "pcy": 0.05,
    "pcz": 0.08,
    "tilt": 1.0,
    "azimuthal": 1.0,
    "sample_tilt": 3.0,
}

#: Perturbation levels as fractions of ``d``: ``{0, +-d/2, +-d}``.
PAPER_LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)

#: The 15 parameter pairs of the paper's six parameters.
PAPER_PAIRS = tuple(itertools.combinations(DEFAULT_PARAMETERS, 2))

#: Final mean NCC above which a run succeeds in the paper's sense.
NCC_SUCCESS = 0.9
#: Mean misorientation to the truth (deg) below which a run may succeed
#: in the strict sense.
MISORIENTATION_SUCCESS = 0.1
#: Largest PC error (at the map centre) below which a run may succeed in
#: the strict sense.
PC_SUCCESS = 1e-3


def paper_geometry(
    navigation_shape: tuple[int, int] = (10, 10),
    shape: tuple[int, int] = (60, 60),
    field_of_view: float = 500.0,
) -> MapGeometry:
    """Return a starting geometry like the paper's BaTiO3 set-up.

    The nominal geometry of the paper's Table 3 (Bruker PC about
    (0.50, 0.20, 0.87), detector tilt 10 deg, sample tilt 70 deg,
    azimuthal 0) on the detector and field of view of
    :func:`~kikuchipy_geomdic.validation.synthetic.default_geometry`. With ``pcz``
    0.87 rather than 0.62 the same PC perturbation moves the pattern
    less, as in the paper.

    Parameters
    ----------
    navigation_shape, shape, field_of_view
        As in :func:`~kikuchipy_geomdic.validation.synthetic.default_geometry`.

    Returns
    -------
    geometry
        :class:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry` with the paper's
        PC and angles.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.study import paper_geometry
    >>> paper_geometry((5, 5), (60, 60)).pc
    (0.5, 0.2, 0.87)
    """
    geo = synthetic.default_geometry(navigation_shape, shape, field_of_view)
    return replace(geo, pc=(0.5, 0.2, 0.87), tilt=10.0, azimuthal=0.0, sample_tilt=70.0)


@dataclass
class PerturbationStudy:
    """The result of :func:`perturbation_study`.

    Attributes
    ----------
    table
        NumPy structured array, one row per run, with columns
        ``material``, ``param1``, ``param2`` (the perturbed pair),
        ``level1``, ``level2`` (fractions of ``d``), ``delta1``,
        ``delta2`` (the perturbations, true minus starting value),
        ``initial_displacement`` (model, fraction of detector width),
        ``initial_displacement_eq2`` (the same averaged as the paper's
        Eq. 2 over the DIC vectors, see
        :func:`~kikuchipy_geomdic.validation.scores.eq2_displacement`: the
        paper's axis), ``initial_displacement_dic`` (measured by the
        refinement after the
        first orientation refinement), ``final_displacement`` (DIC),
        ``final_displacement_model`` (model, refined to true geometry),
        ``initial_ncc``, ``final_ncc``, ``misorientation`` and
        ``max_misorientation`` (deg, to the truth), ``err_<name>`` (refined
        minus true, PCs at the map centre) and ``err_tilt_difference``,
        ``nerr_<name>`` (Eq. 12), ``max_pc_error``, ``success_ncc``,
        ``success`` (strict), ``iterations``, ``converged`` and ``time``
        (s per run).
    scale
        ``{name: d_N / (2 delta)}`` of Eq. 12 at the starting geometry.
    coupling
        Coupling matrix of the six parameters at the starting geometry.
    settings
        The arguments of the study.
    wall_time
        Wall time of the whole study in seconds.
    """

    table: np.ndarray
    scale: dict[str, float]
    coupling: np.ndarray
    settings: dict[str, Any] = field(default_factory=dict)
    wall_time: float = float("nan")

    def summary(
        self, limits: Sequence[float] = (0.02, 0.04, 0.06), axis: str = "initial_displacement"
    ) -> dict[str, Any]:
        """Return the headline numbers of the study.

        Parameters
        ----------
        limits
            Initial displacements (fractions of the width) at which the
            success rate below is reported.
        axis
            Displacement column: "initial_displacement" (model, every
            pixel) or "initial_displacement_eq2" (the paper's Eq. 2
            average over the DIC vectors).

        Returns
        -------
        summary
            ``runs``, ``success_ncc``, ``success`` (counts),
            ``min_failed_displacement`` (smallest initial displacement of
            a strict failure, NaN if none), ``min_failed_displacement_ncc``,
            ``max_success_displacement`` (largest of a strict success),
            ``success_below_<limit>`` as "k/n", the median absolute PC and
            tilt-difference errors of successful runs, and ``wall_time``.
        """
        return summarise(self.table, limits, self.wall_time, axis)

    def to_dataframe(self):
        """Return the table as a :class:`pandas.DataFrame` (needs pandas)."""
        import pandas as pd

        return pd.DataFrame.from_records(self.table)

    def save(self, path) -> None:
        """Write the table as CSV, see
        :func:`~kikuchipy_geomdic.validation.tables.write_table`."""
        write_table(self.table, path)

    def plot_success(self, **kwargs):
        """Fig. 8A; see :func:`~kikuchipy_geomdic.plotting.study.plot_success`."""
        from kikuchipy_geomdic import plotting

        kwargs.setdefault("ncc_success", NCC_SUCCESS)
        kwargs.setdefault("misorientation_success", MISORIENTATION_SUCCESS)
        return plotting.plot_success(self.table, **kwargs)

    def plot_heatmaps(self, **kwargs):
        """Figs. 8C/D; see :func:`~kikuchipy_geomdic.plotting.study.plot_heatmaps`."""
        from kikuchipy_geomdic import plotting

        return plotting.plot_heatmaps(self.table, **kwargs)

    def plot_errors(self, **kwargs):
        """Fig. 9B; see :func:`~kikuchipy_geomdic.plotting.study.plot_errors`."""
        from kikuchipy_geomdic import plotting

        kwargs.setdefault("coupling", self.coupling)
        return plotting.plot_errors(self.table, **kwargs)

    def plot_normalised_errors(self, pair, **kwargs):
        """Fig. 9A; see :func:`~kikuchipy_geomdic.plotting.study.plot_normalised_errors`."""
        from kikuchipy_geomdic import plotting

        return plotting.plot_normalised_errors(self.table, pair, **kwargs)


def perturbation_study(
    master_pattern: EBSDMasterPattern | str = "BaTiO3",
    pairs: Sequence[tuple[str, str]] | None = None,
    levels: Sequence[float] = PAPER_LEVELS,
    deltas: Mapping[str, float] | None = None,
    navigation_shape: tuple[int, int] = (10, 10),
    shape: tuple[int, int] = (60, 60),
    points: int | np.ndarray | None = None,
    orientations: str = "random",
    base_geometry: MapGeometry | None = None,
    parameters: Sequence[str] = DEFAULT_PARAMETERS,
    refine_kwargs: Mapping[str, Any] | None = None,
    orientation_error: float = 0.0,
    start: str = "centred",
    scatter: float = 0.05,
    dose: float | None = None,
    blur: float = 0.0,
    ncc_success: float = NCC_SUCCESS,
    misorientation_success: float = MISORIENTATION_SUCCESS,
    pc_success: float = PC_SUCCESS,
    n_workers: int = 1,
    seed: int = 0,
    verbose: bool = False,
) -> PerturbationStudy:
    """Run the paper's perturbation study (section 4.1) on synthetic data.

    For each pair of parameters and each combination of *levels*, the
    true geometry is the starting (base) geometry plus
    ``(level1 d1, level2 d2)`` on the two parameters, a map is simulated
    at the true geometry with the true orientations, and
    :func:`~kikuchipy_geomdic.refine_geometry_dic` refines *parameters*
    (all six by default, as in the paper) from the base geometry and the
    true orientations. With the defaults, the 15 pairs x 25 combinations
    are the paper's 375 runs.

    Parameters
    ----------
    master_pattern
        Master pattern or a name for
        :func:`~kikuchipy_geomdic.validation.master_patterns.master_pattern` ("BaTiO3",
        "Si").
    pairs
        Parameter pairs; default :data:`PAPER_PAIRS` (all 15). A pair of a
        parameter with itself is allowed (a 1D scan).
    levels
        Perturbation levels as fractions of ``d``; default
        :data:`PAPER_LEVELS` ``(-1, -0.5, 0, 0.5, 1)``.
    deltas
        ``d`` per parameter; default :data:`PAPER_DELTAS`.
    navigation_shape
        Map shape. The map spans the 500 um field of view of
        :func:`~kikuchipy_geomdic.validation.synthetic.default_geometry` whatever
        its shape.
    shape
        Pattern shape (rows, columns).
    points
        Calibration points (number or (N, 2) array); default every map
        point.
    orientations
        "random", "single" or "variants", see
        :func:`~kikuchipy_geomdic.validation.synthetic.synthetic_map`. The same
        orientations (same *seed*) are used in every run.
    base_geometry
        Starting geometry; default
        :func:`~kikuchipy_geomdic.validation.synthetic.default_geometry`.
    parameters
        Parameters refined in every run.
    refine_kwargs
        Further arguments of
        :func:`~kikuchipy_geomdic.refine_geometry_dic` (``max_iterations``,
        ``rois``, ``dic_kwargs``, ``refine_kwargs``, ...).
    orientation_error
        RMS error in degrees of the starting orientations; 0 (the paper's
        setting) starts from the true orientations.
    start
        Start model of :func:`~kikuchipy_geomdic.validation.synthetic.synthetic_map`:
        "centred" (the paper's design; the refinement then gets
        ``orientation_prior=centred_prior(orientation_error)``
        (:func:`~kikuchipy_geomdic.validation.synthetic.centred_prior`) unless
        *refine_kwargs* says otherwise), "uncentred" or "indexed".
    scatter
        Orientation scatter for "single" and "variants" maps.
    dose, blur
        Shot noise (mean counts per pixel) and blur of the "experimental"
        patterns, see :func:`~kikuchipy_geomdic.validation.synthetic.synthetic_map`.
    ncc_success, misorientation_success, pc_success
        Success thresholds, see the module notes: ``success_ncc`` is
        ``final_ncc > ncc_success``; ``success`` is
        ``misorientation < misorientation_success`` (deg) and
        ``max_pc_error < pc_success``.
    n_workers
        Runs in parallel through ``dask.bag`` with the processes
        scheduler when above 1 (each run then uses Dask's synchronous
        scheduler inside); 1 runs them one after the other here.
    seed
        Seed of the orientations and noise (the same in every run).
    verbose
        Print one line per run.

    Returns
    -------
    study
        :class:`PerturbationStudy`.

    Examples
    --------
    One pair, a 1 x 2 grid on a tiny map (a real study takes minutes to
    hours):

    >>> from kikuchipy_geomdic.validation.study import perturbation_study
    >>> study = perturbation_study(
    ...     "Si", pairs=[("pcx", "pcz")], levels=[0.0, 0.5],
    ...     navigation_shape=(3, 3), shape=(40, 40),
    ...     refine_kwargs=dict(max_iterations=3, rois=(4, 4)),
    ... )  # doctest: +SKIP
    >>> study.table["success"].tolist()  # doctest: +SKIP
    [True, True]
    """
    t_start = time.perf_counter()
    material = (
        master_pattern
        if isinstance(master_pattern, str)
        else str(master_pattern.phase.name or "phase")
    )
    if isinstance(master_pattern, str):
        master_patterns.master_pattern(master_pattern)  # Fail early on a bad name
    pairs = list(PAPER_PAIRS if pairs is None else pairs)
    d = dict(PAPER_DELTAS)
    d.update(deltas or {})
    for p in pairs:
        if len(p) != 2 or any(k not in d for k in p):
            raise ValueError(f"Pair {p} is not two of {list(d)}")
    nav = tuple(navigation_shape)
    if base_geometry is None:
        base_geometry = synthetic.default_geometry(nav, tuple(shape))
    pts = _points(nav, points)
    rkw = dict(refine_kwargs or {})
    scale, coupling = sensitivities(
        base_geometry, pts, DEFAULT_PARAMETERS, rkw.get("steps"), tuple(rkw.get("rois", (8, 8)))
    )
    # What every run shares, and what the study's settings record
    common = dict(
        material=material,
        orientations=orientations,
        parameters=tuple(parameters),
        refine_kwargs=rkw,
        orientation_error=orientation_error,
        start=start,
        dose=dose,
        blur=blur,
        seed=seed,
    )
    run = dict(
        common,
        master_pattern=master_pattern,
        base_geometry=base_geometry,
        scatter=scatter,
        points=pts,
        scale=scale,
        ncc_success=ncc_success,
        misorientation_success=misorientation_success,
        pc_success=pc_success,
        inner_scheduler="synchronous" if n_workers > 1 else None,
        verbose=verbose,
    )
    rows = _run_all(_specs(run, pairs, levels, d), n_workers)
    table = _to_table(rows, _STUDY_COLUMNS)
    settings = dict(
        common,
        pairs=pairs,
        levels=list(levels),
        deltas=d,
        navigation_shape=nav,
        shape=tuple(shape),
        n_points=len(pts),
        n_workers=n_workers,
        errors=[r["error"] for r in rows if "error" in r],
    )
    return PerturbationStudy(
        table, scale, coupling, settings, wall_time=time.perf_counter() - t_start
    )
