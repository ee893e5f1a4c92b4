"""Reading a command's inputs: patterns, crystal map, master pattern and
starting detector, each checked against the others; every problem a user
can fix is a :class:`CLIError`.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
from pathlib import Path

from kikuchipy_geomdic.cli._run import CLIError, _one_line, _warn

__all__ = [
    "load_patterns",
    "load_crystal_map",
    "load_master_pattern",
    "start_detector",
]


#: Master patterns shipped with the package, by name.
MASTER_PATTERN_NAMES = ("Si", "BaTiO3", "Ni")


_UM = ("um", "µm", "μm", "micron", "microns", "micrometre", "micrometer")
_LENGTH_TO_UM = {"nm": 1e-3, "mm": 1e3}


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
    """The patterns, crystal map, master pattern (a list with several
    ``--master-pattern``) and the phases to refine
    (:class:`~kikuchipy_geomdic.indexing.phases_to_refine.PhaseToRefine`) of
    ``refine`` and ``reindex``, each checked against the others."""
    from kikuchipy_geomdic.indexing.phases_to_refine import phases_to_refine

    signal = load_patterns(args.patterns)
    xmap = load_crystal_map(args.orientations, signal)
    _check_step_sizes(signal, xmap)
    specs = [_named_spec(s) for s in args.master_pattern]
    mps = [load_master_pattern(spec, args.energy) for _, spec in specs]
    if len(mps) > 1 and args.pseudo_symmetry is not None:
        raise CLIError("--pseudo-symmetry takes one --master-pattern (one phase)")
    mp = mps[0] if len(mps) == 1 else mps
    phases = phases_to_refine(xmap, mp, _phase_arg(args.phase))
    for (name, spec), p in zip(specs, phases):
        own = xmap.phases[p.phase_id].name
        if name is not None and name.lower() not in (own.lower(), str(p.phase_id)):
            raise CLIError(
                f"--master-pattern {name}={spec}: its phase {p.name!r} is the map's phase "
                f"{own!r} (id {p.phase_id}), not {name!r}"
            )
    return signal, xmap, mp, phases


def _named_spec(spec: str) -> tuple[str | None, str]:
    """``NAME=FILE`` as (NAME, FILE); a file or shipped name as (None, it)."""
    if "=" in spec and not Path(spec).exists():
        name, _, rest = spec.partition("=")
        return name, rest
    return None, spec


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
