"""Master patterns and phases of silicon, tetragonal BaTiO3, nickel and iron.

Master patterns
---------------
:func:`master_pattern` returns a Lambert master pattern (both hemispheres)
for silicon, tetragonal BaTiO3, nickel or any orix
:class:`~orix.crystal_map.Phase`: dynamical for Si, BaTiO3 and Ni from the
package data, or kinematical, built here with diffsims/kikuchipy for any
phase. For nickel there is a second, independent dynamical master pattern
(``kind="emsoft"``), so that "experimental" patterns can be simulated with
one simulator and calibrated with another; for BaTiO3 and the iron phases
ferrite (``"Fe_bcc"``), austenite (``"Fe_fcc"``) and bct martensite
(``"Fe_bct"``) the second simulator is de-ebsd (``kind="de-ebsd"``) or
ebsdsim (``kind="ebsdsim"``), whichever is not the default.

Data and credits
----------------
- ``data/Si_dynamical.npz`` and ``data/Ni_dynamical.npz``: computed with
  ebsdsim 0.2.4 (MIT licence), 20 kV, sample tilt 70 deg, Lambert
  201 x 201. Each is ebsdsim's per-energy-bin master pattern read with
  ``kikuchipy.load(path, hemisphere="both")`` and averaged over the energy
  bins with ebsdsim's ``bin_weights`` (``np.average`` in float64, stored
  as float32); the npz keeps the CIF the simulation used. Ni from
  ``data/Ni.cif`` (a = 3.524 angstrom), the lattice of the phase attached
  to it.
- ``data/BaTiO3_dynamical.npz``: computed with de-ebsd 0.2.1
  (GPL-3.0-or-later; Bloch waves, its own Monte Carlo depth profile),
  20 kV, sample tilt 70 deg, dmin 0.04 nm, Lambert 801 x 801 per
  hemisphere from ``data/BaTiO3.cif``. The full grid is shipped, with the
  intensities rounded to float16 (relative error at most 5e-4; patterns
  projected from it correlate with those from the float32 original to
  1 - 1e-7): resampled to 401 x 401 it would lose 4 % of the pattern
  correlation at 120 px. See ``data/README.md``.
- ``data/BaTiO3_ebsdsim.npz`` (``kind="ebsdsim"``): a second BaTiO3
  master pattern, computed with ebsdsim 0.2.4 (MIT) from the same CIF,
  Lambert 401 x 401, dmin 0.05 nm, the 20 kV energy bin: another
  simulator for realistic test data (120 px patterns correlate 0.92 with
  de-ebsd's; ebsdsim's and EMsoft's Ni 0.92).
- ``data/Fe_bcc_dynamical.npz``, ``Fe_fcc_dynamical.npz``,
  ``Fe_bct_dynamical.npz``: ebsdsim 0.2.4 (MIT), made as the Ni one
  (Lambert 201 x 201, float32) from ``data/Fe_bcc.cif`` (Im-3m,
  a = 2.8665 angstrom), ``Fe_fcc.cif`` (Fm-3m, a = 3.60 angstrom) and
  ``Fe_bct.cif`` (I4/mmm, a = 2.85, c = 2.92125 angstrom, c/a = 1.025);
  ``data/Fe_*_deebsd.npz`` (``kind="de-ebsd"``): the same CIFs computed
  with de-ebsd 0.2.1 (GPL-3.0-or-later), the other simulator of
  realistic multi-phase test data. Settings, times and the two
  simulators' agreement: ``data/README.md``.
- ``kind="emsoft"``: kikuchipy's shipped EMsoft Ni master pattern
  (``kikuchipy.data.nickel_ebsd_master_pattern_small``, 20 kV, 401 x 401,
  uint8; simulated with EMsoft, Callahan and De Graef, Microsc.
  Microanal. 19 (2013) 1255; data set under CC BY 4.0, shipped with
  kikuchipy), read offline from the kikuchipy installation, not copied
  into this package.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting,
calibration.
"""

from __future__ import annotations

import functools
from importlib import resources

import numpy as np
from kikuchipy.signals import EBSDMasterPattern
from orix.crystal_map import Phase

__all__ = ["phase", "master_pattern", "stretched"]

