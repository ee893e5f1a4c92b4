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

Displacements
-------------
The paper's x axis is the mean displacement magnitude between the
starting and the true pattern sets. Two versions are reported, both from
the geometry model
(:meth:`~kikuchipy_geomdic.geometry.MapGeometry.displacement`), so free
of DIC tracking errors and defined also where DIC would no longer find
the features: :func:`mean_displacement` averages the model field over
every pixel of every calibration pattern per ROI, then takes the mean
magnitude over ROIs divided by the detector width;
:func:`eq2_displacement` samples it where DIC finds vectors and averages
as the paper's Eq. 2 does (an ROI without vectors in a pattern adds
zero), which is the paper's measure and comes out smaller. The
DIC-measured values of the refinement are kept beside them.

Tilt and sample tilt
--------------------
In kikuchipy's projection only ``tilt - sample_tilt`` is observable (see
:mod:`~kikuchipy_geomdic.geometry`); the refinement splits a change of it
equally between the two. Their individual errors are therefore reported
but the meaningful one is ``err_tilt_difference``, the error of
``tilt - sample_tilt``.
"""

from __future__ import annotations

import contextlib
import itertools
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation

from kikuchipy_geomdic.calibration.refinement import calibration_points, refine_geometry_dic
from kikuchipy_geomdic.calibration.solve import coupling_matrix
from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, DEFAULT_STEPS, MapGeometry
from kikuchipy_geomdic.geometry.maps import flat_index
from kikuchipy_geomdic.io.files import atomic_write_text, csv_text
from kikuchipy_geomdic.patterns import displacement as dsp
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation import synthetic

__all__ = [
    "PAPER_DELTAS",
    "PAPER_LEVELS",
    "PAPER_PAIRS",
    "NCC_SUCCESS",
    "MISORIENTATION_SUCCESS",
    "PC_SUCCESS",
    "paper_geometry",
    "mean_displacement",
    "eq2_displacement",
    "sensitivities",
    "PerturbationStudy",
    "perturbation_study",
    "summarise",
    "read_table",
    "pairs_in",
    "write_table",
    "format_table",
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

_PC = ("pcx", "pcy", "pcz")


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
        :class:`~kikuchipy_geomdic.geometry.MapGeometry` with the paper's
        PC and angles.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.study import paper_geometry
    >>> paper_geometry((5, 5), (60, 60)).pc
    (0.5, 0.2, 0.87)
    """
    geo = synthetic.default_geometry(navigation_shape, shape, field_of_view)
    return replace(geo, pc=(0.5, 0.2, 0.87), tilt=10.0, azimuthal=0.0, sample_tilt=70.0)


def _all_points(navigation_shape: tuple[int, int]) -> np.ndarray:
    """Every (row, col) point of a map, row-major."""
    return np.stack([a.ravel() for a in np.indices(navigation_shape)], axis=1)


def _pixel_grid(shape: tuple[int, int], max_side: int = 60):
    step = max(1, int(np.ceil(max(shape) / max_side)))
    y, x = np.mgrid[0 : shape[0] : step, 0 : shape[1] : step]
    return x.ravel().astype(float), y.ravel().astype(float)


def _average_field(
    geometry_a: MapGeometry, geometry_b: MapGeometry, points: np.ndarray, rois
) -> np.ndarray:
    """ROI-averaged model displacement (R, 2) from A to B, over *points*."""
    x, y = _pixel_grid(geometry_a.shape)
    uv = geometry_a.displacement(geometry_b, points, x, y)  # (n, m, 2)
    idx = dsp.roi_index(x, y, geometry_a.shape, rois)
    n_rois = rois[0] * rois[1]
    out = np.zeros((n_rois, 2))
    valid = np.isfinite(uv).all(axis=-1)  # (n, m)
    for c in range(2):
        vals = np.where(valid, uv[..., c], 0.0)
        s = np.zeros(n_rois)
        cnt = np.zeros(n_rois)
        np.add.at(s, idx, vals.sum(axis=0))
        np.add.at(cnt, idx, valid.sum(axis=0))
        out[:, c] = s / np.maximum(cnt, 1)
    return out


