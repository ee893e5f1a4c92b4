"""The ``kikuchipy-geomdic`` command line.

Three commands, each a thin layer over the Python API:

``demo``
    Calibrate a synthetic silicon map with a known, perturbed geometry and
    print the recovered values against the truth.
``refine``
    Calibrate the sample-detector geometry of a measured map
    (:func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`) and write
    the calibrated detector in every PC convention, a summary, the
    per-iteration history and the diagnostic figures.
``reindex``
    Refine every orientation of a map with a calibrated detector
    (:func:`~kikuchipy_geomdic.indexing.reindex.reindex`) and write an orix crystal
    map (``.ang`` and orix h5). With ``--pseudo-symmetry`` (``refine``
    too) the variants of a pseudo-symmetric material are told apart, and
    ``reindex`` writes each point's variant, its domain in the parent
    crystal's frame (:func:`~kikuchipy_geomdic.indexing.variants.domain_labels`),
    confidence, margin and significance (a call within the pattern's noise
    is not ``converged``), and draws the domain map (``domains.png``).

``kikuchipy-geomdic COMMAND --help`` lists the options. Known errors (a
missing or unreadable file, a master pattern of the wrong phase or
energy, maps and patterns of different sizes) end the program with one
line ``kikuchipy-geomdic: error: ...`` on stderr and exit code 2; Ctrl-C
ends it with exit code 130. Output files are written to a hidden staging
folder inside the output folder and moved into place only once all are
written, the summary (``summary.json``, ``reindex.json``) last: an
interrupted run leaves no file that looks complete, and input files are
only read.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shlex
import shutil
import sys
import tempfile
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "main",
    "CLIError",
    "load_patterns",
    "load_crystal_map",
    "load_master_pattern",
    "start_detector",
]

PROG = "kikuchipy-geomdic"
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130

#: Master patterns shipped with the package, by name.
#: A calibration point whose DIC residual exceeds this many times the
#: median failed (its start orientation is far off); the demo reports it.
FAILED_POINT_FACTOR = 5

MASTER_PATTERN_NAMES = ("Si", "BaTiO3")

#: Files ``refine`` writes, in the order they are moved into place (the
#: summary last: its presence marks a complete run).
REFINE_OUTPUTS = (
    "detector.txt",
    "detector_tsl.txt",
    "detector_oxford.txt",
    "detector_emsoft4.txt",
    "detector_emsoft5.txt",
    "history.csv",
    "displacement_fields.png",
    "convergence.png",
    "sensitivity.png",
    "coupling.png",
    "summary.json",
)

#: Files ``reindex`` writes, the summary last.
REINDEX_OUTPUTS = ("xmap_refined.ang", "xmap_refined.h5", "reindex.json")
#: The domain figure ``reindex --pseudo-symmetry`` writes besides them.
DOMAIN_FIGURE = "domains.png"

_UM = ("um", "µm", "μm", "micron", "microns", "micrometre", "micrometer")
_LENGTH_TO_UM = {"nm": 1e-3, "mm": 1e3}


class CLIError(Exception):
    """An error the user can fix: printed as one line, exit code 2."""


def _one_line(e: BaseException | str) -> str:
    text = str(e).strip() or type(e).__name__
    return " ".join(text.split())


def _warn(message: str) -> None:
    print(f"{PROG}: warning: {_one_line(message)}", file=sys.stderr)


@contextlib.contextmanager
def _cli_warnings():
    """Show Python warnings as one ``kikuchipy-geomdic: warning:`` line."""
    with warnings.catch_warnings():

        def show(message, category, filename, lineno, file=None, line=None):
            _warn(str(message))

        warnings.showwarning = show
        yield


def _demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import numpy as np

    from kikuchipy_geomdic.geometry import rotation_vectors
    from kikuchipy_geomdic.geometry.maps import flat_index
    from kikuchipy_geomdic.validation import synthetic
    from kikuchipy_geomdic.validation.camera import Camera

    dose = None if args.paper or not args.dose else args.dose
    start = "centred" if args.paper else "indexed"
    error = 0.3 if args.paper else 1.0
    t0 = time.perf_counter()
    # A user's map is recorded by a camera and processed (background lobe,
    # blur, shot noise, static and dynamic background removal); the
    # paper's study is noise-free
    noise = dict(camera=Camera(dose=dose)) if dose else {}
    sm = synthetic.synthetic_map(
        "Si",
        navigation_shape=(args.rows, args.cols),
        orientations="random",
        shape=(args.size, args.size),
        orientation_error=error,
        start=start,
        seed=args.seed,
        **noise,
    )
    how = (
        "orientations = truth with a zero-mean 0.3 deg scatter (the paper's study), "
        "orientation_prior 0.3 deg"
        if args.paper
        else "orientations indexed by kikuchipy at that geometry (as a user has them), "
        "no orientation prior"
    )
    print(
        f"Synthetic silicon map: {args.rows} x {args.cols} patterns of {args.size} x "
        f"{args.size} px over {sm.geometry.step_sizes[1] * (args.cols - 1):.0f} um "
        f"({sm.master_pattern.metadata.General.title}, "
        f"{f'camera patterns, {dose:g} counts/px, backgrounds removed' if dose else 'noise-free'}"
        "), made in "
        f"{time.perf_counter() - t0:.1f} s.\nStart: true geometry plus a known "
        f"perturbation; {how}."
    )
    t1 = time.perf_counter()
    from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic

    res = refine_geometry_dic(
        *sm.start_inputs,
        points=args.points,
        orientation_prior=synthetic.centred_prior(error) if args.paper else None,
        seed=args.seed,
        show_progressbar=True,
    )
    t_ref = time.perf_counter() - t1
    print(res.table(sm.geometry))
    if res.undetermined:
        print(
            f"Poorly determined by this map: {', '.join(res.undetermined)} (standard "
            "errors above DETERMINACY_LIMITS): they leave their start only by a significant "
            "step. A wider field of view, more points or an orientation prior determine them "
            "better."
        )
    idx = flat_index(res.points, sm.geometry.navigation_shape)
    truth = sm.xmap.rotations[idx]
    # A start the indexing got wrong is a failed point, not a precision
    rms = res.xmap.prop["dic_rms"]
    ok = rms <= FAILED_POINT_FACTOR * np.median(rms)
    for label, rot in (("start", sm.start_xmap.rotations[idx]), ("after", res.xmap.rotations)):
        dev = rotation_vectors(~truth[ok] * rot[ok])
        absolute = np.rad2deg(np.linalg.norm(dev, axis=1)).mean()
        relative = np.rad2deg(np.linalg.norm(dev - dev.mean(axis=0), axis=1)).mean()
        print(
            f"Mean misorientation to the truth, {label}: {absolute:.4f} deg, "
            f"{relative:.4f} deg with the common rotation removed"
        )
    if not ok.all():
        print(
            f"({(~ok).sum()} point(s) left out above: their DIC residual is over "
            f"{FAILED_POINT_FACTOR}x the median, a start the indexing got wrong.)"
        )
    pc = np.abs(res.detector.pc - sm.detector.pc).max()
    pc0 = np.abs(sm.start_detector.pc - sm.detector.pc).max()
    print(f"Largest PC error on the map: {pc0:.2e} at the start, {pc:.2e} after.")
    print(
        f"Refinement: {len(res.history)} steps in {t_ref:.1f} s (converged: {res.converged}, "
        f"DIC backend: {res.field_after.backend})."
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pattern = sm.signal.inav[0, 0].data
    res.plot_displacement(pattern=pattern).savefig(out / "displacement_fields.png", dpi=120)
    res.plot_convergence().savefig(out / "convergence.png", dpi=120)
    res.plot_sensitivity(pattern=pattern).savefig(out / "sensitivity.png", dpi=120)
    res.plot_coupling().savefig(out / "coupling.png", dpi=120)
    print(f"Figures written to {out}/")
    return 0


# --------------------------------------------------------------------- #
# Reading inputs
# --------------------------------------------------------------------- #


def _existing(path: str | os.PathLike, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise CLIError(f"{what} {str(p)!r} does not exist")
    return p


def load_patterns(path: str | os.PathLike):
    """Return the EBSD map in a file, lazily.

    Parameters
    ----------
    path
        Any file :func:`kikuchipy.load` reads (EDAX, Oxford or Bruker
        h5ebsd, NORDIF, kikuchipy h5ebsd, ...).

    Returns
    -------
    signal
        :class:`~kikuchipy.signals.LazyEBSD` with a 1D or 2D navigation
        shape. Nothing is read but the metadata.

    Raises
    ------
    CLIError
        If the file is missing or unreadable, or holds no EBSD map.
    """
    import kikuchipy as kp
    from kikuchipy.signals import EBSD

    p = _existing(path, "pattern file")
    try:
        s = kp.load(p, lazy=True)
    except Exception as e:  # every reader fails in its own way
        raise CLIError(f"cannot read patterns from {str(p)!r}: {_one_line(e)}") from None
    if isinstance(s, list):
        maps = [x for x in s if isinstance(x, EBSD)]
        if len(maps) != 1:
            raise CLIError(f"{str(p)!r} holds {len(s)} data sets; give a file with one EBSD map")
        s = maps[0]
    if not isinstance(s, EBSD):
        raise CLIError(f"{str(p)!r} holds a {type(s).__name__}, not EBSD patterns")
    nav = s.axes_manager.navigation_shape
    if len(nav) not in (1, 2):
        what = "a single pattern" if not nav else f"a {len(nav)}D stack of patterns"
        raise CLIError(f"{str(p)!r} holds {what}; a 1D or 2D map of patterns is needed")
    return s


def load_crystal_map(path: str | os.PathLike | None, signal):
    """Return the map's starting orientations.

    Parameters
    ----------
    path
        A crystal map orix reads (``.ang``, ``.ctf``, orix h5), or ``None``
        for the orientations stored with the patterns.
    signal
        The patterns, to take stored orientations from and to check the
        shape against.

    Returns
    -------
    xmap
        :class:`~orix.crystal_map.CrystalMap` of the signal's navigation
        shape.

    Raises
    ------
    CLIError
        Missing or unreadable file, no orientations, or a shape other
        than the patterns'.
    """
    import numpy as np
    from orix import io as orix_io
    from orix.crystal_map import CrystalMap

    from kikuchipy_geomdic.geometry.maps import navigation_shape

    nav = navigation_shape(signal)
    if path is None:
        xmap = getattr(signal, "xmap", None)
        ok = xmap is not None and any(i >= 0 and p.point_group is not None for i, p in xmap.phases)
        if not ok:
            raise CLIError(
                "the pattern file holds no orientations: pass --orientations MAP "
                "(.ang, .ctf or orix h5)"
            )
        where = "the orientations in the pattern file"
    else:
        p = _existing(path, "orientation map")
        try:
            # orix's .ang reader prints about phase names on stdout
            with contextlib.redirect_stdout(io.StringIO()):
                xmap = orix_io.load(str(p))
        except Exception as e:
            raise CLIError(f"cannot read orientations from {str(p)!r}: {_one_line(e)}") from None
        if not isinstance(xmap, CrystalMap):
            raise CLIError(f"{str(p)!r} holds no crystal map")
        where = f"the orientation map {str(p)!r}"
    xnav = navigation_shape(xmap) if xmap.ndim in (1, 2) else tuple(xmap.shape)
    if xnav != nav or xmap.size != int(np.prod(nav)):
        raise CLIError(
            f"{where} has shape {tuple(xmap.shape)} ({xmap.size} points), the patterns "
            f"{nav}: they must describe the same map"
        )
    return xmap


def _check_step_sizes(signal, xmap) -> None:
    """Make the signal's navigation scales micrometres, which the PC field
    needs; take them from the crystal map if the pattern file lacks them."""
    axes = signal.axes_manager.navigation_axes
    for ax in axes:
        unit = str(ax.units or "").strip()
        if unit in _LENGTH_TO_UM:
            ax.scale, ax.units = ax.scale * _LENGTH_TO_UM[unit], "um"
    if all(str(ax.units).strip() in _UM for ax in axes):
        steps = {ax.name: ax.scale for ax in axes}
        xsteps = {"x": xmap.dx, "y": xmap.dy}
        if str(xmap.scan_unit) in _UM and any(
            k in xsteps and xsteps[k] and abs(v - xsteps[k]) > 1e-6 * abs(v)
            for k, v in steps.items()
        ):
            _warn(
                f"step sizes differ: patterns {steps} um, orientation map "
                f"(x {xmap.dx}, y {xmap.dy}) {xmap.scan_unit}; using the patterns'"
            )
        return
    if str(xmap.scan_unit) in _UM and xmap.dx:
        for ax in axes:
            ax.scale = {"y": xmap.dy}.get(ax.name, xmap.dx) or xmap.dx
            ax.units = "um"
        _warn(
            "the pattern file gives no step size in micrometres; using the orientation "
            f"map's (x {xmap.dx}, y {xmap.dy} um)"
        )
        return
    _warn(
        f"step sizes are in {[str(ax.units) for ax in axes]}, not micrometres: the "
        "PC field over the map assumes micrometres"
    )


def _file_energies(path: Path):
    """Beam energies (kV) an EMsoft master pattern file holds, or None."""
    import h5py
    import numpy as np

    try:
        if not h5py.is_hdf5(path):
            return None
        with h5py.File(path, "r") as f:
            for group in ("EMData/EBSDmaster", "EMData/TKDmaster"):
                if f"{group}/EkeVs" in f:
                    return np.atleast_1d(np.asarray(f[f"{group}/EkeVs"][()], dtype=float))
    except OSError:
        return None
    return None


def load_master_pattern(spec: str, energy: float):
    """Return a Lambert master pattern for a beam energy.

    Parameters
    ----------
    spec
        A master pattern file kikuchipy reads (EMsoft h5, ebsdsim npz if
        ebsdsim is installed, ...), or the name of one shipped with the
        package: "Si" or "BaTiO3" (dynamical at 20 kV, kinematical at
        other energies).
    energy
        Beam energy in kV.

    Returns
    -------
    master_pattern
        :class:`~kikuchipy.signals.EBSDMasterPattern` in the Lambert
        projection.

    Raises
    ------
    CLIError
        Missing or unreadable file, not a master pattern, no phase, or a
        file simulated for other energies.
    """
    import numpy as np
    from kikuchipy.signals import EBSDMasterPattern

    from kikuchipy_geomdic.validation import master_patterns

    if not np.isfinite(energy) or not 0 < energy <= 100:
        raise CLIError(f"--energy {energy} kV is not a beam energy")
    p = Path(spec)
    if not p.exists():
        names = {n.lower(): n for n in MASTER_PATTERN_NAMES}
        if spec.lower() in names:
            if energy != 20:
                _warn(
                    f"the shipped dynamical {names[spec.lower()]} master pattern is for "
                    f"20 kV: using a kinematical one computed for {energy:g} kV"
                )
            return master_patterns.master_pattern(names[spec.lower()], kind="auto", energy=energy)
        raise CLIError(
            f"master pattern {spec!r} does not exist (give a file kikuchipy reads, or "
            f"one of {', '.join(MASTER_PATTERN_NAMES)})"
        )
    energies = _file_energies(p)
    if energies is not None and np.min(np.abs(energies - energy)) > 0.5:
        raise CLIError(
            f"the master pattern {str(p)!r} was simulated for "
            + (
                f"{energies.min():g}-{energies.max():g}"
                if energies.size > 1
                else f"{energies[0]:g}"
            )
            + f" kV, not for {energy:g} kV"
        )
    mp = None
    try:
        import kikuchipy as kp

        for kw in (
            dict(projection="lambert", hemisphere="both", energy=energy),
            dict(hemisphere="both"),
            {},
        ):
            try:
                mp = kp.load(p, **kw)
                break
            except TypeError:  # this reader takes other keywords
                continue
    except Exception as e:
        raise CLIError(f"cannot read a master pattern from {str(p)!r}: {_one_line(e)}") from None
    if isinstance(mp, list):
        mp = next((m for m in mp if isinstance(m, EBSDMasterPattern)), mp)
    if not isinstance(mp, EBSDMasterPattern):
        raise CLIError(f"{str(p)!r} holds a {type(mp).__name__}, not an EBSD master pattern")
    if mp.phase is None or mp.phase.point_group is None:
        raise CLIError(f"the master pattern {str(p)!r} has no phase symmetry")
    if mp.projection != "lambert":
        mp = mp.as_lambert(show_progressbar=False)
    axes = [a for a in mp.axes_manager.navigation_axes if a.name == "energy"]
    if axes:
        ax = axes[0]
        lo, hi = ax.low_value - abs(ax.scale) / 2, ax.high_value + abs(ax.scale) / 2
        if not lo <= energy <= hi:
            raise CLIError(
                f"the master pattern {str(p)!r} covers {ax.low_value:g}-{ax.high_value:g} kV, "
                f"not {energy:g} kV"
            )
    return mp


_GEOMETRY_OPTIONS = ("pc", "tilt", "sample_tilt", "azimuthal", "twist", "px_size", "binning")


def start_detector(signal, args: argparse.Namespace | None = None, warn: bool = True):
    """Return the starting detector: the pattern file's, with overrides.

    Parameters
    ----------
    signal
        The patterns; their ``detector`` is read from the file's metadata.
    args
        Namespace with ``pc`` (three values in ``convention``), ``tilt``,
        ``sample_tilt``, ``azimuthal``, ``twist``, ``px_size`` and
        ``binning``; ``None`` values keep the file's.
    warn
        Warn about values that look like kikuchipy's placeholders (PC
        (0.5, 0.5, 0.5), pixel size 1 um).

    Returns
    -------
    detector
        New :class:`~kikuchipy.detectors.EBSDDetector`; the signal's is
        not modified.
    """
    import numpy as np
    from kikuchipy.detectors import EBSDDetector

    from kikuchipy_geomdic.io.conventions import convention_name

    det = signal.detector
    get = (lambda k: getattr(args, k, None)) if args is not None else (lambda k: None)
    kw = dict(
        shape=tuple(signal.axes_manager.signal_shape[::-1]),
        px_size=float(det.px_size),
        binning=float(getattr(det, "_binning", det.binning)),
        tilt=float(det.tilt),
        azimuthal=float(det.azimuthal),
        twist=float(det.twist),
        sample_tilt=float(det.sample_tilt),
    )
    for k in ("px_size", "binning", "tilt", "azimuthal", "twist", "sample_tilt"):
        if get(k) is not None:
            kw[k] = float(get(k))
    if kw["px_size"] <= 0 or kw["binning"] <= 0:
        raise CLIError("--px-size and --binning must be positive")
    conv = get("convention")
    if get("pc") is not None:
        pc, conv = np.asarray(get("pc"), dtype=float), convention_name(conv or "bruker")
    else:
        if conv is not None:
            raise CLIError("--convention gives the convention of --pc X Y Z: pass --pc too")
        pc, conv = det.pc.copy(), "bruker"
        if warn and np.allclose(pc, 0.5):
            _warn(
                "the pattern file has kikuchipy's default PC (0.5, 0.5, 0.5), probably "
                "no calibration: pass a starting --pc X Y Z"
            )
    if warn and get("px_size") is None and kw["px_size"] == 1.0:
        _warn(
            "the detector pixel size is 1 um, kikuchipy's placeholder: the PC field over "
            "the map depends on it, pass --px-size (unbinned, um) and --binning"
        )
    new = EBSDDetector(pc=pc, convention=conv, **kw)
    if not np.isfinite(new.pc).all():
        raise CLIError("the starting PC is not finite")
    return new


def _check_detector(det, signal) -> None:
    from kikuchipy_geomdic.geometry.maps import navigation_shape

    nav, sig = navigation_shape(signal), tuple(signal.axes_manager.signal_shape[::-1])
    if tuple(det.shape) != sig:
        raise CLIError(f"the detector is {tuple(det.shape)} px, the patterns {sig} px")
    n = nav[0] * nav[1]
    if det.navigation_size not in (1, n):
        raise CLIError(
            f"the detector has {det.navigation_size} PCs, the map {n} points {nav}: "
            "it belongs to another map"
        )


def _phase_arg(phase: str | None) -> str | int | None:
    """--phase as a name, or as an id if it is a number."""
    return int(phase) if phase is not None and phase.lstrip("-").isdigit() else phase


def _load_map(args: argparse.Namespace):
    """The patterns, crystal map, master pattern and matched phase id of
    ``refine`` and ``reindex``, each checked against the others."""
    from kikuchipy_geomdic.patterns.phases import check_phase

    signal = load_patterns(args.patterns)
    xmap = load_crystal_map(args.orientations, signal)
    _check_step_sizes(signal, xmap)
    mp = load_master_pattern(args.master_pattern, args.energy)
    return signal, xmap, mp, check_phase(xmap, mp, _phase_arg(args.phase))


def _pseudo_symmetry(args: argparse.Namespace):
    """The operators of ``--pseudo-symmetry`` (None without it)."""
    from kikuchipy_geomdic.indexing.variants import pseudo_symmetry_operators

    if args.pseudo_symmetry is None:
        return None
    try:
        return pseudo_symmetry_operators(args.pseudo_symmetry)
    except ValueError as e:
        raise CLIError(f"--pseudo-symmetry: {_one_line(e)}") from None


def _check_pseudo_symmetry(ops, mp) -> None:
    """The operators must give distinct variants of the master pattern's
    phase (with its point group)."""
    from kikuchipy_geomdic.indexing.variants import check_pseudo_symmetry

    if ops is not None:
        try:
            check_pseudo_symmetry(ops, mp.phase.point_group)
        except ValueError as e:
            raise CLIError(
                f"--pseudo-symmetry does not fit phase {mp.phase.name!r}: {_one_line(e)}"
            ) from None


def _run_on_map(function, args: argparse.Namespace, inputs, **kwargs):
    """``function(signal, xmap, detector, master_pattern, energy, ...)``
    on the ``--scheduler`` cluster (if any), with kikuchipy's progress
    unless ``--quiet``; the result and the wall time in seconds."""
    t0 = time.perf_counter()
    with _dask_client(args.scheduler):
        out = function(*inputs, args.energy, show_progressbar=not args.quiet, **kwargs)
    return out, time.perf_counter() - t0


def _calibration_points(signal, xmap, phase_id: int, n: int):
    """About *n* usable points spread over the map, without NaN or blank
    patterns (each candidate pattern is read once)."""
    import numpy as np

    from kikuchipy_geomdic.calibration.refinement import calibration_points
    from kikuchipy_geomdic.geometry.maps import flat_index, navigation_shape
    from kikuchipy_geomdic.indexing.reindex import usable_points

    nav = navigation_shape(signal)
    usable = usable_points(xmap, phase_id).reshape(nav)
    data = signal.data
    flat = data.reshape((-1,) + tuple(data.shape[-2:]))
    n_blank = 0
    pts = np.zeros((0, 2), dtype=int)
    for _ in range(50):
        pts = calibration_points(nav, n, usable)
        if not len(pts):
            break
        sel = flat[flat_index(pts, nav)]
        sel = np.asarray(sel.compute() if hasattr(sel, "compute") else sel, dtype=np.float32)
        finite = np.isfinite(sel).all(axis=(1, 2))
        ok = finite.copy()
        ok[finite] = sel[finite].std(axis=(1, 2)) > 0
        if ok.all():
            break
        n_blank += int((~ok).sum())
        usable[pts[~ok, 0], pts[~ok, 1]] = False
    return pts, int(usable.sum()), n_blank


@contextlib.contextmanager
def _dask_client(address: str | None):
    """Connect to a running dask scheduler (address or scheduler file)
    for the duration; nothing if *address* is None."""
    if not address:
        yield None
        return
    try:
        from distributed import Client
    except ImportError:
        raise CLIError("--scheduler needs the 'distributed' package") from None
    kw = {"scheduler_file": address} if address.endswith(".json") else {"address": address}
    try:
        client = Client(timeout="20s", **kw)
    except (OSError, TimeoutError, ValueError) as e:
        raise CLIError(
            f"cannot connect to the dask scheduler {address!r}: {_one_line(e)}"
        ) from None
    try:
        yield client
    finally:
        client.close()


# --------------------------------------------------------------------- #
# Writing outputs
# --------------------------------------------------------------------- #


class _Staging:
    """Output files written to a hidden folder inside *out*, moved into
    *out* by :meth:`commit` (the last name, the summary, last). Leaving
    the ``with`` block removes the staging folder, so an interrupted or
    failed run leaves nothing that looks complete."""

    def __init__(self, out: str | os.PathLike, names: Sequence[str], overwrite: bool):
        self.out = Path(out)
        self.names = tuple(names)
        self.tmp: Path | None = None
        if self.out.exists() and not self.out.is_dir():
            raise CLIError(f"--out {str(self.out)!r} is a file, not a folder")
        present = [n for n in self.names if (self.out / n).exists()]
        if present and not overwrite:
            raise CLIError(
                f"{str(self.out)!r} already holds results ({present[0]}, ...): pass "
                "--overwrite or choose another --out"
            )

    def __enter__(self) -> _Staging:
        self.out.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=".kikuchipy-geomdic-", dir=self.out))
        return self

    def path(self, name: str) -> Path:
        assert name in self.names and self.tmp is not None
        return self.tmp / name

    def commit(self) -> list[Path]:
        marker = self.out / self.names[-1]
        marker.unlink(missing_ok=True)  # an old summary must not vouch for new files
        moved = []
        for name in self.names:
            if (self.tmp / name).exists():
                os.replace(self.tmp / name, self.out / name)
                moved.append(self.out / name)
        return moved

    def __exit__(self, *exc) -> bool:
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
        return False


def _history_csv(history: list[dict], names: Sequence[str]) -> str:
    from kikuchipy_geomdic.io.conventions import csv_text

    cols = [
        "iteration",
        "accepted",
        "damping",
        "ncc_before",
        "ncc_after",
        "displacement_before",
        "displacement_after",
    ]
    # accepted as 1 or 0, which every CSV reader takes for a number
    rows = (
        [
            *(int(h[c]) if c == "accepted" else h[c] for c in cols),
            *(h["parameters"][n] for n in names),
        ]
        for h in history
    )
    return csv_text([*cols, *names], rows)


def _inputs(args: argparse.Namespace, signal, master_pattern, **extra) -> dict[str, Any]:
    from kikuchipy_geomdic.geometry.maps import navigation_shape

    return {
        "command": shlex.join([PROG, *getattr(args, "argv", [])]),
        "patterns": str(Path(args.patterns).resolve()),
        "orientations": (
            str(Path(args.orientations).resolve()) if args.orientations else "pattern file"
        ),
        "master_pattern": (
            str(Path(args.master_pattern).resolve())
            if Path(args.master_pattern).exists()
            else args.master_pattern
        ),
        "master_pattern_title": str(master_pattern.metadata.General.title),
        "energy_kv": float(args.energy),
        "navigation_shape": list(navigation_shape(signal)),
        "pattern_shape": list(signal.axes_manager.signal_shape[::-1]),
        **extra,
    }


# --------------------------------------------------------------------- #
# refine
# --------------------------------------------------------------------- #


def _refine(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
    from kikuchipy_geomdic.geometry.maps import flat_index, navigation_shape
    from kikuchipy_geomdic.io import conventions as cv

    staging = _Staging(args.out, REFINE_OUTPUTS, args.overwrite)
    say = (lambda *a: None) if args.quiet else print
    ops = _pseudo_symmetry(args)
    signal, xmap, mp, phase_id = _load_map(args)
    _check_pseudo_symmetry(ops, mp)
    det = start_detector(signal, args)
    _check_detector(det, signal)

    pts, n_usable, n_blank = _calibration_points(signal, xmap, phase_id, args.points)
    if n_blank:
        _warn(f"{n_blank} calibration candidate pattern(s) hold NaN or are blank: skipped")
    if len(pts) < args.points:
        _warn(
            f"only {len(pts)} usable point(s) for the {args.points} requested (points not "
            "indexed, with invalid rotations, of another phase or with NaN or blank "
            f"patterns are excluded): calibrating with {len(pts)}"
        )
    if not len(pts):
        raise CLIError("no usable calibration point in the map")
    nav = navigation_shape(signal)
    say(
        f"Calibrating the geometry of {str(args.patterns)!r}: map {nav}, patterns "
        f"{tuple(det.shape)} px, {mp.phase.name}, {args.energy:g} kV, "
        f"{len(pts)} points"
    )
    res, seconds = _run_on_map(
        refine_geometry_dic,
        args,
        (signal, xmap, det, mp),
        parameters=args.parameters,
        points=pts,
        solver=args.solver,
        full_field=False if args.dic_only else None,
        orientation_prior=args.orientation_prior,
        rois=tuple(args.rois),
        max_iterations=args.max_iterations,
        phase=phase_id,
        seed=args.seed,
        pseudo_symmetry_ops=ops,
    )
    summary = cv.summary_from_result(
        res,
        **_inputs(
            args,
            signal,
            mp,
            phase=mp.phase.name,
            pseudo_symmetry=args.pseudo_symmetry,
            points_requested=args.points,
            seconds=round(seconds, 3),
        ),
    )
    flat = signal.data.reshape((-1,) + tuple(signal.data.shape[-2:]))
    pattern = flat[int(flat_index(res.points[0], res.geometry.navigation_shape))]
    pattern = np.asarray(pattern.compute() if hasattr(pattern, "compute") else pattern)

    with staging as st:
        cv.save_detector(res.detector, st.path("detector.txt"), "bruker")
        for conv in ("tsl", "oxford", "emsoft4", "emsoft5"):
            cv.save_detector(res.detector, st.path(f"detector_{conv}.txt"), conv)
        st.path("history.csv").write_text(_history_csv(res.history, res.parameter_names))
        figures = {
            "displacement_fields.png": lambda: res.plot_displacement(pattern=pattern),
            "convergence.png": res.plot_convergence,
            "sensitivity.png": lambda: res.plot_sensitivity(pattern=pattern),
            "coupling.png": res.plot_coupling,
        }
        for name, make in figures.items():
            fig = make()
            fig.savefig(st.path(name), dpi=120)
            plt.close(fig)
        cv.write_summary(summary, st.path("summary.json"))
        st.commit()
    say(cv.format_summary(summary))
    cal = summary["calibration"]
    say(
        f"{cal['iterations']} iteration(s) in {seconds:.1f} s (converged: "
        f"{summary['converged']}); mean NCC {cal['mean_ncc']:.4f} over {cal['points']} points."
    )
    say(f"Results written to {str(staging.out)!r}: {', '.join(REFINE_OUTPUTS)}")
    return 0


# --------------------------------------------------------------------- #
# reindex
# --------------------------------------------------------------------- #


def _reindex_detector(args: argparse.Namespace, signal):
    """The detector to reindex with, and where it came from."""
    from kikuchipy_geomdic.geometry.maps import navigation_shape
    from kikuchipy_geomdic.io import conventions as cv

    overrides = [k for k in _GEOMETRY_OPTIONS + ("convention",) if getattr(args, k) is not None]
    if args.detector is None:
        return start_detector(signal, args), "the pattern file's metadata" + (
            f" with {', '.join(overrides)} from the command line" if overrides else ""
        )
    if overrides:
        raise CLIError(
            f"--detector gives the whole geometry: leave out --{overrides[0].replace('_', '-')}"
        )
    p = _existing(args.detector, "detector")
    if p.is_dir():
        for name in ("detector.txt", "summary.json"):
            if (p / name).is_file():
                p = p / name
                break
        else:
            raise CLIError(f"{str(p)!r} holds neither detector.txt nor summary.json")
    if p.suffix.lower() == ".json":
        geo = cv.geometry_from_summary(cv.read_summary(p))
        nav = navigation_shape(signal)
        if tuple(geo.navigation_shape) != nav:
            raise CLIError(
                f"{str(p)!r} was calibrated on a map of {tuple(geo.navigation_shape)} "
                f"points, the patterns are {nav}"
            )
        det = geo.detector()
    else:
        det = cv.load_detector(p)
    return det, str(p)


def _reindex(args: argparse.Namespace) -> int:
    import numpy as np
    from orix import io as orix_io

    from kikuchipy_geomdic.geometry.maps import navigation_shape
    from kikuchipy_geomdic.indexing.reindex import reindex, usable_points
    from kikuchipy_geomdic.io import conventions as cv

    ops = _pseudo_symmetry(args)
    figure = ops is not None and args.method == "geomdic"
    names = REINDEX_OUTPUTS[:-1] + (DOMAIN_FIGURE,) * figure + REINDEX_OUTPUTS[-1:]
    staging = _Staging(args.out, names, args.overwrite)
    say = (lambda *a: None) if args.quiet else print
    signal, xmap, mp, phase_id = _load_map(args)
    _check_pseudo_symmetry(ops, mp)
    det, source = _reindex_detector(args, signal)
    _check_detector(det, signal)
    kw: dict[str, Any] = {"method": args.method}
    if ops is not None:
        kw["pseudo_symmetry_ops"] = ops
    if args.method == "kikuchipy":
        kw["kikuchipy_method"] = args.kikuchipy_method
    elif args.method_kwargs or args.trust_region is not None:
        raise CLIError("--method-kwargs and --trust-region are options of --method kikuchipy")
    if args.method_kwargs:
        try:
            kw["method_kwargs"] = json.loads(args.method_kwargs)
        except json.JSONDecodeError as e:
            raise CLIError(f"--method-kwargs is not JSON: {e}") from None
        if not isinstance(kw["method_kwargs"], dict):
            raise CLIError('--method-kwargs must be a JSON object, e.g. \'{"method": "Powell"}\'')
    if args.trust_region is not None:
        kw["trust_region"] = list(args.trust_region)

    todo = usable_points(xmap, phase_id)
    say(
        f"Reindexing {int(todo.sum())} point(s) of {str(args.patterns)!r} "
        f"({navigation_shape(signal)} map, {xmap.phases[phase_id].name}) with the detector "
        f"from {source}"
    )
    out, seconds = _run_on_map(reindex, args, (signal, xmap, det, mp), phase=phase_id, **kw)
    refined = out.prop["refined"].astype(bool)
    scores = out.prop["scores"][refined]
    evals = "iterations" if args.method == "geomdic" else "num_evals"
    stats = {
        "points": int(out.size),
        "refined": int(refined.sum()),
        "not_refined_unusable": int((~todo.ravel()).sum()),
        "not_refined_nan_patterns": int((todo.ravel() & ~refined).sum()),
        "mean_ncc": float(scores.mean()) if scores.size else None,
        "median_ncc": float(np.median(scores)) if scores.size else None,
        "min_ncc": float(scores.min()) if scores.size else None,
        "mean_evaluations": float(out.prop[evals][refined].mean()) if scores.size else None,
        # Refined but not to be trusted (geomdic: poor for where they are)
        "flagged": int((refined & (out.prop.get("converged", refined) == 0)).sum()),
        "seconds": round(seconds, 3),
        "patterns_per_second": float(refined.sum() / seconds) if seconds > 0 else None,
    }
    if "domain" in out.prop:
        from kikuchipy_geomdic.indexing.variants import variant_names

        counts = np.bincount(out.prop["domain"][out.prop["domain"] >= 0], minlength=ops.size + 1)
        stats["domains"] = dict(zip(variant_names(ops), counts.tolist()))
    summary = {
        "format": "kikuchipy-geomdic reindex summary",
        "format_version": 1,
        "versions": cv._versions(),
        "detector_source": source,
        "detector_reference_pc": {c: cv.export_geometry(_one_pc(det), c) for c in cv.CONVENTIONS},
        "refine_kwargs": {k: v for k, v in kw.items() if k != "pseudo_symmetry_ops"},
        "pseudo_symmetry": None
        if ops is None
        else {"source": args.pseudo_symmetry, "operators": ops.data.tolist()},
        "result": stats,
        "inputs": _inputs(args, signal, mp, phase=out.phases[phase_id].name),
    }
    with staging as st:
        _write_ang(st.path("xmap_refined.ang"), out, det)
        orix_io.save(str(st.path("xmap_refined.h5")), out, overwrite=True)
        if figure:
            _domain_figure(out, ops, st.path(DOMAIN_FIGURE))
        cv.write_summary(summary, st.path("reindex.json"))
        st.commit()
    say(
        f"Refined {stats['refined']} of {stats['points']} points in {seconds:.1f} s"
        + (
            f"; mean NCC {stats['mean_ncc']:.4f} (min {stats['min_ncc']:.4f})"
            if scores.size
            else ""
        )
        + f"; {stats['not_refined_unusable']} not indexed or unusable, "
        f"{stats['not_refined_nan_patterns']} with NaN patterns"
        + (
            f"; {stats['flagged']} flagged as not converged (property 'converged' = 0)."
            if args.method == "geomdic"
            else "."
        )
    )
    if "domains" in stats:
        say("Points per domain (c axis in the parent frame): " + ", ".join(
            f"{k} {v}" for k, v in stats["domains"].items()
        ))  # fmt: skip
    say(f"Results written to {str(staging.out)!r}: {', '.join(staging.names)}")
    return 0


def _domain_figure(xmap, ops, path: Path) -> None:
    """The domain map, margin map and score histograms (the paper's Fig. 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kikuchipy_geomdic.indexing.variants import variant_names
    from kikuchipy_geomdic.plotting import plot_variants

    fig = plot_variants(xmap, names=variant_names(ops))
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: Properties of a reindexing with --pseudo-symmetry written as extra
#: columns of the .ang file (the orix h5 file holds every property).
ANG_VARIANT_COLUMNS = (
    "variant",
    "domain",
    "confidence",
    "cross_variant_margin",
    "variant_significance",
)


def _write_ang(path: Path, xmap, detector) -> None:
    """Write an .ang file (orix) with NCC as confidence index, the input's
    image quality if it has one, the variant properties as extra columns
    (:data:`ANG_VARIANT_COLUMNS`, those the map has) and the detector's
    mean PC (EDAX TSL convention) in the header, where OIM Analysis looks
    for it."""
    from orix import io as orix_io

    kw = {"confidence_index_prop": "scores"}
    extra = [k for k in ANG_VARIANT_COLUMNS if k in xmap.prop]
    if extra:
        kw["extra_prop"] = extra
    if "iq" in xmap.prop:
        kw["image_quality_prop"] = "iq"
    orix_io.save(str(path), xmap, overwrite=True, **kw)
    pc = _one_pc(detector).pc_tsl().reshape(3)
    lines = path.read_text().split("\n")
    for i, line in enumerate(lines):
        if not line.startswith("#"):
            break
        for key, value in zip(("x-star", "y-star", "z-star"), pc, strict=True):
            if line.split()[1:2] == [key]:
                lines[i] = f"# {key:<22} {value:.6f}"
    path.write_text("\n".join(lines))


def _one_pc(det):
    """The detector with its mean PC (for the summary)."""
    new = det.deepcopy()
    new.pc = det.pc_average
    return new


# --------------------------------------------------------------------- #
# Parser
# --------------------------------------------------------------------- #


def _common_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "patterns",
        metavar="PATTERNS",
        help="EBSD map: any file kikuchipy.load reads (EDAX, Oxford or Bruker h5ebsd, "
        "NORDIF, kikuchipy h5ebsd, ...); read lazily",
    )
    common.add_argument(
        "--orientations",
        metavar="MAP",
        help="starting orientations: a crystal map orix reads (.ang, .ctf, orix h5); "
        "default: the orientations stored with the patterns",
    )
    common.add_argument(
        "--master-pattern",
        metavar="MP",
        required=True,
        help="master pattern file kikuchipy reads (e.g. EMsoft h5), or a shipped one: "
        + ", ".join(MASTER_PATTERN_NAMES),
    )
    common.add_argument(
        "--energy", metavar="KV", type=float, required=True, help="beam energy in kV"
    )
    common.add_argument(
        "--phase",
        metavar="NAME",
        help="name or id of the map's phase to use, which must match the master "
        "pattern's (default: the map's only indexed phase)",
    )
    common.add_argument(
        "--pseudo-symmetry",
        metavar="OPS",
        help="operators of the material's pseudo-symmetric variants: a name the package "
        "knows (BaTiO3: its six c-axis variants) or an .npy or text file of an (n, 4) "
        "array of unit quaternions (crystal frame, acting as op * rotation, identity left "
        "out). refine: each calibration point takes the variant its pattern shows; reindex: "
        "each point is refined in every variant and writes its variant, domain (the variant "
        "in the parent crystal's frame), confidence, margin and significance (calls within "
        "the pattern's noise get converged 0), and domains.png (with "
        "--method kikuchipy: its pseudo_symmetry_index and the domain, no figure)",
    )
    geo = common.add_argument_group("starting geometry (default: the pattern file's metadata)")
    geo.add_argument(
        "--pc",
        metavar=("X", "Y", "Z"),
        nargs=3,
        type=float,
        help="projection centre in --convention",
    )
    geo.add_argument(
        "--convention",
        choices=("bruker", "edax", "tsl", "oxford", "emsoft", "emsoft4", "emsoft5"),
        type=str.lower,
        help="convention of --pc (default bruker; emsoft = emsoft5)",
    )
    geo.add_argument("--tilt", type=float, metavar="DEG", help="detector tilt")
    geo.add_argument("--sample-tilt", type=float, metavar="DEG", help="sample tilt")
    geo.add_argument(
        "--azimuthal",
        type=float,
        metavar="DEG",
        help="detector azimuthal angle (kikuchipy >= 0.12 sign)",
    )
    geo.add_argument("--twist", type=float, metavar="DEG", help="detector twist")
    geo.add_argument(
        "--px-size", type=float, metavar="UM", help="unbinned detector pixel size in micrometres"
    )
    geo.add_argument("--binning", type=float, metavar="B", help="detector binning")
    run = common.add_argument_group("running")
    run.add_argument("--overwrite", action="store_true", help="replace results already in --out")
    run.add_argument("--quiet", action="store_true", help="no progress output")
    run.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the dask work on a running dask.distributed scheduler (address "
        "such as tcp://host:8786, or a scheduler file .json); see docs/cluster.md",
    )
    run.add_argument("--traceback", action="store_true", help="show the full traceback of errors")
    return common