_DATA = resources.files("kikuchipy_geomdic") / "data"
#: The iron phases, each shipped from ebsdsim ("dynamical", the
#: calibration's) and from de-ebsd (the other simulator of test data)
_IRON = ("Fe_bcc", "Fe_fcc", "Fe_bct")
#: File and simulator of each shipped dynamical master pattern by kind:
#: "dynamical" is the best one, "ebsdsim" ebsdsim's (the same for Si, Ni
#: and iron), "de-ebsd" de-ebsd's
_DYNAMICAL_FILES = {
    "dynamical": {
        "Si": ("Si_dynamical.npz", "ebsdsim 0.2.4"),
        "Ni": ("Ni_dynamical.npz", "ebsdsim 0.2.4"),
        "BaTiO3": ("BaTiO3_dynamical.npz", "de-ebsd 0.2.1"),
        **{k: (f"{k}_dynamical.npz", "ebsdsim 0.2.4") for k in _IRON},
    },
    "ebsdsim": {
        "Si": ("Si_dynamical.npz", "ebsdsim 0.2.4"),
        "Ni": ("Ni_dynamical.npz", "ebsdsim 0.2.4"),
        "BaTiO3": ("BaTiO3_ebsdsim.npz", "ebsdsim 0.2.4"),
        **{k: (f"{k}_dynamical.npz", "ebsdsim 0.2.4") for k in _IRON},
    },
    "de-ebsd": {
        "BaTiO3": ("BaTiO3_dynamical.npz", "de-ebsd 0.2.1"),
        **{k: (f"{k}_deebsd.npz", "de-ebsd 0.2.1") for k in _IRON},
    },
}
_KINDS = ("auto", "dynamical", "ebsdsim", "de-ebsd", "kinematical", "emsoft")
_PHASES = {
    "si": "Si",
    "silicon": "Si",
    "batio3": "BaTiO3",
    "bto": "BaTiO3",
    "ni": "Ni",
    "nickel": "Ni",
    "fe_bcc": "Fe_bcc",
    "ferrite": "Fe_bcc",
    "fe_fcc": "Fe_fcc",
    "austenite": "Fe_fcc",
    "fe_bct": "Fe_bct",
    "martensite": "Fe_bct",
}


def _phase_key(name: str) -> str:
    try:
        return _PHASES[name.lower()]
    except KeyError:
        raise ValueError(
            f"Unknown phase {name!r}: use 'Si', 'BaTiO3', 'Ni', 'Fe_bcc' (ferrite), "
            "'Fe_fcc' (austenite), 'Fe_bct' (martensite) or pass an orix Phase"
        ) from None


def phase(name: str) -> Phase:
    """Return the orix phase of silicon, tetragonal BaTiO3, nickel or iron.

    Parameters
    ----------
    name
        "Si", "BaTiO3", "Ni", "Fe_bcc" (or "ferrite"), "Fe_fcc" (or
        "austenite") or "Fe_bct" (or "martensite"), case-insensitive.

    Returns
    -------
    phase
        Phase read from the CIF shipped with the package (lattice
        parameters in angstrom).

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.master_patterns import phase
    >>> phase("BaTiO3").point_group.name
    '4mm'
    >>> p = phase("Ni")
    >>> p.point_group.name, p.structure.lattice.a
    ('m-3m', 3.524)
    >>> p = phase("martensite")
    >>> p.name, p.point_group.name, p.structure.lattice.c
    ('Fe_bct', '4/mmm', 2.92125)
    """
    key = _phase_key(name)
    with resources.as_file(_DATA / f"{key}.cif") as path:
        p = Phase.from_cif(str(path))
    p.name = key
    return p


