"""Realistic two-phase maps: grains of two phases, a vendor's phase labels
with a fraction of them wrong, and the truth to score a calibration and a
per-point phase decision against.

:func:`two_phase_map` builds a Voronoi polycrystal whose grains are of
phase A or phase B, records it as
:class:`~kikuchipy_geomdic.validation.camera.Camera` does (background lobe,
per-grain brightness, phosphor blur, shot noise, kikuchipy's static and
dynamic background removal) from the *other* simulator's master patterns
(de-ebsd's, while the calibration gets ebsdsim's), and starts it as a
vendor's map comes: a phase label per point, a fraction of them the other
phase, and orientations indexed in the labelled phase at the nominal
(wrong) geometry.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.indexing.reindex import quiet
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation._map_patterns import _axes, _brightness, _simulate_map
from kikuchipy_geomdic.validation.camera import MODERATE, Camera
from kikuchipy_geomdic.validation.orientations import (
    _random_rotations,
    _true_orientations,
    perturb_rotations,
)

__all__ = ["PAIRS", "TwoPhaseMap", "two_phase_map"]

#: The benchmark's phase pairs: an easy one (bcc against fcc iron, bands
#: of different lattices) and a hard one (bcc ferrite against bct
#: martensite with c/a = 1.025: the same bands, 2.5 % apart along c).
PAIRS = {
    "ferrite+austenite": ("Fe_bcc", "Fe_fcc"),
    "ferrite+martensite": ("Fe_bcc", "Fe_bct"),
}


@dataclass(frozen=True)
class TwoPhaseMap:
    """A two-phase EBSD map with its truth and a vendor's start.

    Attributes
    ----------
    signal
        Processed :class:`~kikuchipy.signals.EBSD` map (navigation axes
        in um) carrying the start detector and start crystal map, as a
        file from a microscope would.
    geometry, detector, xmap
        The truth: geometry, detector with the PC of every point, and the
        crystal map with both phases (ids 0 and 1, in *phases* order),
        each point in its true phase and orientation; property ``grain``.
    start_geometry, start_detector, start_xmap
        The start: the perturbed geometry and the vendor's map, each point
        labelled with a phase (the true one, or the other where
        ``mislabelled``) and its orientation indexed in that phase at the
        start geometry.
    master_patterns
        ``{phase name: master pattern}`` to calibrate and reindex with.
    simulators
        ``{phase name: master pattern}`` the patterns were simulated from.
    mislabelled
        Boolean array of the map's shape: True where the start's label is
        the other phase.
    energy
        Beam energy in kV.
    camera
        The camera that recorded the patterns.
    """

    signal: EBSD
    geometry: MapGeometry
    detector: EBSDDetector
    xmap: CrystalMap
    start_geometry: MapGeometry
    start_detector: EBSDDetector
    start_xmap: CrystalMap
    master_patterns: dict[str, EBSDMasterPattern]
    simulators: dict[str, EBSDMasterPattern]
    mislabelled: np.ndarray
    energy: float
    camera: Camera

    @property
    def phase_names(self) -> tuple[str, str]:
        """The two phases' names, in id order (0, 1)."""
        return tuple(self.xmap.phases[i].name for i in (0, 1))

    @property
    def true_phase(self) -> np.ndarray:
        """The true phase id of each point, of the map's shape."""
        return self.xmap.phase_id.reshape(self.geometry.navigation_shape)

    @property
    def start_phase(self) -> np.ndarray:
        """The start's (vendor's) phase id of each point, of the map's shape."""
        return self.start_xmap.phase_id.reshape(self.geometry.navigation_shape)