def mean_displacement(
    geometry_a: MapGeometry,
    geometry_b: MapGeometry,
    points: np.ndarray | None = None,
    rois: tuple[int, int] = (8, 8),
) -> float:
    """Return the paper's mean displacement magnitude between geometries.

    The forward displacement from geometry A to B is evaluated at every
    pixel of the pattern at every calibration point (every fourth pixel
    or so for patterns larger than 60 px), averaged per ROI and over the
    points (Eq. 2), and the mean magnitude over ROIs is divided by the
    detector width.

    Parameters
    ----------
    geometry_a, geometry_b
        :class:`~kikuchipy_geomdic.geometry.MapGeometry` of one map and
        detector shape.
    points
        Calibration points (N, 2) (row, column); default the whole map.
    rois
        ROI grid (rows, columns).

    Returns
    -------
    displacement
        Fraction of the detector width.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.validation.study import mean_displacement
    >>> geo = synthetic.default_geometry((5, 5), (60, 60))
    >>> d = mean_displacement(geo, geo.updated({"pcx": 0.02}))
    >>> round(d, 4)  # pcx moves the whole pattern by 2 % of its width
    0.02
    """
    if points is None:
        points = _all_points(geometry_a.navigation_shape)
    f = _average_field(geometry_a, geometry_b, np.asarray(points), tuple(rois))
    return float(np.linalg.norm(f, axis=1).mean() / geometry_a.shape[1])