def master_pattern(
    phase_or_name: str | Phase = "Si",
    kind: str = "auto",
    energy: float = 20,
    half_size: int = 100,
    min_dspacing: float = 0.8,
) -> EBSDMasterPattern:
    """Return a Lambert master pattern with both hemispheres.

    Parameters
    ----------
    phase_or_name
        A name of :func:`phase` or an orix phase (lattice parameters in
        angstrom).
    kind
        "dynamical" (package data at 20 kV only: Si, Ni and iron computed
        with ebsdsim, BaTiO3 with de-ebsd), "ebsdsim" (the same for Si, Ni
        and iron; for BaTiO3 a 401 x 401 ebsdsim pattern, a second
        simulator for realistic test data), "de-ebsd" (BaTiO3 and iron:
        de-ebsd's, for iron the second simulator), "emsoft" (Ni only: kikuchipy's shipped EMsoft
        master pattern, 20 kV, 401 x 401, to simulate "experimental"
        patterns with another simulator than the one used to calibrate),
        "kinematical" (any phase, any energy), or "auto": dynamical
        where available, else kinematical.
    energy
        Beam energy in kV (kinematical only; dynamical and EMsoft ones
        are 20 kV).
    half_size
        Half the side of the kinematical master pattern in pixels.
    min_dspacing
        Smallest interplanar spacing of the kinematical reflectors, in
        angstrom.

    Returns
    -------
    master_pattern
        :class:`~kikuchipy.signals.EBSDMasterPattern`, Lambert projection,
        hemisphere "both", float32. ``metadata.General.title`` says which
        kind it is. Its phase is :func:`phase` of the name (lattice in
        angstrom), also for the EMsoft Ni pattern (kikuchipy's phase of
        it is in nm), so that crystal maps simulated from one Ni master
        pattern can be refined with kikuchipy against the other.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.master_patterns import master_pattern
    >>> mp = master_pattern("Si")
    >>> mp.projection, mp.hemisphere, mp.metadata.General.title
    ('lambert', 'both', 'Si dynamical (ebsdsim 0.2.4)')
    >>> master_pattern("BaTiO3").metadata.General.title
    'BaTiO3 dynamical (de-ebsd 0.2.1)'
    >>> master_pattern("BaTiO3", kind="ebsdsim").data.shape
    (2, 401, 401)
    >>> master_pattern("Ni", kind="emsoft").metadata.General.title
    'Ni dynamical (EMsoft, kikuchipy data)'
    >>> master_pattern("ferrite", kind="de-ebsd").metadata.General.title
    'Fe_bcc dynamical (de-ebsd 0.2.1)'
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {', '.join(map(repr, _KINDS))}, not {kind!r}")
    if isinstance(phase_or_name, Phase):
        if kind in ("dynamical", "ebsdsim", "de-ebsd", "emsoft"):
            raise ValueError(
                "Dynamical master patterns exist only for the named phases of phase() "
                "(EMsoft: 'Ni')"
            )
        return _kinematical(phase_or_name, energy, half_size, min_dspacing).deepcopy()
    key = _phase_key(phase_or_name)
    if kind == "emsoft":
        if key != "Ni":
            raise ValueError(f"The EMsoft master pattern is for 'Ni' only, not {key!r}")
        if energy != 20:
            raise ValueError("The EMsoft Ni master pattern is for 20 kV")
        return _emsoft_ni().deepcopy()
    if kind == "kinematical":
        return _kinematical_named(key, energy, half_size, min_dspacing).deepcopy()
    if energy != 20:
        if kind in ("dynamical", "ebsdsim", "de-ebsd"):
            raise ValueError("The shipped dynamical master patterns are for 20 kV")
        return _kinematical_named(key, energy, half_size, min_dspacing).deepcopy()
    if kind == "de-ebsd" and key not in _DYNAMICAL_FILES[kind]:
        raise ValueError(f"No de-ebsd master pattern of {key!r} is shipped")
    return _dynamical(key, "dynamical" if kind == "auto" else kind).deepcopy()


@functools.lru_cache(maxsize=8)
def _dynamical(key: str, kind: str = "dynamical") -> EBSDMasterPattern:
    name, simulator = _DYNAMICAL_FILES[kind][key]
    with resources.as_file(_DATA / name) as path:
        npz = np.load(path)
        # BaTiO3 is stored as float16 to keep its 801 x 801 grid small
        data = npz["data"].astype(np.float32)
    mp = _lambert_master_pattern(data, phase(key))
    mp.metadata.General.title = f"{key} dynamical ({simulator})"
    return mp


def _lambert_master_pattern(data: np.ndarray, phase_) -> EBSDMasterPattern:
    """The master pattern of Lambert *data* (2, n, n), north then south,
    of the orix *phase_*, laid out as the package's ``*_dynamical.npz``."""
    n = data.shape[-1]
    axes = [
        {"size": 2, "name": "hemisphere", "scale": 1, "offset": 0, "units": ""},
        {"size": n, "name": "height", "scale": 1, "offset": -(n // 2), "units": "px"},
        {"size": n, "name": "width", "scale": 1, "offset": -(n // 2), "units": "px"},
    ]
    return EBSDMasterPattern(
        data, axes=axes, projection="lambert", hemisphere="both", phase=phase_
    )


@functools.lru_cache(maxsize=1)
def _emsoft_ni() -> EBSDMasterPattern:
    import kikuchipy as kp

    # Shipped in the kikuchipy wheel (offline): EMsoft, 20 kV, 401 x 401,
    # uint8. kikuchipy's phase has its lattice in nm; give it the
    # package's Ni phase (angstrom) so that kikuchipy, which requires
    # identical phases, refines maps simulated from it with the ebsdsim
    # Ni master pattern and vice versa
    mp = kp.data.nickel_ebsd_master_pattern_small(projection="lambert", hemisphere="both")
    mp.data = mp.data.astype(np.float32)
    mp.phase = phase("Ni")
    mp.metadata.General.title = "Ni dynamical (EMsoft, kikuchipy data)"
    return mp


@functools.lru_cache(maxsize=8)
def _kinematical_named(key, energy, half_size, min_dspacing) -> EBSDMasterPattern:
    return _kinematical(phase(key), energy, half_size, min_dspacing)


def _kinematical(p: Phase, energy, half_size, min_dspacing) -> EBSDMasterPattern:
    from diffsims.crystallography import ReciprocalLatticeVector
    from kikuchipy.simulations import KikuchiPatternSimulator

    g = ReciprocalLatticeVector.from_min_dspacing(p.deepcopy(), min_dspacing)
    # Without sanitising, Si gets a non-zero F(200), a forbidden reflection
    g.sanitise_phase()
    g.calculate_structure_factor()
    f = abs(g.structure_factor)
    g = g[f > 1e-4 * f.max()]
    g.calculate_theta(energy * 1e3)
    sim = KikuchiPatternSimulator(g)
    # Point groups without inversion (BaTiO3's 4mm) need both hemispheres
    mp = sim.calculate_master_pattern(half_size=half_size, hemisphere="both")
    mp = mp.as_lambert(show_progressbar=False)
    mp.data = mp.data.astype(np.float32)
    mp.metadata.General.title = f"{p.name} kinematical"
    return mp


def stretched(
    master_pattern: EBSDMasterPattern, stretch: float, energy: float = 20
) -> EBSDMasterPattern:
    """Return the master pattern of the crystal of *master_pattern* with
    its c axis (crystal z) *stretch* times as long: c/a changed, as in a
    crystal that is not its CIF's.

    Every Lambert pixel takes the intensity the master pattern holds at
    its direction ``u`` mapped by the stretch's inverse,
    ``diag(1, 1, 1 / stretch) u`` normalised (the projection's bilinear
    lookup): the bands and zone axes move as the lattice's directions do;
    their widths, which change with the d-spacings by as little, do not.
    Data from another lattice than the CIF's for the benchmarks, from any
    simulator's master pattern.

    Parameters
    ----------
    master_pattern
        Lambert master pattern, both hemispheres.
    stretch
        The c axis' length over the master pattern's (> 0).
    energy
        Beam energy in kV (the slice of a multi-energy master pattern).

    Returns
    -------
    master_pattern
        A new :class:`~kikuchipy.signals.EBSDMasterPattern` (float32), its
        phase's lattice stretched alike.

    Examples
    --------
    >>> mp = master_pattern("BaTiO3", kind="ebsdsim")
    >>> flat = stretched(mp, 0.994)
    >>> flat.data.shape == mp.data.shape, round(flat.phase.structure.lattice.c, 4)
    (True, 4.0123)
    """
    from kikuchipy.signals.util._master_pattern import _lambert2vector

    from kikuchipy_geomdic.indexing._lambert import _project
    from kikuchipy_geomdic.indexing.orientation import master_pattern_arrays

    if not stretch > 0:
        raise ValueError(f"stretch must be positive, not {stretch!r}")
    arrays = master_pattern_arrays(master_pattern, energy)
    n = arrays.upper.shape[-1]
    grid = np.linspace(-1, 1, n)
    x, y = np.meshgrid(grid, grid)
    v = _lambert2vector(x.ravel(), y.ravel())
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    out = np.empty((2, n * n), dtype=np.float32)
    jac = np.empty((1, 3))
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    for h, sign in enumerate((1.0, -1.0)):
        d = v * [1.0, 1.0, sign / stretch]
        d = np.ascontiguousarray(d / np.linalg.norm(d, axis=1, keepdims=True))
        value = np.empty(n * n)
        _project(identity, d, arrays.upper, arrays.lower, arrays.scale, value, jac, False)
        out[h] = value
    new = EBSDMasterPattern(
        out.reshape(2, n, n),
        projection="lambert",
        hemisphere="both",
        phase=master_pattern.phase.deepcopy(),
    )
    lat = new.phase.structure.lattice
    lat.setLatPar(c=lat.c * stretch)
    new.metadata.General.title = f"{master_pattern.metadata.General.title}, c axis x {stretch:g}"
    return new
