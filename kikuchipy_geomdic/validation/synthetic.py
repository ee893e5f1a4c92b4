"""Synthetic EBSD maps with a known geometry and known orientations.

Ground truth is this package's main instrument: a map simulated here comes
with its true geometry and orientations, a perturbed starting geometry and
starting orientations made by one of three start models (the paper's
centred scatter, an uncentred scatter, or orientations refined at the
wrong geometry as a user would have them after indexing; see
:func:`synthetic_map` and
:func:`~kikuchipy_geomdic.validation.orientations.common_rotation`), so that any
calibration can be scored.

The pieces live in their own modules: master patterns in
:mod:`~kikuchipy_geomdic.validation.master_patterns`, orientations and
starts in :mod:`~kikuchipy_geomdic.validation.orientations`, detector
noise in :mod:`~kikuchipy_geomdic.validation.camera`.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap, PhaseList

from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.patterns.simulation import check_master_pattern
from kikuchipy_geomdic.validation import master_patterns
from kikuchipy_geomdic.validation._map_patterns import _refine_orientations, _signal
from kikuchipy_geomdic.validation.camera import Camera
from kikuchipy_geomdic.validation.orientations import _start_orientations, _true_orientations

__all__ = [
    "START_MODELS",
    "default_geometry",
    "DEFAULT_PERTURBATION",
    "SyntheticMap",
    "synthetic_map",
    "MIN_PRIOR",
    "centred_prior",
]


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
        :class:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry` with reference
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
        The :class:`~kikuchipy_geomdic.validation.camera.Camera` that recorded them, or None for
        model-family patterns (:func:`~kikuchipy_geomdic.validation.camera.degrade_patterns`).
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
        Lambert master pattern, or a name for
        :func:`~kikuchipy_geomdic.validation.master_patterns.master_pattern`.
    navigation_shape
        Map shape (rows, columns).
    orientations
        "single" (one crystal, orientations scattered by *scatter*), "random"
        (uniformly random per point), "grains" (a polycrystal: Voronoi grains
        of :data:`~kikuchipy_geomdic.validation.orientations.GRAIN_POINTS`
        points on average, random orientations scattered by *scatter* within
        each, property ``grain``), "variants" (BaTiO3-like diagonal domains,
        each one of the six variants of
        :func:`~kikuchipy_geomdic.indexing.variants.variant_operators` applied
        to one parent orientation, scattered by *scatter*) or "stripes"
        (diagonal stripes of the variants
        :data:`~kikuchipy_geomdic.validation.orientations.STRIPE_VARIANTS` of
        one parent, 90 and 180 deg domains, scattered by *scatter*, and a
        start with the parent's variant everywhere: what an indexer that
        cannot tell the variants apart returns). ``xmap.prop["variant"]`` is
        the true variant index *k* of each point (its orientation is
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
        orientations (see :func:`~kikuchipy_geomdic.validation.orientations.perturb_rotations` and
        *start*).
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
          points (see :func:`~kikuchipy_geomdic.validation.orientations.common_rotation`).
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
        (:class:`~kikuchipy_geomdic.validation.camera.Camera`: background
        lobe, per-grain brightness, blur, Poisson counts in uint16, static and
        dynamic background removal): realistic data, on which the
        calibration's figures are measured. Then *dose*, *background* and
        *blur* must be left at their defaults. None (default):
        ``a * blur(S) + b`` plus Poisson noise
        (:func:`~kikuchipy_geomdic.validation.camera.degrade_patterns`), the
        full-field model's own family, a best case.
    simulator
        The master pattern the *data* are simulated from, or its *kind* for
        :func:`~kikuchipy_geomdic.validation.master_patterns.master_pattern`
        ("emsoft", "ebsdsim", ...); default *master_pattern*. Another
        simulator of the same phase than the master pattern the map is
        calibrated with (``SyntheticMap.master_pattern``) is what a user has.

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
    master_pattern, simulator = _master_patterns(master_pattern, simulator)
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
    if start not in START_MODELS:
        raise ValueError(f"start must be one of {START_MODELS}, not {start!r}")
    rng = np.random.default_rng(seed)
    rot, prop = _true_orientations(orientations, nav, scatter, rng)
    start_rot, start_prop = _start_orientations(
        rot, prop, orientations, start, orientation_error, rng, seed
    )
    noise_seed = int(rng.integers(2**63))

    mp_phase = master_pattern.phase.deepcopy()
    xmap = _crystal_map(rot, nav, geometry.step_sizes, mp_phase, prop)
    start_xmap = _crystal_map(start_rot, nav, geometry.step_sizes, mp_phase, start_prop)
    start_geometry = geometry.updated(
        DEFAULT_PERTURBATION if perturbation is None else perturbation
    )
    detector, start_detector = _detector(geometry), _detector(start_geometry)
    noise = dict(dose=dose, background=background, blur=blur, seed=noise_seed)
    if camera is not None:
        noise = dict(camera=camera, seed=noise_seed)
    labels = _labels(prop, orientations, rot.size)
    signal = _signal(simulator, rot, detector, geometry, energy, noise, labels, lazy)
    if start == "indexed":
        start_rot = _refine_orientations(
            signal, start_xmap, start_detector, master_pattern, energy
        )
        start_xmap = _crystal_map(start_rot, nav, geometry.step_sizes, mp_phase, start_prop)
    signal.detector = start_detector.deepcopy()
    signal.xmap = start_xmap.deepcopy()
    signal.metadata.General.title = f"synthetic {master_pattern.phase.name} map"
    return SyntheticMap(
        signal, geometry, detector, xmap,  # the truth
        start_geometry, start_detector, start_xmap,  # the start
        master_pattern, float(energy), start, simulator, camera,
    )  # fmt: skip


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


def _master_patterns(master_pattern, simulator):
    """The master pattern to calibrate with and the one to simulate from."""
    if isinstance(master_pattern, str):
        master_pattern = master_patterns.master_pattern(master_pattern)
    check_master_pattern(master_pattern)
    if simulator is None:
        simulator = master_pattern
    elif isinstance(simulator, str):
        simulator = master_patterns.master_pattern(master_pattern.phase.name, kind=simulator)
    check_master_pattern(simulator)
    if simulator.phase.name != master_pattern.phase.name:
        raise ValueError(
            f"simulator is of phase {simulator.phase.name!r}, master_pattern of "
            f"{master_pattern.phase.name!r}: both must be the same phase"
        )
    return master_pattern, simulator


def _detector(geometry: MapGeometry) -> EBSDDetector:
    detector = geometry.detector()
    if len(detector.navigation_shape) == 1:  # One-row maps keep 2D PCs
        detector.pc = detector.pc.reshape(geometry.navigation_shape + (3,))
    return detector


def _labels(prop, orientations, n) -> np.ndarray:
    # One brightness per grain (or domain, or point of a random map)
    if orientations == "single":
        return np.zeros(n, dtype=int)
    return prop.get("grain", prop.get("variant", np.arange(n)))