def _parser() -> argparse.ArgumentParser:
    from kikuchipy_geomdic.geometry import DEFAULT_PARAMETERS, PARAMETERS

    parser = argparse.ArgumentParser(
        prog="kikuchipy-geomdic",
        description="Global DIC-based EBSD sample-detector geometry calibration.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="calibrate a synthetic silicon map with a known, perturbed geometry",
        description=(
            "Simulate a silicon map with a known geometry, start from a perturbed "
            "one with orientations indexed at it, calibrate, and print start, "
            "refined and true values with standard errors."
        ),
    )
    demo.add_argument("--rows", type=int, default=10, help="map rows (default 10)")
    demo.add_argument("--cols", type=int, default=10, help="map columns (default 10)")
    demo.add_argument("--size", type=int, default=120, help="pattern side in px (default 120)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--points", type=int, default=100, help="calibration points (default 100)")
    demo.add_argument(
        "--dose",
        type=float,
        default=150,
        help="mean counts per pixel of the camera patterns (background lobe, blur, shot "
        "noise, static and dynamic background removal; default 150; 0: noise-free, "
        "unprocessed)",
    )
    demo.add_argument(
        "--paper",
        action="store_true",
        help="the paper's idealised start instead: noise-free, orientations = truth "
        "with zero-mean scatter, and the matching orientation prior",
    )
    demo.add_argument(
        "--out", default="geomdic-demo", help="folder for the figures (default geomdic-demo)"
    )
    demo.set_defaults(func=_demo)

    common = _common_parser()
    refine = sub.add_parser(
        "refine",
        parents=[common],
        help="calibrate the sample-detector geometry of a map",
        description=(
            "Calibrate PC, detector tilt, azimuthal and sample tilt of an EBSD map by "
            "global DIC. Writes to --out: the calibrated detector in kikuchipy's text "
            "format (detector.txt, Bruker; detector_<convention>.txt for tsl, oxford, "
            "emsoft4 and emsoft5), summary.json (the geometry in every PC convention, "
            "the angles, versions), history.csv and four diagnostic figures."
        ),
        epilog=(
            "example: kikuchipy-geomdic refine map.h5 --orientations map.ang "
            "--master-pattern Si --energy 20 --pc 0.51 0.27 0.62 --px-size 70 "
            "--binning 8 --out calibration"
        ),
    )
    refine.add_argument(
        "--parameters",
        nargs="+",
        choices=PARAMETERS,
        default=list(DEFAULT_PARAMETERS),
        metavar="NAME",
        help=f"parameters to refine (default: {' '.join(DEFAULT_PARAMETERS)}; "
        f"choices: {' '.join(PARAMETERS)})",
    )
    refine.add_argument(
        "--solver",
        choices=("joint", "paper"),
        default="joint",
        help="joint: geometry and one rotation per point from every pattern's field "
        "(default); paper: the paper's averaged-field loop",
    )
    refine.add_argument(
        "--dic-only",
        action="store_true",
        help="skip the full-field stage (Gauss-Newton on the intensities) after the DIC "
        "stage: for a master pattern from another simulator than the one that "
        "describes the patterns, whose intensities differ more than its band positions",
    )
    refine.add_argument(
        "--orientation-prior",
        type=float,
        default=None,
        metavar="DEG",
        help="RMS error of the starting orientations, believed independent and "
        "zero-mean (default: none; the angles are then measured from the PC field only)",
    )
    refine.add_argument(
        "--points",
        type=_positive_int,
        default=100,
        metavar="N",
        help="calibration points spread over the map (default 100)",
    )
    refine.add_argument(
        "--max-iterations",
        type=_positive_int,
        default=10,
        metavar="N",
        help="upper bound on geometry updates (default 10)",
    )
    refine.add_argument(
        "--rois",
        type=_positive_int,
        nargs=2,
        default=[8, 8],
        metavar=("ROWS", "COLS"),
        help="ROI grid of the displacement field (default 8 8)",
    )
    refine.add_argument("--seed", type=int, default=0, help="seed of the DIC noise (default 0)")
    _command_output(refine, "refine", _refine)

    reidx = sub.add_parser(
        "reindex",
        parents=[common],
        help="refine every orientation of a map with a calibrated detector",
        description=(
            "Refine the orientation of every indexed point of the map with a calibrated "
            "detector (this package's Gauss-Newton solver, or kikuchipy's "
            "refine_orientation with --method kikuchipy; through dask: lazy, chunk by "
            "chunk, on a dask.distributed cluster with --scheduler). Writes to --out "
            "xmap_refined.ang, xmap_refined.h5 (orix) and reindex.json; with "
            "--pseudo-symmetry each point's variant, domain, confidence, margin and "
            "significance in both "
            "maps and the domain figure domains.png."
        ),
        epilog=(
            "example: kikuchipy-geomdic reindex map.h5 --orientations map.ang "
            "--master-pattern Si --energy 20 --detector calibration --out reindexed"
        ),
    )
    reidx.add_argument(
        "--detector",
        metavar="CAL",
        help="calibrated detector: a refine output folder, its detector*.txt or "
        "summary.json (default: the pattern file's detector with the geometry options)",
    )
    reidx.add_argument(
        "--method",
        choices=("geomdic", "kikuchipy"),
        default="geomdic",
        help="geomdic (default): this package's Gauss-Newton solver, poor points "
        "re-seeded from their neighbours and flagged; kikuchipy: kikuchipy's "
        "refine_orientation",
    )
    reidx.add_argument(
        "--kikuchipy-method",
        default="minimize",
        help="with --method kikuchipy: its optimisation method (default minimize: Nelder-Mead)",
    )
    reidx.add_argument(
        "--method-kwargs",
        metavar="JSON",
        help="with --method kikuchipy: keyword arguments of its method as JSON, e.g. "
        '\'{"method": "Powell"}\'',
    )
    reidx.add_argument(
        "--trust-region",
        type=float,
        nargs=3,
        metavar=("D1", "D2", "D3"),
        help="with --method kikuchipy: +- bounds in degrees on the three Euler angles",
    )
    _command_output(reidx, "reindex", _reindex)
    return parser


def _command_output(parser: argparse.ArgumentParser, command: str, func) -> None:
    """The ``--out`` folder of a command (default ``geomdic-<command>``)
    and the function that runs it."""
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=f"geomdic-{command}",
        help=f"output folder (default geomdic-{command})",
    )
    parser.set_defaults(func=func)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not positive")
    return value


def main(argv: list[str] | None = None) -> int:
    """Run the command line.

    Parameters
    ----------
    argv
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    status
        Exit code: 0 on success, 2 on an error (a one-line message on
        stderr), 130 when interrupted.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    if args.command == "demo":
        return args.func(args)
    args.argv = argv
    try:
        with _cli_warnings():
            return args.func(args)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (CLIError, OSError, ValueError) as e:
        if getattr(args, "traceback", False):
            raise
        print(f"{PROG}: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