def two_phase_map(
    phases: tuple[str, str] = PAIRS["ferrite+austenite"],
    navigation_shape: tuple[int, int] = (15, 15),
    shape: tuple[int, int] = (80, 80),
    fraction: float = 0.5,
    mislabel: float = 0.05,
    wrong_orientation: str = "nearest",
    camera: Camera = MODERATE,
    perturbation: Mapping[str, float] | None = None,
    orientation_error: float = 1.0,
    scatter: float = 0.05,
    data: str = "de-ebsd",
    calibrate: str = "dynamical",
    geometry: MapGeometry | None = None,
    energy: float = 20.0,
    seed: int = 0,
) -> TwoPhaseMap:
    """Return a realistic two-phase map with its truth and a vendor's start.

    Parameters
    ----------
    phases
        Names of phase A and phase B for
        :func:`~kikuchipy_geomdic.validation.master_patterns.phase`, e.g. a
        value of :data:`PAIRS`. They get phase ids 0 and 1.
    navigation_shape
        Map shape (rows, columns).
    shape
        Detector shape, used when *geometry* is not given.
    fraction
        Probability of a grain to be of phase B. Both phases always get at
        least one grain.
    mislabel
        Fraction of points whose start label is the other phase (rounded
        to a whole number of points, drawn uniformly over the map).
    wrong_orientation
        What the vendor's index of a mislabelled point gives before its
        refinement: "nearest" (default), the true rotation read in the
        other phase's symmetry, scattered like every start, or "random", a
        random orientation. "nearest" is what a wrong-phase index of the
        hard pair gives (bcc and bct bands coincide but for the
        tetragonality) and the harder case for a phase decision in
        general: the wrong phase is then at its best fit near the truth,
        not at a random orientation a score rejects at once.
    camera
        How the patterns are recorded and processed.
    perturbation
        ``{parameter: change}`` from the true to the start geometry;
        default :data:`~kikuchipy_geomdic.validation.synthetic.DEFAULT_PERTURBATION`.
    orientation_error
        RMS angle (deg) of the random error of the orientations before
        the vendor's refinement (not centred).
    scatter
        RMS orientation scatter (deg) within a grain.
    data, calibrate
        Kinds of :func:`~kikuchipy_geomdic.validation.master_patterns.master_pattern`
        the patterns are simulated from ("de-ebsd") and that
        ``master_patterns`` holds for calibration ("dynamical":
        ebsdsim's): two simulators, as a user has.
    geometry
        True geometry; default
        :func:`~kikuchipy_geomdic.validation.synthetic.default_geometry`.
    energy
        Beam energy in kV.
    seed
        Seed of everything random: grains, phases, orientations, labels,
        noise.

    Returns
    -------
    two_phase
        :class:`TwoPhaseMap`.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation.multiphase import two_phase_map
    >>> tp = two_phase_map(navigation_shape=(4, 5), shape=(40, 40), mislabel=0.1, seed=2)
    >>> tp.phase_names, tp.signal.data.shape
    (('Fe_bcc', 'Fe_fcc'), (4, 5, 40, 40))
    >>> int(tp.mislabelled.sum()), bool((tp.start_phase != tp.true_phase).sum() == 2)
    (2, True)
    """
    if wrong_orientation not in ("nearest", "random"):
        raise ValueError(
            f"wrong_orientation must be 'nearest' or 'random', not {wrong_orientation!r}"
        )
    if not 0 <= mislabel <= 1 or not 0 < fraction < 1:
        raise ValueError("mislabel must be in [0, 1] and fraction in (0, 1)")
    nav = tuple(int(n) for n in navigation_shape)
    geometry = synthetic.default_geometry(nav, shape) if geometry is None else geometry
    if geometry.navigation_shape != nav:
        raise ValueError(f"geometry.navigation_shape differs from navigation_shape {nav}")
    names = tuple(master_patterns.phase(p).name for p in phases)
    if len(set(names)) != 2:
        raise ValueError(f"phases must name two different phases, not {phases!r}")
    mps = {n: master_patterns.master_pattern(n, kind=calibrate) for n in names}
    sims = {n: master_patterns.master_pattern(n, kind=data) for n in names}
    phase_list = PhaseList(phases=[mps[n].phase.deepcopy() for n in names], ids=[0, 1])

    rng = np.random.default_rng(seed)
    rot, prop = _true_orientations("grains", nav, scatter, rng)
    grain = prop["grain"]
    true_phase = _grain_phases(grain, fraction, rng)
    label, mislabelled = _labels(true_phase, mislabel, rng)
    start_rot = perturb_rotations(rot, orientation_error, rng, centred=False)
    if wrong_orientation == "random":
        start_rot[mislabelled] = _random_rotations(int(mislabelled.sum()), rng)
    noise_seed = int(rng.integers(2**63))

    steps = geometry.step_sizes
    xmap = _two_phase_crystal_map(rot, true_phase, nav, steps, phase_list, grain)
    start_geometry = geometry.updated(
        synthetic.DEFAULT_PERTURBATION if perturbation is None else perturbation
    )
    detector = synthetic._detector(geometry)
    start_detector = synthetic._detector(start_geometry)
    signal = _record(sims, names, rot, true_phase, grain, detector, geometry, energy, camera,
                     noise_seed)  # fmt: skip
    start_rot = _vendor_refinement(signal, start_rot, label, nav, steps, phase_list,
                                   start_detector, mps, names, energy)  # fmt: skip
    start_xmap = _two_phase_crystal_map(start_rot, label, nav, steps, phase_list, grain)
    signal.detector = start_detector.deepcopy()
    signal.xmap = start_xmap.deepcopy()
    signal.metadata.General.title = f"synthetic {names[0]} + {names[1]} map"
    return TwoPhaseMap(
        signal, geometry, detector, xmap,  # the truth
        start_geometry, start_detector, start_xmap,  # the start
        mps, sims, mislabelled.reshape(nav), float(energy), camera,
    )  # fmt: skip