def eq2_displacement(
    master_pattern: EBSDMasterPattern,
    rotations: Rotation,
    geometry_a: MapGeometry,
    geometry_b: MapGeometry,
    points: np.ndarray,
    energy: float = 20.0,
    rois: tuple[int, int] = (8, 8),
    seed: int = 0,
    **dic_kwargs,
) -> tuple[float, float]:
    r"""Return the mean displacement as the paper measured it (Eq. 2).

    Patterns are simulated at the calibration points with *rotations*
    under geometry A (the paper's :math:`\mathbf{A}^0`) and B (the
    "experimental" :math:`\mathbf{B}`), and DIC is run between them. The
    model displacement from A to B is then evaluated where DIC measured
    (the vectors' positions) and averaged as Eq. 2 averages: an ROI without
    vectors in a pattern adds zero and the sum is divided by N. This is
    what the paper's displacement axis is, without the tracking errors that
    make DIC fail at large displacements; it is smaller than
    :func:`mean_displacement` because of the zeros.

    Parameters
    ----------
    master_pattern
        Lambert master pattern.
    rotations
        Orientations at *points* (N,).
    geometry_a, geometry_b
        Starting and true geometry.
    points
        Calibration points (N, 2).
    energy
        Beam energy in kV.
    rois
        ROI grid.
    seed
        Seed of the DIC.
    **dic_kwargs
        Further options of
        :func:`~kikuchipy_geomdic.patterns.displacement.measure_displacements`.

    Returns
    -------
    model, measured
        Mean magnitude over ROIs with vectors, fraction of the detector
        width: the model field at the measured positions, and the field
        DIC measured.
    """
    points = np.asarray(points)
    a = simulate_patterns(master_pattern, rotations, geometry_a.detector(points), energy)
    b = simulate_patterns(master_pattern, rotations, geometry_b.detector(points), energy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = dsp.measure_displacements(a, b, rois=tuple(rois), seed=seed, **dic_kwargs)
    pos = f.positions  # (N, R, 2)
    uv = geometry_a.displacement(geometry_b, points, pos[..., 0], pos[..., 1])
    uv = np.where((f.counts > 0)[..., None] & np.isfinite(uv), uv, 0.0)
    mean = uv.sum(axis=0) / len(points)
    has = f.total_counts > 0
    if not has.any():
        return float("nan"), float("nan")
    model = float(np.linalg.norm(mean[has], axis=1).mean() / geometry_a.shape[1])
    return model, f.mean_displacement


def sensitivities(
    geometry: MapGeometry,
    points: np.ndarray | None = None,
    parameters: Sequence[str] = DEFAULT_PARAMETERS,
    steps: Mapping[str, float] | None = None,
    rois: tuple[int, int] = (8, 8),
) -> tuple[dict[str, float], np.ndarray]:
    """Return the normalisation of the paper's Eq. 12 and the coupling.

    For each parameter ``k`` the model displacement field between
    ``p - delta_k`` and ``p + delta_k`` gives the mean magnitude
    ``d_N`` (fraction of the detector width); ``d_N / (2 delta_k)`` is the
    mean displacement per unit of the parameter, and a parameter error
    ``eps_k`` has the normalised error ``eps_k d_N / (2 delta_k)``
    (Eq. 12): the error expressed as a displacement.

    Parameters
    ----------
    geometry
        Geometry at which the sensitivities are taken.
    points
        Calibration points (N, 2); default the whole map.
    parameters
        Parameter names.
    steps
        ``delta_k``; default :data:`~kikuchipy_geomdic.geometry.DEFAULT_STEPS`.
    rois
        ROI grid.

    Returns
    -------
    scale
        ``{name: d_N / (2 delta_k)}`` (fraction of the width per unit).
    coupling
        Coupling matrix (K, K) of the ROI-averaged sensitivity fields
        (the paper's Fig. 3C).

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.validation.study import sensitivities
    >>> geo = synthetic.default_geometry((5, 5), (60, 60))
    >>> scale, coupling = sensitivities(geo)
    >>> round(scale["pcx"], 3)  # a pcx change moves everything by itself
    1.0
    >>> round(float(coupling[3, 5]), 3)  # tilt and sample_tilt: opposite
    -1.0
    """
    if points is None:
        points = _all_points(geometry.navigation_shape)
    st = dict(DEFAULT_STEPS)
    st.update(steps or {})
    scale, cols_ = {}, []
    for k in parameters:
        d = st[k]
        f = _average_field(
            geometry.updated({k: -d}), geometry.updated({k: d}), np.asarray(points), rois
        )
        scale[k] = float(np.linalg.norm(f, axis=1).mean() / geometry.shape[1] / (2 * d))
        cols_.append(f.ravel() / (2 * d))
    return scale, coupling_matrix(np.stack(cols_, axis=1))


def _misorientation(a: Rotation, b: Rotation) -> np.ndarray:
    """Rotation angle (deg) between rotations, no crystal symmetry: the
    refined orientations start at (or near) the truth and move
    continuously, so a symmetry-equivalent jump would itself be a
    failure."""
    return np.rad2deg((a * ~b).angle)


def _disorientation_from_mean(rot: Rotation) -> float:
    """The paper's single-crystal metric: mean angle to the mean."""
    return float(_misorientation(rot, rot.mean()).mean())


def _geometry_errors(refined: MapGeometry, truth: MapGeometry) -> dict[str, float]:
    centre = np.array([truth.reference])
    pc_r = refined.pc_at(centre)[0]
    pc_t = truth.pc_at(centre)[0]
    err = {k: float(pc_r[i] - pc_t[i]) for i, k in enumerate(_PC)}
    for k in ("tilt", "azimuthal", "sample_tilt"):
        err[k] = float(getattr(refined, k) - getattr(truth, k))
    err["tilt_difference"] = err["tilt"] - err["sample_tilt"]
    return err


_STUDY_COLUMNS = (
    [
        ("material", "U16"),
        ("param1", "U12"),
        ("param2", "U12"),
        ("level1", "f8"),
        ("level2", "f8"),
        ("delta1", "f8"),
        ("delta2", "f8"),
        ("initial_displacement", "f8"),
        ("initial_displacement_eq2", "f8"),
        ("initial_displacement_dic", "f8"),
        ("final_displacement", "f8"),
        ("final_displacement_model", "f8"),
        ("initial_ncc", "f8"),
        ("final_ncc", "f8"),
        ("misorientation", "f8"),
        ("max_misorientation", "f8"),
    ]
    + [(f"err_{k}", "f8") for k in DEFAULT_PARAMETERS + ("tilt_difference",)]
    + [(f"nerr_{k}", "f8") for k in DEFAULT_PARAMETERS]
    + [
        ("max_pc_error", "f8"),
        ("success_ncc", "?"),
        ("success", "?"),
        ("iterations", "i8"),
        ("converged", "?"),
        ("time", "f8"),
    ]
)


def _to_table(rows: Sequence[Mapping[str, Any]], columns) -> np.ndarray:
    dtype = np.dtype(columns)
    out = np.zeros(len(rows), dtype=dtype)
    for i, r in enumerate(rows):
        for name in dtype.names:
            out[name][i] = r.get(name, np.nan if dtype[name].kind == "f" else 0)
    return out


def pairs_in(table) -> list[tuple[str, str]]:
    """Return the parameter pairs of a study table, in order of appearance.

    Parameters
    ----------
    table
        Study table (:attr:`PerturbationStudy.table`).

    Returns
    -------
    pairs
        List of (param1, param2).

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.validation.study import pairs_in
    >>> t = np.array([("pcx", "pcy"), ("pcx", "pcy"), ("pcz", "tilt")],
    ...              dtype=[("param1", "U12"), ("param2", "U12")])
    >>> pairs_in(t)
    [('pcx', 'pcy'), ('pcz', 'tilt')]
    """
    return list(dict.fromkeys(zip(map(str, table["param1"]), map(str, table["param2"]))))


def read_table(path) -> np.ndarray:
    """Read a table written by :func:`write_table` (CSV).

    Parameters
    ----------
    path
        CSV file with a header line.

    Returns
    -------
    table
        NumPy structured array with the study's columns.
    """
    raw = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    raw = np.atleast_1d(raw)
    dtype = np.dtype(_STUDY_COLUMNS)
    out = np.zeros(raw.size, dtype=dtype)
    for name in dtype.names:
        if dtype[name].kind == "f":
            out[name] = np.nan
        if name in raw.dtype.names:
            col = raw[name]
            if dtype[name].kind == "b":
                col = np.array([str(v).strip().lower() in ("true", "1") for v in col])
            out[name] = col
    return out


def write_table(table: np.ndarray, path) -> None:
    """Write a study table as CSV, atomically (read back with
    :func:`read_table`).

    Parameters
    ----------
    table
        NumPy structured array, e.g. :attr:`PerturbationStudy.table`.
    path
        CSV file to write; floats get 8 significant digits.
    """
    atomic_write_text(path, csv_text(table.dtype.names, table.tolist(), digits=8))


def format_table(
    rows: Sequence[Mapping[str, Any]] | np.ndarray, columns=None, floatfmt="{:.4g}"
) -> str:
    """Return rows (dicts or a structured array) as a Markdown table.

    Parameters
    ----------
    rows
        List of dicts or a NumPy structured array.
    columns
        Columns to show; default all (the first row's keys).
    floatfmt
        Format of floats.

    Returns
    -------
    text
        Header, separator and one line per row, without a final newline.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.study import format_table
    >>> print(format_table([{"a": 1, "b": 0.5}]))
    | a | b |
    |---|---|
    | 1 | 0.5 |
    """
    if isinstance(rows, np.ndarray):
        names = rows.dtype.names
        rows = [{n: r[n] for n in names} for r in rows]
    if not rows:
        return ""
    columns = list(columns or rows[0].keys())

    def fmt(v):
        if isinstance(v, (bool, np.bool_)):
            return str(bool(v))
        if isinstance(v, (float, np.floating)):
            return floatfmt.format(float(v))
        return str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
    return "\n".join(lines)


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
        Eq. 2 over the DIC vectors, see :func:`eq2_displacement`: the
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
        """Write the table as CSV, see :func:`write_table`."""
        write_table(self.table, path)

    def plot_success(self, **kwargs):
        """Fig. 8A; see :func:`~kikuchipy_geomdic.plotting.plot_success`."""
        from kikuchipy_geomdic import plotting

        kwargs.setdefault("ncc_success", NCC_SUCCESS)
        kwargs.setdefault("misorientation_success", MISORIENTATION_SUCCESS)
        return plotting.plot_success(self.table, **kwargs)

    def plot_heatmaps(self, **kwargs):
        """Figs. 8C/D; see :func:`~kikuchipy_geomdic.plotting.plot_heatmaps`."""
        from kikuchipy_geomdic import plotting

        return plotting.plot_heatmaps(self.table, **kwargs)

    def plot_errors(self, **kwargs):
        """Fig. 9B; see :func:`~kikuchipy_geomdic.plotting.plot_errors`."""
        from kikuchipy_geomdic import plotting

        kwargs.setdefault("coupling", self.coupling)
        return plotting.plot_errors(self.table, **kwargs)

    def plot_normalised_errors(self, pair, **kwargs):
        """Fig. 9A; see :func:`~kikuchipy_geomdic.plotting.plot_normalised_errors`."""
        from kikuchipy_geomdic import plotting

        return plotting.plot_normalised_errors(self.table, pair, **kwargs)


def summarise(
    table: np.ndarray,
    limits=(0.02, 0.04, 0.06),
    wall_time=float("nan"),
    axis: str = "initial_displacement",
) -> dict:
    """Return the headline numbers of a study table.

    Parameters
    ----------
    table
        Study table (:attr:`PerturbationStudy.table`).
    limits
        Initial displacements (fractions of the width) below which the
        successes are counted (``success_below_<limit>``).
    wall_time
        Wall time of the study, s, copied into the summary.
    axis
        Displacement column the limits refer to: "initial_displacement"
        or the paper's "initial_displacement_eq2".

    Returns
    -------
    summary
        Run and success counts, the smallest failed and largest
        successful displacement, median and largest errors, run times
        (as :meth:`PerturbationStudy.summary`).
    """
    t = table
    d0 = t[axis]
    out: dict[str, Any] = {
        "runs": int(t.size),
        "success_ncc": int(t["success_ncc"].sum()),
        "success": int(t["success"].sum()),
    }
    fail = ~t["success"]
    out["min_failed_displacement"] = float(d0[fail].min()) if fail.any() else float("nan")
    fail_ncc = ~t["success_ncc"]
    out["min_failed_displacement_ncc"] = (
        float(d0[fail_ncc].min()) if fail_ncc.any() else float("nan")
    )
    out["max_success_displacement"] = (
        float(d0[t["success"]].max()) if t["success"].any() else float("nan")
    )
    for lim in limits:
        below = d0 < lim
        out[f"success_below_{100 * lim:g}%"] = (
            f"{int(t['success'][below].sum())}/{int(below.sum())}"
        )
    ok = t["success"]
    if ok.any():
        pc = np.abs(np.stack([t[f"err_{k}"][ok] for k in _PC]))
        out["median_abs_pc_error"] = float(np.median(pc))
        out["max_abs_pc_error"] = float(pc.max())
        out["median_abs_tilt_difference_error"] = float(
            np.median(np.abs(t["err_tilt_difference"][ok]))
        )
        out["median_abs_azimuthal_error"] = float(np.median(np.abs(t["err_azimuthal"][ok])))
        out["median_misorientation"] = float(np.median(t["misorientation"][ok]))
    out["mean_run_time"] = float(t["time"].mean()) if t.size else float("nan")
    out["wall_time"] = float(wall_time)
    return out


def _run_spec(spec: dict) -> dict:
    """One run of the study (module level so that Dask can pickle it)."""
    import dask

    t0 = time.perf_counter()
    mp = spec["master_pattern"]
    if isinstance(mp, str):
        mp = synthetic.master_pattern(mp)
    base: MapGeometry = spec["base_geometry"]
    delta = {spec["param1"]: spec["delta1"]}
    delta[spec["param2"]] = delta.get(spec["param2"], 0.0) + spec["delta2"]
    truth = base.updated(delta)
    row = {
        k: spec[k]
        for k in ("material", "param1", "param2", "level1", "level2", "delta1", "delta2")
    }
    ctx = (
        dask.config.set(scheduler=spec["inner_scheduler"])
        if spec.get("inner_scheduler")
        else contextlib.nullcontext()
    )
    with ctx, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sm = synthetic.synthetic_map(
            mp,
            base.navigation_shape,
            orientations=spec["orientations"],
            geometry=truth,
            perturbation={k: -v for k, v in delta.items()},
            orientation_error=spec["orientation_error"],
            start=spec.get("start", "centred"),
            scatter=spec["scatter"],
            dose=spec["dose"],
            blur=spec["blur"],
            seed=spec["seed"],
        )
        pts = spec["points"]
        row["initial_displacement"] = mean_displacement(sm.start_geometry, truth, pts)
        idx0 = flat_index(pts, base.navigation_shape)
        row["initial_displacement_eq2"] = eq2_displacement(
            sm.master_pattern,
            sm.xmap.rotations[idx0],
            sm.start_geometry,
            truth,
            pts,
            sm.energy,
            tuple(spec["refine_kwargs"].get("rois", (8, 8))),
        )[0]
        kwargs = dict(spec["refine_kwargs"])
        if sm.start == "centred":
            kwargs.setdefault(
                "orientation_prior", synthetic.centred_prior(spec["orientation_error"])
            )
        try:
            res = refine_geometry_dic(
                *sm.start_inputs,
                parameters=spec["parameters"],
                points=pts,
                show_progressbar=False,
                **kwargs,
            )
        except Exception as exc:  # A failed run is a result, not a crash
            row.update(
                error=repr(exc), success=False, success_ncc=False, time=time.perf_counter() - t0
            )
            return row
    idx = flat_index(res.points, sm.geometry.navigation_shape)
    mis = _misorientation(res.xmap.rotations, sm.xmap.rotations[idx])
    err = _geometry_errors(res.geometry, truth)
    scale = spec["scale"]
    row.update(
        initial_displacement_dic=res.history[0]["displacement_before"] if res.history else np.nan,
        final_displacement=res.field_after.mean_displacement,
        final_displacement_model=mean_displacement(res.geometry, truth, res.points),
        initial_ncc=res.history[0]["ncc_before"] if res.history else np.nan,
        final_ncc=float(np.mean(res.xmap.scores)),
        misorientation=float(mis.mean()),
        max_misorientation=float(mis.max()),
        iterations=len(res.history),
        converged=bool(res.converged),
    )
    for k, v in err.items():
        row[f"err_{k}"] = v
    for k in DEFAULT_PARAMETERS:
        row[f"nerr_{k}"] = err[k] * scale[k]
    row["max_pc_error"] = max(abs(err[k]) for k in _PC)
    row["success_ncc"] = bool(row["final_ncc"] > spec["ncc_success"])
    row["success"] = bool(
        row["misorientation"] < spec["misorientation_success"]
        and row["max_pc_error"] < spec["pc_success"]
    )
    row["time"] = time.perf_counter() - t0
    if spec.get("verbose"):
        print(
            f"[{spec['material']}] {spec['param1']}={spec['delta1']:+g} "
            f"{spec['param2']}={spec['delta2']:+g}: d0 {100 * row['initial_displacement']:.2f} %, "
            f"NCC {row['final_ncc']:.4f}, mis {row['misorientation']:.3f} deg, "
            f"PC err {row['max_pc_error']:.1e}, {'ok' if row['success'] else 'FAIL'} "
            f"({row['time']:.1f} s)",
            flush=True,
        )
    return row


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
        :func:`~kikuchipy_geomdic.validation.synthetic.master_pattern` ("BaTiO3",
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
        synthetic.master_pattern(master_pattern)  # Fail early on a bad name
    pairs = list(PAPER_PAIRS if pairs is None else pairs)
    d = dict(PAPER_DELTAS)
    d.update(deltas or {})
    for p in pairs:
        if len(p) != 2 or any(k not in d for k in p):
            raise ValueError(f"Pair {p} is not two of {list(d)}")
    nav = tuple(navigation_shape)
    if base_geometry is None:
        base_geometry = synthetic.default_geometry(nav, tuple(shape))
    if points is None:
        pts = _all_points(nav)
    elif np.ndim(points) == 0:
        pts = calibration_points(nav, int(points))
    else:
        pts = np.asarray(points, dtype=int)
    rkw = dict(refine_kwargs or {})
    scale, coupling = sensitivities(
        base_geometry, pts, DEFAULT_PARAMETERS, rkw.get("steps"), tuple(rkw.get("rois", (8, 8)))
    )
    parallel = n_workers > 1
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
        inner_scheduler="synchronous" if parallel else None,
        verbose=verbose,
    )
    specs = [
        dict(
            run,
            param1=p1,
            param2=p2,
            level1=float(l1),
            level2=float(l2),
            delta1=float(l1) * d[p1],
            delta2=float(l2) * d[p2],
        )
        for p1, p2 in pairs
        for l1 in levels
        for l2 in levels
    ]
    if parallel:
        import dask.bag as db

        bag = db.from_sequence(specs, npartitions=len(specs))
        rows = bag.map(_run_spec).compute(scheduler="processes", num_workers=n_workers)
    else:
        rows = [_run_spec(s) for s in specs]
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
