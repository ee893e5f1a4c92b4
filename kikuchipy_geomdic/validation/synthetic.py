"""Synthetic EBSD maps with a known geometry and known orientations.

Ground truth is this package's main instrument: a map simulated here comes
with its true geometry and orientations, a perturbed starting geometry and
starting orientations made by one of three start models (the paper's
centred scatter, an uncentred scatter, or orientations refined at the
wrong geometry as a user would have them after indexing; see
:func:`synthetic_map` and :func:`common_rotation`), so that any
calibration can be scored.

Master patterns
---------------
:func:`master_pattern` returns a Lambert master pattern (both hemispheres)
for silicon, tetragonal BaTiO3, nickel or any orix
:class:`~orix.crystal_map.Phase`: dynamical for Si, BaTiO3 and Ni from the
package data, or kinematical, built here with diffsims/kikuchipy for any
phase. For nickel there is a second, independent dynamical master pattern
(``kind="emsoft"``), so that "experimental" patterns can be simulated with
one simulator and calibrated with another.

Data and credits
----------------
- ``data/Si_dynamical.npz`` and ``data/Ni_dynamical.npz``: computed with
  ebsdsim 0.2.4 (MIT licence), 20 kV, sample tilt 70 deg, Lambert
  201 x 201. Each is ebsdsim's per-energy-bin master pattern read with
  ``kikuchipy.load(path, hemisphere="both")`` and averaged over the energy
  bins with ebsdsim's ``bin_weights`` (``np.average`` in float64, stored
  as float32); the npz keeps the CIF the simulation used. Ni was computed
  from ebsdsim's preset ``Ni.cif`` (a = 3.4751 angstrom, 1.4 % below
  nickel's 3.524 angstrom, so its bands are about 1.4 % wider than real
  Ni's), while the phase attached to it, :func:`phase` "Ni" from
  ``data/Ni.cif``, has a = 3.524 angstrom.
- ``data/BaTiO3_dynamical.npz``: computed with de-ebsd 0.2.1
  (GPL-3.0-or-later; Bloch waves, its own Monte Carlo depth profile),
  20 kV, sample tilt 70 deg, dmin 0.04 nm, Lambert 801 x 801 per
  hemisphere from ``data/BaTiO3.cif``. The full grid is shipped, with the
  intensities rounded to float16 (relative error at most 5e-4; patterns
  projected from it correlate with those from the float32 original to
  1 - 1e-7): resampled to 401 x 401 it would lose 4 % of the pattern
  correlation at 120 px. See ``data/README.md``.
- ``data/BaTiO3_ebsdsim.npz`` (``kind="ebsdsim"``): the coarse BaTiO3
  master pattern computed with ebsdsim 0.2.4 (MIT) as Si and Ni, Lambert
  129 x 129, dmin 0.08 nm, from the same CIF; grainy, kept as a second
  simulator.
- ``kind="emsoft"``: kikuchipy's shipped EMsoft Ni master pattern
  (``kikuchipy.data.nickel_ebsd_master_pattern_small``, 20 kV, 401 x 401,
  uint8; simulated with EMsoft, Callahan and De Graef, Microsc.
  Microanal. 19 (2013) 1255; data set under CC BY 4.0, shipped with
  kikuchipy), read offline from the kikuchipy installation, not copied
  into this package.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from typing import NamedTuple

import dask.array as da
import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern, LazyEBSD
from orix.crystal_map import CrystalMap, Phase, PhaseList
from orix.quaternion import Rotation
from scipy import ndimage

from kikuchipy_geomdic.geometry import (
    MapGeometry,
    copy_detector,
    rotation_vectors,
    rotations_from_vectors,
)
from kikuchipy_geomdic.indexing.reindex import quiet
from kikuchipy_geomdic.indexing.variants import VARIANT_NAMES, variant_operators  # noqa: F401
from kikuchipy_geomdic.patterns.simulation import check_master_pattern, simulate_patterns

__all__ = [
    "phase",
    "master_pattern",
    "STRIPE_VARIANTS",
    "perturb_rotations",
    "rotation_vectors",
    "CommonRotation",
    "common_rotation",
    "START_MODELS",
    "default_geometry",
    "DEFAULT_PERTURBATION",
    "SyntheticMap",
    "synthetic_map",
    "MIN_PRIOR",
    "centred_prior",
    "degrade_patterns",
    "Camera",
    "MODERATE",
    "REAL_NI",
    "camera_counts",
]

_DATA = resources.files("kikuchipy_geomdic") / "data"
#: File and simulator of each shipped dynamical master pattern by kind:
#: "dynamical" is the best one, "ebsdsim" ebsdsim's (the same for Si and Ni)
_DYNAMICAL_FILES = {
    "dynamical": {
        "Si": ("Si_dynamical.npz", "ebsdsim 0.2.4"),
        "Ni": ("Ni_dynamical.npz", "ebsdsim 0.2.4"),
        "BaTiO3": ("BaTiO3_dynamical.npz", "de-ebsd 0.2.1"),
    },
    "ebsdsim": {
        "Si": ("Si_dynamical.npz", "ebsdsim 0.2.4"),
        "Ni": ("Ni_dynamical.npz", "ebsdsim 0.2.4"),
        "BaTiO3": ("BaTiO3_ebsdsim.npz", "ebsdsim 0.2.4"),
    },
}
_PHASES = {
    "si": "Si",
    "silicon": "Si",
    "batio3": "BaTiO3",
    "bto": "BaTiO3",
    "ni": "Ni",
    "nickel": "Ni",
}


def _phase_key(name: str) -> str:
    try:
        return _PHASES[name.lower()]
    except KeyError:
        raise ValueError(
            f"Unknown phase {name!r}: use 'Si', 'BaTiO3', 'Ni' or pass an orix Phase"
        ) from None


def phase(name: str) -> Phase:
    """Return the orix phase of silicon, tetragonal BaTiO3 or nickel.

    Parameters
    ----------
    name
        "Si", "BaTiO3" or "Ni" (case-insensitive).

    Returns
    -------
    phase
        Phase read from the CIF shipped with the package (lattice
        parameters in angstrom).

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.synthetic import phase
    >>> phase("BaTiO3").point_group.name
    '4mm'
    >>> p = phase("Ni")
    >>> p.point_group.name, p.structure.lattice.a
    ('m-3m', 3.524)
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
        "Si", "BaTiO3", "Ni" or an orix phase (lattice parameters in
        angstrom).
    kind
        "dynamical" (package data at 20 kV only: Si and Ni computed with
        ebsdsim, BaTiO3 with de-ebsd), "ebsdsim" (the same for Si and Ni;
        for BaTiO3 a coarse, grainy 129 x 129 ebsdsim pattern, a second
        simulator for mismatch tests), "emsoft" (Ni only: kikuchipy's shipped EMsoft
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
    >>> from kikuchipy_geomdic.validation.synthetic import master_pattern
    >>> mp = master_pattern("Si")
    >>> mp.projection, mp.hemisphere, mp.metadata.General.title
    ('lambert', 'both', 'Si dynamical (ebsdsim 0.2.4)')
    >>> master_pattern("BaTiO3").metadata.General.title
    'BaTiO3 dynamical (de-ebsd 0.2.1)'
    >>> master_pattern("BaTiO3", kind="ebsdsim").data.shape
    (2, 129, 129)
    >>> master_pattern("Ni", kind="emsoft").metadata.General.title
    'Ni dynamical (EMsoft, kikuchipy data)'
    """
    if kind not in ("auto", "dynamical", "ebsdsim", "kinematical", "emsoft"):
        raise ValueError(
            f"kind must be 'auto', 'dynamical', 'ebsdsim', 'kinematical' or 'emsoft', not {kind!r}"
        )
    if isinstance(phase_or_name, Phase):
        if kind in ("dynamical", "ebsdsim", "emsoft"):
            raise ValueError(
                "Dynamical master patterns exist only for 'Si', 'BaTiO3' and 'Ni' (EMsoft: 'Ni')"
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
        if kind in ("dynamical", "ebsdsim"):
            raise ValueError("The shipped dynamical master patterns are for 20 kV")
        return _kinematical_named(key, energy, half_size, min_dspacing).deepcopy()
    return _dynamical(key, "ebsdsim" if kind == "ebsdsim" else "dynamical").deepcopy()


#: Variants (indices into :func:`variant_operators`) of the diagonal
#: stripes of ``synthetic_map(orientations="stripes")``, in order: the
#: parent (+z) between a 90 deg domain (c along +x) and a 180 deg one
#: (-z), so that the map has both kinds of domain wall and the parent
#: covers about half of it.
STRIPE_VARIANTS = (0, 2, 0, 1)


def _random_rotations(n: int, rng: np.random.Generator) -> Rotation:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Rotation(q)


def perturb_rotations(rotations: Rotation, scatter: float, rng, centred: bool = True) -> Rotation:
    """Return rotations times small random rotations.

    Parameters
    ----------
    rotations
        Rotations to perturb (any shape; flattened).
    scatter
        RMS misorientation angle in degrees. Each rotation is multiplied
        (on the right, in the sample frame) by a rotation whose rotation
        vector has normal components of standard deviation
        ``scatter / sqrt(3)``.
    rng
        :class:`numpy.random.Generator` or a seed.
    centred
        Subtract the mean rotation vector so that the perturbations have
        exactly zero mean (the paper's perturbation study). A common
        rotation of all orientations is indistinguishable from a change
        of the detector angles, so the random common part of uncentred
        perturbations (of size ``scatter / sqrt(n)``, see
        :func:`common_rotation`) is a bias no calibration can remove.
        The same *rng* state draws the same numbers either way: only the
        centring differs.

    Returns
    -------
    perturbed
        Flat :class:`~orix.quaternion.Rotation`.

    Examples
    --------
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation.synthetic import common_rotation, perturb_rotations
    >>> truth = Rotation.identity(100)
    >>> angle, _ = common_rotation(perturb_rotations(truth, 0.3, 0), truth)
    >>> bool(angle < 1e-12)
    True
    >>> angle, _ = common_rotation(perturb_rotations(truth, 0.3, 0, centred=False), truth)
    >>> bool(0.005 < angle < 0.1)
    True
    """
    rng = np.random.default_rng(rng)
    rotations = rotations.flatten()
    v = rng.normal(scale=np.deg2rad(scatter) / np.sqrt(3), size=(rotations.size, 3))
    if centred and rotations.size > 1:
        v -= v.mean(axis=0)
    return rotations * rotations_from_vectors(v)


class CommonRotation(NamedTuple):
    """Mean deviation of starting orientations from the truth."""

    #: Angle in degrees of the mean rotation vector.
    angle: float
    #: Unit axis (3,) in the sample frame; ``[0, 0, 1]`` when *angle* is 0.
    axis: np.ndarray

    @property
    def vector(self) -> np.ndarray:
        """The mean rotation vector (3,) in degrees."""
        return self.angle * self.axis


def _rotations_of(r) -> Rotation:
    if isinstance(r, CrystalMap):
        return r.rotations.flatten()
    return Rotation(r).flatten()


def common_rotation(
    start: Rotation | CrystalMap, truth: Rotation | CrystalMap, symmetry=None
) -> CommonRotation:
    """Return the common part of the deviations of *start* from *truth*.

    The deviation of each orientation is the sample-frame rotation ``T``
    with ``start = truth * T`` (orix's right factor, as in
    :func:`perturb_rotations`), i.e. ``T = ~truth * start``. Its common
    part is the mean of the rotation vectors of ``T`` over the map (for
    deviations of a few degrees, the mean rotation up to terms of second
    order in the angles). It is what no calibration can tell from a change of the
    detector angles: zero for the "centred" start of
    :func:`synthetic_map`, of order ``orientation_error / sqrt(n)`` for
    "uncentred" and larger for "indexed", where the geometry error was
    absorbed into the orientations.

    Parameters
    ----------
    start, truth
        Rotations or crystal maps of the same size (flattened; for crystal
        maps, the points in the data).
    symmetry
        Optional orix :class:`~orix.quaternion.Symmetry` (e.g. the phase's
        point group): each start is first replaced by the equivalent
        ``op * start`` (crystal-frame operator, left factor) closest to its
        truth. Not needed for starts within a few degrees of the truth.

    Returns
    -------
    common
        :class:`CommonRotation` ``(angle, axis)``, angle in degrees,
        unpacks as a tuple; ``common.vector`` is the mean rotation vector
        in degrees.

    Examples
    --------
    >>> import numpy as np
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation.synthetic import common_rotation
    >>> truth = Rotation.random(5)
    >>> t = Rotation.from_axes_angles([0, 0, 1], np.deg2rad(0.5))
    >>> angle, axis = common_rotation(truth * t, truth)
    >>> round(angle, 6), np.round(axis, 6).tolist()
    (0.5, [0.0, 0.0, 1.0])
    """
    s = _rotations_of(start)
    t = _rotations_of(truth)
    if s.size != t.size:
        raise ValueError(f"start has {s.size} rotations, truth {t.size}")
    dev = ~t * s
    if symmetry is not None:
        best = np.abs(dev.a)
        q = dev.data.copy()
        ops = getattr(symmetry, "proper_subgroup", symmetry)
        for op in Rotation(ops).flatten():
            cand = ~t * (op * s)
            better = np.abs(cand.a) > best
            best = np.where(better, np.abs(cand.a), best)
            q[better] = cand.data[better]
        dev = Rotation(q)
    v = np.rad2deg(rotation_vectors(dev).mean(axis=0))
    angle = float(np.linalg.norm(v))
    axis = v / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    return CommonRotation(angle, axis)


def default_geometry(
    navigation_shape: tuple[int, int] = (10, 10),
    shape: tuple[int, int] = (120, 120),
    field_of_view: float = 500.0,
) -> MapGeometry:
    """Return a realistic true geometry for a synthetic map.

    A 480 x 480 detector of 70 um pixels (33.6 mm wide) binned to
    *shape*, about 21 mm from the sample, sample tilt 70 deg, and a map
    *field_of_view* micrometres wide: large enough that the PC moves by
    about 1.5 % of the detector width across the map, as it does at low
    magnification on a real microscope. This is what makes the angles
    observable: for one pattern a change of tilt, azimuthal or twist is
    reproduced exactly by a change of orientation, so with per-point
    orientations the angles are seen only through the PC field.

    Parameters
    ----------
    navigation_shape
        Map shape (rows, columns).
    shape
        Detector shape (rows, columns) after binning; 480 must be a
        multiple of the number of columns.
    field_of_view
        Map width and height in micrometres.

    Returns
    -------
    geometry
        :class:`~kikuchipy_geomdic.geometry.MapGeometry` with reference
        at the map centre.
    """
    ny, nx = navigation_shape
    step = field_of_view / max(max(ny, nx) - 1, 1)
    return MapGeometry(
        pc=(0.51, 0.27, 0.62),
        shape=shape,
        px_size=70.0,
        binning=480 / shape[1],
        step_sizes=(step, step),
        navigation_shape=navigation_shape,
        tilt=2.0,
        azimuthal=0.3,
        sample_tilt=70.0,
        twist=0.0,
    )


#: Starting geometry error used when none is given: a mean displacement of
#: about 1.5 % of the detector width (measured by DIC), inside the paper's
#: reliable range of 4 %.
DEFAULT_PERTURBATION = {
    "pcx": 0.015,
    "pcy": -0.012,
    "pcz": 0.018,
    "tilt": 0.9,
    "azimuthal": -0.75,
    "sample_tilt": 0.0,
}


@dataclass(frozen=True)
class SyntheticMap:
    """A synthetic EBSD map with its ground truth and a starting point.

    Attributes
    ----------
    signal
        :class:`~kikuchipy.signals.EBSD` or ``LazyEBSD`` with navigation
        axes scaled by the step sizes (um), carrying the *starting*
        detector and crystal map, as a file from a microscope would.
    geometry, detector, xmap
        The truth: geometry, detector with the PC of every map point, and
        orientations (property ``variant`` for BaTiO3 variant maps).
    start_geometry, start_detector, start_xmap
        The starting point: perturbed geometry and starting orientations
        made by the start model *start*.
    master_pattern
        The master pattern to calibrate with: the one the map was
        simulated from unless *simulator* says otherwise.
    energy
        Beam energy in kV.
    start
        Start model of the orientations, one of :data:`START_MODELS`
        (see :func:`synthetic_map`).
    simulator
        The master pattern the patterns were simulated from.
    camera
        The :class:`Camera` that recorded them, or None for model-family
        patterns (:func:`degrade_patterns`).
    """

    signal: EBSD
    geometry: MapGeometry
    detector: EBSDDetector
    xmap: CrystalMap
    start_geometry: MapGeometry
    start_detector: EBSDDetector
    start_xmap: CrystalMap
    master_pattern: EBSDMasterPattern
    energy: float
    start: str = "centred"
    simulator: EBSDMasterPattern | None = None
    camera: Camera | None = None

    @property
    def start_inputs(self) -> tuple:
        """The first five arguments of
        :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic` for a
        calibration from the start: ``(signal, start_xmap, start_detector,
        master_pattern, energy)``, so that
        ``refine_geometry_dic(*sm.start_inputs, **options)``."""
        return (
            self.signal,
            self.start_xmap,
            self.start_detector,
            self.master_pattern,
            self.energy,
        )


#: Start models of :func:`synthetic_map`: how the starting orientations
#: are made from the true ones.
START_MODELS = ("centred", "uncentred", "indexed")

#: Smallest orientation prior (deg) for a centred start: a start equal to
#: the truth is believed to within this, rather than exactly.
MIN_PRIOR = 0.05


def centred_prior(orientation_error: float) -> float:
    """Return the ``orientation_prior`` matching a centred start.

    A "centred" start (:func:`synthetic_map`, the paper's study design)
    scatters the true orientations by *orientation_error* with no common
    part, so the refinement may believe the start to within that error,
    but never to better than :data:`MIN_PRIOR`.

    Parameters
    ----------
    orientation_error
        RMS error (deg) of the starting orientations.

    Returns
    -------
    prior
        ``orientation_prior`` (deg) of
        :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.synthetic import centred_prior
    >>> centred_prior(0.3), centred_prior(0)
    (0.3, 0.05)
    """
    return max(float(orientation_error), MIN_PRIOR)


def synthetic_map(
    master_pattern: EBSDMasterPattern | str = "Si",
    navigation_shape: tuple[int, int] = (10, 10),
    orientations: str = "random",
    geometry: MapGeometry | None = None,
    shape: tuple[int, int] = (120, 120),
    scatter: float = 0.05,
    perturbation: Mapping[str, float] | None = None,
    orientation_error: float = 0.3,
    dose: float | None = None,
    background: float = 0.0,
    blur: float = 0.0,
    energy: float = 20.0,
    lazy: bool = False,
    seed: int = 0,
    start: str = "centred",
    camera: Camera | None = None,
    simulator: EBSDMasterPattern | str | None = None,
) -> SyntheticMap:
    """Return a synthetic EBSD map with a known geometry and orientations.

    Parameters
    ----------
    master_pattern
        Lambert master pattern, or a name for :func:`master_pattern`.
    navigation_shape
        Map shape (rows, columns).
    orientations
        "single" (one crystal, orientations scattered by *scatter*),
        "random" (uniformly random per point), "grains" (a polycrystal:
        Voronoi grains of :data:`GRAIN_POINTS` points on average, random
        orientations scattered by *scatter* within each, property
        ``grain``), "variants" (BaTiO3-like
        diagonal domains, each one of the six variants of
        :func:`variant_operators` applied to one parent orientation,
        scattered by *scatter*) or "stripes" (diagonal stripes of the
        variants :data:`STRIPE_VARIANTS` of one parent, 90 and 180 deg
        domains, scattered by *scatter*, and a start with the parent's
        variant everywhere: what an indexer that cannot tell the variants
        apart returns). ``xmap.prop["variant"]`` is the true variant
        index *k* of each point (its orientation is
        ``variant_operators()[k] * parent`` times the scatter),
        ``start_xmap.prop["variant"]`` that of the start.
    geometry
        True geometry; default :func:`default_geometry` for this map and
        *shape*.
    shape
        Detector shape, used when *geometry* is not given.
    scatter
        RMS orientation scatter in degrees within a crystal or domain.
    perturbation
        ``{parameter: change}`` from the true to the starting geometry;
        default :data:`DEFAULT_PERTURBATION`. Pass ``{}`` to start at the
        truth.
    orientation_error
        RMS angle in degrees of the random error of the starting
        orientations (see :func:`perturb_rotations` and *start*).
    dose
        Mean electron counts per pixel for Poisson shot noise; ``None``
        for no shot noise.
    background
        Relative amplitude of a smooth, off-centre Gaussian background
        the pattern rides on (0 for none); intensities become
        ``(1 + background * g(x, y)) * pattern``.
    blur
        Standard deviation in pixels of a Gaussian blur (0 for none).
    energy
        Beam energy in kV.
    lazy
        Return a ``LazyEBSD`` whose patterns are simulated chunk by chunk
        when computed (bounded memory for large maps).
    seed
        Seed of everything random: orientations, starting orientations
        and noise. The same seed gives the same map, and for every start
        model the same truth, patterns and random draws.
    start
        How the starting orientations are made (:data:`START_MODELS`):

        - "centred": the truth times a random scatter of RMS
          *orientation_error* centred to exactly zero mean, the paper's
          perturbation study. No common rotation, so no bias that looks
          like a detector-angle error.
        - "uncentred": the same random scatter, not centred: its mean is
          random, of order ``orientation_error / sqrt(n)`` for *n*
          points (see :func:`common_rotation`).
        - "indexed": what a user has after indexing at the nominal
          (wrong) geometry: the "uncentred" start refined point by point
          with kikuchipy's ``EBSD.refine_orientation`` (default method,
          SciPy Nelder-Mead, no trust region) against the map's own
          patterns (noisy if *dose* is set) at the *starting* detector.
          The geometry error is then absorbed into the orientations,
          which share a common rotation much larger than
          ``orientation_error / sqrt(n)``. With "variants" or "stripes",
          each point starts in a random variant (recorded in
          ``start_xmap.prop["variant"]``) before that refinement, as an
          indexer that cannot tell the variants apart leaves it; with 1
          deg of *orientation_error* and a geometry 2 % off, a 13 x 13
          stripe map of 120 px starts a median 1.9 deg from the nearest
          variant, a tenth of it beyond 8 deg. Costs about 1.3 s for 7 x 7
          patterns of 60 x 60 px and 7 s for 11 x 11 of 96 x 96 (2
          cores, after numba's first compilation); with *lazy* the
          patterns are simulated chunk by chunk during the refinement, in
          bounded memory.
    camera
        Make the patterns as a camera records and a user processes them
        (:class:`Camera`: background lobe, per-grain brightness, blur,
        Poisson counts in uint16, static and dynamic background removal):
        realistic data, on which the calibration's figures are measured.
        Then *dose*, *background* and *blur* must be left at their
        defaults. None (default): ``a * blur(S) + b`` plus Poisson noise
        (:func:`degrade_patterns`), the full-field model's own family, a
        best case.
    simulator
        The master pattern the *data* are simulated from, or its *kind*
        for :func:`master_pattern` ("emsoft", "ebsdsim", ...); default
        *master_pattern*. Another simulator of the same phase than the
        master pattern the map is calibrated with (``SyntheticMap.master_pattern``)
        is what a user has.

    Returns
    -------
    synthetic
        :class:`SyntheticMap`.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.synthetic import synthetic_map
    >>> sm = synthetic_map("Si", (3, 4), shape=(40, 40), seed=1)
    >>> sm.signal.data.shape
    (3, 4, 40, 40)
    >>> sm.xmap.shape, sm.detector.navigation_shape
    ((3, 4), (3, 4))

    Stripes of 90 and 180 deg domains, starting from one variant:

    >>> sm = synthetic_map("BaTiO3", (4, 4), "stripes", shape=(40, 40), seed=1)
    >>> sm.xmap.prop["variant"].reshape(4, 4)
    array([[0, 0, 2, 2],
           [0, 2, 2, 0],
           [2, 2, 0, 0],
           [2, 0, 0, 1]])
    >>> int(sm.start_xmap.prop["variant"].max())
    0
    """
    if isinstance(master_pattern, str):
        master_pattern = globals()["master_pattern"](master_pattern)
    check_master_pattern(master_pattern)
    if simulator is None:
        simulator = master_pattern
    elif isinstance(simulator, str):
        simulator = globals()["master_pattern"](master_pattern.phase.name, kind=simulator)
    check_master_pattern(simulator)
    if simulator.phase.name != master_pattern.phase.name:
        raise ValueError(
            f"simulator is of phase {simulator.phase.name!r}, master_pattern of "
            f"{master_pattern.phase.name!r}: both must be the same phase"
        )
    if camera is not None and (dose is not None or background or blur):
        raise ValueError(
            "Give either camera or dose/background/blur: a Camera sets its own "
            "noise, background and blur"
        )
    nav = tuple(int(n) for n in navigation_shape)
    if len(nav) != 2 or min(nav) < 1:
        raise ValueError(f"navigation_shape must be (rows, columns), not {navigation_shape}")
    if geometry is None:
        geometry = default_geometry(nav, shape)
    elif geometry.navigation_shape != nav:
        raise ValueError(
            f"geometry.navigation_shape {geometry.navigation_shape} differs from "
            f"navigation_shape {nav}"
        )
    if perturbation is None:
        perturbation = DEFAULT_PERTURBATION
    if start not in START_MODELS:
        raise ValueError(f"start must be one of {START_MODELS}, not {start!r}")
    rng = np.random.default_rng(seed)
    n = nav[0] * nav[1]
    rows, cols = np.indices(nav)

    prop = {}
    if orientations == "random":
        rot = _random_rotations(n, rng)
    elif orientations == "single":
        rot = perturb_rotations(_random_rotations(1, rng) * Rotation.identity(n), scatter, rng)
    elif orientations == "grains":
        grain = _grains(nav, rng).ravel()
        rot = perturb_rotations(_random_rotations(grain.max() + 1, rng)[grain], scatter, rng)
        prop["grain"] = grain
    elif orientations in ("variants", "stripes"):
        cycle = np.arange(6) if orientations == "variants" else np.array(STRIPE_VARIANTS)
        variant = cycle[_domains(nav, cycle.size).ravel()]
        parent = _random_rotations(1, rng)
        rot = variant_operators()[variant] * parent
        rot = perturb_rotations(rot, scatter, rng)
        prop["variant"] = variant
    else:
        raise ValueError(
            "orientations must be 'single', 'random', 'grains', 'variants' or 'stripes', "
            f"not {orientations!r}"
        )
    # "indexed" refines the "uncentred" start: same draws for all models
    start_rot = perturb_rotations(rot, orientation_error, rng, centred=start == "centred")
    start_prop = prop
    if orientations in ("variants", "stripes") and start == "indexed":
        # An indexer cannot tell the variants apart: each point comes in a
        # random one (a generator of its own, so the truth, the patterns and
        # the other start models keep their draws)
        drawn = np.random.default_rng([seed, 25]).integers(6, size=n)
        ops = variant_operators()
        start_rot = ops[drawn] * ~ops[variant] * start_rot
        start_prop = {"variant": drawn}
    elif orientations == "stripes":
        # The variant operator removed from each start: the parent's variant
        # with the point's own scatter and start error
        start_rot = ~variant_operators()[variant] * start_rot
        start_prop = {"variant": np.zeros_like(variant)}
    noise_seed = int(rng.integers(2**63))

    mp_phase = master_pattern.phase.deepcopy()
    dy, dx = geometry.step_sizes
    xmap = _crystal_map(rot, nav, (dy, dx), mp_phase, prop)
    start_xmap = _crystal_map(start_rot, nav, (dy, dx), mp_phase, start_prop)
    start_geometry = geometry.updated(perturbation)
    detector = geometry.detector()
    start_detector = start_geometry.detector()
    if len(detector.navigation_shape) == 1:  # One-row maps keep 2D PCs
        detector.pc = detector.pc.reshape(nav + (3,))
        start_detector.pc = start_detector.pc.reshape(nav + (3,))

    if camera is not None:
        degrade = dict(camera=camera, seed=noise_seed)
        # One brightness per grain (or domain, or point of a random map)
        label = prop.get("grain", prop.get("variant", np.arange(n)))
        if orientations == "single":
            label = np.zeros(n, dtype=int)
        draws = np.random.default_rng([noise_seed, 1]).uniform(-1, 1, int(label.max()) + 1)
        brightness = 1 + camera.brightness * draws[label]
    else:
        degrade = dict(dose=dose, background=background, blur=blur, seed=noise_seed)
        brightness = np.ones(n)
    data = _simulate_map(
        simulator,
        rot.data.reshape(nav + (4,)),
        detector.pc,
        geometry,
        energy,
        degrade,
        brightness,
    )
    axes = [
        {"name": "y", "size": nav[0], "scale": dy, "units": "um"},
        {"name": "x", "size": nav[1], "scale": dx, "units": "um"},
        {"name": "dy", "size": geometry.shape[0], "scale": 1, "units": "px"},
        {"name": "dx", "size": geometry.shape[1], "scale": 1, "units": "px"},
    ]
    if lazy:
        signal = LazyEBSD(data, axes=axes)
    else:
        signal = EBSD(data.compute(scheduler="threads"), axes=axes)
    if camera is not None:
        camera.process(signal)
    if start == "indexed":
        start_rot = _refine_orientations(
            signal, start_xmap, start_detector, master_pattern, energy
        )
        start_xmap = _crystal_map(start_rot, nav, (dy, dx), mp_phase, start_prop)
    signal.detector = start_detector.deepcopy()
    signal.xmap = start_xmap.deepcopy()
    signal.metadata.General.title = f"synthetic {master_pattern.phase.name} map"
    return SyntheticMap(
        signal=signal,
        geometry=geometry,
        detector=detector,
        xmap=xmap,
        start_geometry=start_geometry,
        start_detector=start_detector,
        start_xmap=start_xmap,
        master_pattern=master_pattern,
        energy=float(energy),
        start=start,
        simulator=simulator,
        camera=camera,
    )


def _refine_orientations(signal, xmap, detector, master_pattern, energy) -> Rotation:
    # kikuchipy's orientation refinement at fixed (per-point) PCs, as a
    # user would run it after indexing at the nominal geometry: default
    # method (SciPy Nelder-Mead) and no trust region, because with a trust
    # region SciPy builds the first simplex from 5 % of each start value,
    # clipped to the bounds, and stalls on orientations with a small Euler
    # angle (Phi near 2 deg). It builds a dask graph over the signal's
    # chunks, so a lazy signal is simulated chunk by chunk
    with quiet():
        refined = signal.refine_orientation(xmap, detector, master_pattern, energy)
    return refined.rotations.flatten()


#: Map points per grain of ``orientations="grains"`` (on average).
GRAIN_POINTS = 16


def _grains(nav: tuple[int, int], rng) -> np.ndarray:
    # Voronoi cells of random centres: grains larger than a step, as in a
    # real polycrystal map, so that neighbours share an orientation
    n = max(2, nav[0] * nav[1] // GRAIN_POINTS)
    centres = rng.uniform([0, 0], nav, size=(n, 2))
    points = np.indices(nav).reshape(2, -1).T + 0.5
    d = ((points[:, None, :] - centres[None]) ** 2).sum(axis=-1)
    return d.argmin(axis=1).reshape(nav)


def _domains(nav: tuple[int, int], n: int = 6) -> np.ndarray:
    # Diagonal stripes, as ferroelectric domain walls often run; all n
    # domains appear once the map has n or more diagonals
    rows, cols = np.indices(nav)
    n_diag = nav[0] + nav[1] - 1
    return ((rows + cols) * n // max(n_diag, 1)) % n


def _crystal_map(rot, nav, steps, mp_phase, prop) -> CrystalMap:
    dy, dx = steps
    rows, cols = np.indices(nav)
    return CrystalMap(
        rotations=rot.flatten(),
        x=(cols * dx).ravel().astype(float),
        y=(rows * dy).ravel().astype(float),
        phase_list=PhaseList(mp_phase),
        prop={k: np.asarray(v).ravel() for k, v in prop.items()},
        scan_unit="um",
    )


def _simulate_map(master_pattern, quats, pcs, geometry, energy, degrade, brightness) -> da.Array:
    nav = quats.shape[:2]
    sig = tuple(geometry.shape)
    # Rows of patterns per chunk: about 32 MiB of float32 output each
    rows_per_chunk = max(1, int(32 * 2**20 // (4 * nav[1] * sig[0] * sig[1])))
    chunks = (min(rows_per_chunk, nav[0]), nav[1])
    q = da.from_array(quats, chunks=chunks + (4,))
    p = da.from_array(pcs, chunks=chunks + (3,))
    b = da.from_array(brightness.reshape(nav + (1,)), chunks=chunks + (1,))
    camera = degrade.get("camera")
    return da.map_blocks(
        _simulate_block,
        q,
        p,
        b,
        master_pattern=master_pattern,
        template=geometry.detector(points=[[0, 0]]),
        energy=energy,
        degrade=degrade,
        nav_cols=nav[1],
        dtype=np.float32 if camera is None else np.uint16,
        chunks=q.chunks[:2] + ((sig[0],), (sig[1],)),
        drop_axis=2,
        new_axis=[2, 3],
    )


def _simulate_block(q, p, b, master_pattern, template, energy, degrade, nav_cols, block_info=None):
    shape = q.shape[:2]
    det = copy_detector(template, pc=p.reshape(-1, 3))
    patterns = simulate_patterns(master_pattern, Rotation(q.reshape(-1, 4)), det, energy)
    # Flat map indices so that noise does not depend on the chunking
    (r0, _), (c0, _) = block_info[0]["array-location"][:2]
    rows, cols = np.indices(shape)
    flat = ((rows + r0) * nav_cols + cols + c0).ravel()
    degrade = dict(degrade)
    camera = degrade.pop("camera", None)
    if camera is None:
        out = degrade_patterns(patterns, index=flat, **degrade)
    else:
        out = camera_counts(patterns, p.reshape(-1, 3), camera, b.ravel(), degrade["seed"], flat)
    return out.reshape(shape + patterns.shape[1:])


def degrade_patterns(
    patterns: np.ndarray,
    dose: float | None = None,
    background: float = 0.0,
    blur: float = 0.0,
    seed: int = 0,
    index: np.ndarray | None = None,
) -> np.ndarray:
    """Return patterns degraded as on a real detector.

    Parameters
    ----------
    patterns
        Noise-free patterns (n, rows, columns), non-negative intensities.
    dose
        Mean counts per pixel for Poisson shot noise, or ``None``.
    background
        Relative amplitude of a smooth Gaussian background (0 for none).
    blur
        Gaussian blur standard deviation in pixels (0 for none).
    seed
        Seed; pattern *k* draws its noise from ``(seed, index[k])``.
    index
        Map index of each pattern (default ``arange(n)``), so that a
        pattern's noise does not depend on which chunk it was in.

    Returns
    -------
    degraded
        float32 array of the same shape; unchanged patterns if all
        degradations are off.
    """
    out = np.asarray(patterns, dtype=np.float32).copy()
    n, nr, nc = out.shape
    if index is None:
        index = np.arange(n)
    if background:
        y, x = np.mgrid[0:nr, 0:nc]
        g = np.exp(-(((x - 0.45 * nc) / (0.6 * nc)) ** 2 + ((y - 0.35 * nr) / (0.6 * nr)) ** 2))
        out *= (1 + background * g).astype(np.float32)
    if blur:
        out = ndimage.gaussian_filter(out, sigma=(0, blur, blur)).astype(np.float32)
    if dose is not None:
        for k in range(n):
            rng = np.random.default_rng([seed, int(index[k])])
            mean = max(float(out[k].mean()), 1e-12)
            lam = np.clip(out[k], 0, None) * (dose / mean)
            out[k] = rng.poisson(lam).astype(np.float32)
    return out


@dataclass(frozen=True)
class Camera:
    """How a camera records patterns and a user processes them.

    Patterns made by :func:`degrade_patterns` (``a * blur(S) + b`` plus
    shot noise) are in the full-field model's own family; patterns from a
    microscope are not. A :class:`Camera` makes them as a microscope and a
    user do (:func:`camera_counts`, then :meth:`process`):

    1. expected counts ``dose * b_i * B(x, y) * (1 + contrast * K)``, K
       the clean pattern standardised, B a smooth background lobe peaking
       below the pattern centre (corners about 0.3 of the peak), b_i a
       brightness per grain (``1 +- brightness``);
    2. the phosphor's blur (*blur* px) of the expected counts, then
       Poisson noise, stored as uint16;
    3. kikuchipy's static background removal (dividing by the map's mean
       pattern, which on a map of few grains still holds bands: a faint
       inverted ghost common to every pattern) and dynamic background
       removal (dividing by a Gaussian-blurred copy), each stretching the
       result to the full uint16 range.

    Attributes
    ----------
    dose
        Mean counts per pixel (30 for kikuchipy's real Ni patterns).
    contrast
        Kikuchi contrast: relative amplitude of the standardised pattern
        on the background.
    brightness
        Relative spread of the brightness between grains.
    blur
        Standard deviation (px) of the phosphor's Gaussian blur.
    static, dynamic
        Whether the user removes the static and the dynamic background.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.synthetic import Camera, synthetic_map
    >>> sm = synthetic_map("Si", (3, 3), shape=(40, 40), camera=Camera(dose=30))
    >>> sm.signal.data.dtype.name
    'uint16'
    """

    dose: float = 150.0
    contrast: float = 0.1
    brightness: float = 0.1
    blur: float = 0.6
    static: bool = True
    dynamic: bool = True

    def process(self, signal: EBSD) -> None:
        """Remove the static and dynamic backgrounds of a raw map in place,
        as a user does with kikuchipy (lazy signals stay lazy)."""
        if self.static:
            mean = signal.data.mean(axis=(0, 1))
            if isinstance(mean, da.Array):
                mean = mean.compute()
            static_bg = np.round(mean).astype(signal.data.dtype)
            signal.remove_static_background("divide", static_bg=static_bg, show_progressbar=False)
            # Kept with the map, as kikuchipy's readers keep the one a
            # microscope records
            signal.static_background = static_bg
        if self.dynamic:
            signal.remove_dynamic_background("divide", show_progressbar=False)


#: Moderate noise: 150 counts per pixel.
MODERATE = Camera(dose=150.0)
#: The noise of kikuchipy's real Ni patterns: 30 counts per pixel.
REAL_NI = Camera(dose=30.0)


def camera_counts(
    patterns: np.ndarray,
    pcs: np.ndarray,
    camera: Camera,
    brightness: np.ndarray | None = None,
    seed: int = 0,
    index: np.ndarray | None = None,
) -> np.ndarray:
    """Return the raw counts a camera records for clean patterns.

    Steps 1 and 2 of :class:`Camera`: a background lobe at each pattern's
    PC, the Kikuchi pattern as a small modulation of it, the phosphor's
    blur, then Poisson noise.

    Parameters
    ----------
    patterns
        Clean simulated patterns (n, rows, columns).
    pcs
        Bruker PC of each pattern (n, 3): the lobe peaks below it and
        widens with pcz.
    camera
        The :class:`Camera`.
    brightness
        Relative brightness b_i of each pattern (n,), default 1.
    seed
        Seed; pattern *k* draws its noise from ``(seed, index[k])``.
    index
        Map index of each pattern (default ``arange(n)``).

    Returns
    -------
    counts
        uint16 array of the shape of *patterns*.
    """
    p = np.asarray(patterns, dtype=np.float64)
    n, nr, nc = p.shape
    pcs = np.asarray(pcs, dtype=float).reshape(n, 3)
    if index is None:
        index = np.arange(n)
    if brightness is None:
        brightness = np.ones(n)
    flat = p.reshape(n, -1)
    k = (flat - flat.mean(axis=1, keepdims=True)) / np.maximum(
        flat.std(axis=1, keepdims=True), 1e-12
    )
    y, x = np.mgrid[0:nr, 0:nc] + 0.5
    out = np.empty(p.shape, dtype=np.uint16)
    for i in range(n):
        # The backscatter lobe: peak a fifth of the height below the PC,
        # width growing with the detector distance
        x0, y0, width = pcs[i, 0] * nc, (pcs[i, 1] + 0.2) * nr, pcs[i, 2] * nc
        lobe = np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * (0.8 * width) ** 2))
        lobe /= lobe.mean()
        expected = (
            camera.dose * brightness[i] * lobe * (1 + camera.contrast * k[i].reshape(nr, nc))
        )
        expected = np.clip(expected, 0, None)
        if camera.blur:
            expected = ndimage.gaussian_filter(expected, camera.blur)
        rng = np.random.default_rng([seed, int(index[i])])
        out[i] = np.minimum(rng.poisson(expected), np.iinfo(np.uint16).max)
    return out


@functools.lru_cache(maxsize=4)
def _dynamical(key: str, kind: str = "dynamical") -> EBSDMasterPattern:
    name, simulator = _DYNAMICAL_FILES[kind][key]
    with resources.as_file(_DATA / name) as path:
        npz = np.load(path)
        # BaTiO3 is stored as float16 to keep its 801 x 801 grid small
        data = npz["data"].astype(np.float32)
    n = data.shape[-1]
    axes = [
        {"size": 2, "name": "hemisphere", "scale": 1, "offset": 0, "units": ""},
        {"size": n, "name": "height", "scale": 1, "offset": -(n // 2), "units": "px"},
        {"size": n, "name": "width", "scale": 1, "offset": -(n // 2), "units": "px"},
    ]
    mp = EBSDMasterPattern(
        data, axes=axes, projection="lambert", hemisphere="both", phase=phase(key)
    )
    mp.metadata.General.title = f"{key} dynamical ({simulator})"
    return mp


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