def _grain_phases(grain: np.ndarray, fraction: float, rng) -> np.ndarray:
    """The true phase id (0 or 1) of each point, drawn per grain."""
    n = int(grain.max()) + 1
    of_grain = (rng.random(n) < fraction).astype(int)
    if of_grain.min() == of_grain.max():
        # A map of one phase measures no phase decision: flip one grain
        of_grain[0] = 1 - of_grain[0]
    return of_grain[grain]


def _labels(true_phase: np.ndarray, mislabel: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """The vendor's labels: the truth with a fraction of points swapped."""
    n = true_phase.size
    wrong = np.zeros(n, dtype=bool)
    wrong[rng.choice(n, size=int(round(mislabel * n)), replace=False)] = True
    return np.where(wrong, 1 - true_phase, true_phase), wrong


def _two_phase_crystal_map(rot, phase_id, nav, steps, phase_list, grain) -> CrystalMap:
    dy, dx = steps
    rows, cols = np.indices(nav)
    return CrystalMap(
        rotations=rot.flatten(),
        phase_id=np.asarray(phase_id).ravel(),
        x=(cols * dx).ravel().astype(float),
        y=(rows * dy).ravel().astype(float),
        phase_list=phase_list.deepcopy(),
        prop={"grain": np.asarray(grain).ravel()},
        scan_unit="um",
    )


def _record(sims, names, rot, true_phase, grain, detector, geometry, energy, camera, seed):
    """The camera's processed map: each point's counts from its phase's
    simulator, then the user's background removal over the whole map."""
    nav = geometry.navigation_shape
    brightness = _brightness(camera, seed, grain)
    quats = rot.data.reshape(nav + (4,))
    noise = dict(camera=camera, seed=seed)
    # Counts of every point from both simulators: the noise of a point
    # depends on its index and the seed only, so picking per point is
    # one recording of the map
    counts = [
        _simulate_map(sims[n], quats, detector.pc, geometry, energy, noise, brightness).compute(
            scheduler="threads"
        )
        for n in names
    ]
    is_b = true_phase.reshape(nav + (1, 1)) == 1
    data = np.where(is_b, counts[1], counts[0])
    signal = EBSD(data, axes=_axes(geometry))
    camera.process(signal)
    return signal


def _vendor_refinement(signal, start_rot, label, nav, steps, phase_list, detector, mps, names,
                       energy) -> Rotation:  # fmt: skip
    """The start orientations refined by kikuchipy in each point's labelled
    phase at the start detector, as a vendor's indexing leaves them."""
    out = start_rot.data.copy()
    xmap = _two_phase_crystal_map(start_rot, label, nav, steps, phase_list, np.zeros(label.size))
    for pid, name in enumerate(names):
        keep = label == pid
        if not keep.any():
            continue
        with quiet():
            refined = signal.refine_orientation(
                xmap, detector, mps[name], energy, navigation_mask=~keep.reshape(nav)
            )
        # kikuchipy returns the refined points alone, in row-major order
        out[keep] = refined.rotations.data.reshape(-1, 4)
    return Rotation(out)
