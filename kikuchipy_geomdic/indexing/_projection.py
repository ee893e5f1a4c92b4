"""What the orientation kernel projects from and what it projects: the
master pattern's hemispheres as arrays, the detector as arrays, and
patterns with their analytic derivatives.

The projection is kikuchipy's (same Lambert lookup, same bilinear
interpolation, same per-hemisphere rescaling), so the optimum the solver
reaches is kikuchipy's ``refine_orientation`` optimum. The public names
are presented by :mod:`~kikuchipy_geomdic.indexing.orientation`.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.pattern import rescale_intensity
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation
from scipy import ndimage

from kikuchipy_geomdic.indexing._lambert import (
    _SQRT_PI_HALF,
    _project_stack,
    _project_stack_derivatives,
)
from kikuchipy_geomdic.patterns.simulation import check_master_pattern

# --------------------------------------------------------------------- #
# Master pattern
# --------------------------------------------------------------------- #


@dataclass(frozen=True)
class MasterPatternArrays:
    """The two hemispheres the kernel projects from.

    Attributes
    ----------
    upper, lower
        Square Lambert hemispheres, float32, each rescaled to [-1, 1] as
        kikuchipy's refinement rescales them (when not float32 already).
    smoothing
        Standard deviation (degrees) of the Gaussian they were smoothed
        with; 0 for the master pattern itself.
    stretch
        The crystal's c axis (its z) over the master pattern's: patterns
        projected from these arrays are those of a lattice stretched along
        it (1: the master pattern's own).
    """

    upper: np.ndarray
    lower: np.ndarray
    smoothing: float = 0.0
    stretch: float = 1.0
    _smoothed: dict = field(default_factory=dict, repr=False, compare=False)

    @cached_property
    def hemispheres(self) -> np.ndarray:
        """Both hemispheres in one array (2 npx, npx), upper then lower:
        the Gauss-Newton kernel looks either up without a branch."""
        return np.ascontiguousarray(np.concatenate([self.upper, self.lower]), dtype=np.float32)

    @property
    def scale(self) -> float:
        """kikuchipy's factor from the Lambert square to pixels."""
        return (self.upper.shape[1] - 1) / 2

    def smoothed(self, sigma: float) -> MasterPatternArrays:
        """Return the hemispheres smoothed by a Gaussian of *sigma* degrees
        (at the Lambert centre; remembered, as every chunk asks again)."""
        if sigma <= 0:
            return self
        if sigma not in self._smoothed:
            px = sigma / math.degrees(_SQRT_PI_HALF / self.scale)
            up = _smooth_across_equator(self.upper, self.lower, px)
            lo = _smooth_across_equator(self.lower, self.upper, px)
            self._smoothed[sigma] = MasterPatternArrays(
                up.astype(np.float32), lo.astype(np.float32), sigma, self.stretch
            )
        return self._smoothed[sigma]


def _smooth_across_equator(hemisphere, other, sigma):
    """Gaussian smoothing of one Lambert hemisphere that continues into the
    other one across the square's edge (the equator).

    Past an edge of the square the sphere continues in the other
    hemisphere, mirrored across that edge (the square Lambert projection
    of a direction just below the equator lands just inside the other
    square's same edge). Smoothing with any padding of the hemisphere's
    own pixels puts a false seam there, and patterns that look across the
    equator (a BaTiO3 90 deg domain, c axis in the sample plane) then
    pulled Gauss-Newton degrees away from a start 0.4 deg off.
    """
    w = min(int(math.ceil(4 * sigma)), hemisphere.shape[0] - 1)
    big = np.pad(np.asarray(hemisphere, np.float64), w, mode="reflect")
    ring = np.pad(np.asarray(other, np.float64), w, mode="reflect")
    inner = (slice(w, w + hemisphere.shape[0]), slice(w, w + hemisphere.shape[1]))
    ring[inner] = big[inner]
    return ndimage.gaussian_filter(ring, sigma, mode="nearest")[inner]


@dataclass(frozen=True)
class PhaseArrays:
    """The hemispheres of several phases and the phase of each pattern: a
    stack of patterns of several phases projects (and differentiates) each
    pattern from its own phase's :class:`MasterPatternArrays`.

    Attributes
    ----------
    phases
        A :class:`MasterPatternArrays` per phase.
    labels
        Index into *phases* of each pattern (N,), int.
    """

    phases: tuple
    labels: np.ndarray

    def groups(self, n: int):
        """Yield each phase's pattern indices and arrays, for a stack of *n*."""
        if n != self.labels.size:
            raise ValueError(f"{n} patterns for the phase labels of {self.labels.size}")
        for k, arrays in enumerate(self.phases):
            rows = np.flatnonzero(self.labels == k)
            if rows.size:
                yield rows, arrays


def master_pattern_arrays(
    master_pattern: EBSDMasterPattern | MasterPatternArrays, energy: float
) -> MasterPatternArrays:
    """Return the hemispheres of *master_pattern* at *energy* as kikuchipy's
    refinement projects them.

    Parameters
    ----------
    master_pattern
        Lambert :class:`~kikuchipy.signals.EBSDMasterPattern`, one or both
        hemispheres (or its arrays, returned as they are).
    energy
        Beam energy in kV (selects the slice of a multi-energy pattern).

    Returns
    -------
    arrays
        :class:`MasterPatternArrays`.

    Examples
    --------
    >>> from kikuchipy_geomdic.validation import master_patterns
    >>> from kikuchipy_geomdic.indexing.orientation import master_pattern_arrays
    >>> mpa = master_pattern_arrays(master_patterns.master_pattern("Si"), 20)
    >>> mpa.upper.shape, mpa.upper.dtype.name, mpa.scale
    ((201, 201), 'float32', 100.0)
    """
    if isinstance(master_pattern, (MasterPatternArrays, PhaseArrays)):
        return master_pattern
    check_master_pattern(master_pattern)
    if master_pattern.data.shape[-1] != master_pattern.data.shape[-2]:
        raise ValueError(
            f"The master pattern's Lambert hemispheres must be square, not "
            f"{master_pattern.data.shape[-2:]}"
        )
    # The one private kikuchipy call: the slice selection by energy and the
    # hemisphere layout (kikuchipy is pinned to 0.13 in pyproject.toml)
    upper, lower = master_pattern._get_master_pattern_arrays_from_energy(energy=energy)
    upper, lower = np.asarray(upper), np.asarray(lower)
    if upper.dtype != np.float32:
        # As kikuchipy's refinement: each hemisphere rescaled on its own
        upper = rescale_intensity(upper, dtype_out=np.float32)
        lower = rescale_intensity(lower, dtype_out=np.float32)
    return MasterPatternArrays(
        np.ascontiguousarray(upper, dtype=np.float32),
        np.ascontiguousarray(lower, dtype=np.float32),
    )


def detector_pcs(detector: EBSDDetector, n: int) -> np.ndarray:
    """Return the detector's Bruker PCs as (n, 3), one repeated or n given.

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.indexing.orientation import detector_pcs
    >>> detector_pcs(EBSDDetector(pc=[0.5, 0.3, 0.6]), 2).tolist()
    [[0.5, 0.3, 0.6], [0.5, 0.3, 0.6]]
    """
    pcs = np.ascontiguousarray(detector.pc.reshape(-1, 3), dtype=np.float64)
    if pcs.shape[0] == 1:
        return np.repeat(pcs, n, axis=0)
    if pcs.shape[0] != n:
        raise ValueError(f"The detector has {pcs.shape[0]} PCs for {n} patterns; give one or {n}")
    return pcs


def detector_matrix(detector: EBSDDetector) -> np.ndarray:
    """Return the detector-to-sample matrix (3, 3) of *detector*'s angles,
    as kikuchipy projects with it.

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.indexing.orientation import detector_matrix
    >>> detector_matrix(EBSDDetector(sample_tilt=70)).shape
    (3, 3)
    """
    return np.ascontiguousarray((~detector.sample_to_detector).to_matrix().reshape(3, 3))


def project_patterns(
    rotations: Rotation,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern | MasterPatternArrays,
    energy: float = 20.0,
) -> np.ndarray:
    """Return patterns projected by this module's kernel.

    The same intensities as kikuchipy's ``get_patterns`` (float32
    rounding aside) before any rescaling of the output; used to check the
    kernel against kikuchipy and to score orientations.

    Parameters
    ----------
    rotations
        Orientations (N,).
    detector
        Detector with one PC or N PCs.
    master_pattern, energy
        Lambert master pattern (or its arrays) and beam energy in kV.

    Returns
    -------
    patterns
        Array (N, rows, columns), float64.

    Examples
    --------
    A noise-free synthetic map's patterns, again at its true orientations
    and PCs:

    >>> import numpy as np
    >>> from kikuchipy_geomdic.indexing.orientation import project_patterns
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(30, 30), seed=0)
    >>> sim = project_patterns(sm.xmap.rotations, sm.detector, sm.master_pattern)
    >>> sim.shape, sim.dtype.name
    ((4, 30, 30), 'float64')
    >>> e = sm.signal.data.reshape(4, -1)
    >>> bool(min(np.corrcoef(a.ravel(), b)[0, 1] for a, b in zip(sim, e)) > 0.9999)
    True
    """
    q = np.ascontiguousarray(Rotation(rotations).flatten().data, dtype=np.float64)
    arrays = master_pattern_arrays(master_pattern, energy)
    return project_arrays(
        q, detector_pcs(detector, q.shape[0]), detector_matrix(detector), arrays, detector.shape
    )


def project_derivatives(
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return projected patterns and their analytic derivatives by a
    rotation of the crystal and by the pattern's PC.

    One pass of the kernel: the gradient of the bilinear master-pattern
    interpolant by the crystal direction, chained through the Lambert
    projection, gives both the rotation derivative (``d x grad``) and the
    PC derivative (``grad`` along how the pixel's direction moves with the
    PC). Both are the exact derivatives of the model kikuchipy evaluates
    (almost everywhere: bilinear interpolation has kinks at the master
    pattern's cell edges), so a geometry column reduced against the
    rotation columns is free of finite-difference error.

    Parameters
    ----------
    quaternions
        Orientations (N, 4).
    pcs
        Bruker PCs (N, 3).
    om
        :func:`detector_matrix`.
    arrays
        :func:`master_pattern_arrays`.
    shape
        Pattern shape (rows, columns).

    Returns
    -------
    patterns
        (N, P), P = rows * columns, float64.
    rotation
        (N, P, 3): intensity per radian of the sample-frame rotation ``T``
        of ``g -> g * T`` (orix's right factor, the refinement's update).
    pc
        (N, P, 3): intensity per unit of the pattern's PCx, PCy, PCz
        (Bruker).

    Examples
    --------
    The PC derivative against a finite difference:

    >>> import numpy as np
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.indexing import orientation as ori
    >>> from kikuchipy_geomdic.validation import master_patterns
    >>> arrays = ori.master_pattern_arrays(master_patterns.master_pattern("Si"), 20)
    >>> pc = np.array([[0.5, 0.3, 0.6]])
    >>> q = Rotation.from_euler(np.deg2rad([[10, 20, 30]])).data
    >>> om = ori.detector_matrix(EBSDDetector(sample_tilt=70))
    >>> s, j_rot, j_pc = ori.project_derivatives(q, pc, om, arrays, (40, 40))
    >>> h = [[1e-7, 0, 0]]
    >>> fd = (ori.project_arrays(q, pc + h, om, arrays, (40, 40)).ravel() - s[0]) / 1e-7
    >>> bool(np.corrcoef(fd, j_pc[0, :, 0])[0, 1] > 0.9999)
    True
    """
    return _on_stack(_project_stack_derivatives, quaternions, pcs, om, arrays, shape)


def project_arrays(
    quaternions: np.ndarray,
    pcs: np.ndarray,
    om: np.ndarray,
    arrays: MasterPatternArrays,
    shape: tuple[int, int],
) -> np.ndarray:
    """:func:`project_patterns` on plain arrays: quaternions (N, 4), Bruker
    PCs (N, 3), the :func:`detector_matrix` and the pattern shape."""
    out = _on_stack(_project_stack, quaternions, pcs, om, arrays, shape)
    return out.reshape((out.shape[0],) + tuple(shape))


def _on_stack(kernel, quaternions, pcs, om, arrays, shape):
    """Run a stack *kernel* of :mod:`~kikuchipy_geomdic.indexing._lambert` on
    plain arrays: quaternions (N, 4), PCs (N, 3), the detector matrix, the
    master pattern's arrays and the pattern shape."""
    q = np.ascontiguousarray(quaternions, dtype=np.float64).reshape(-1, 4)
    pcs = np.ascontiguousarray(pcs, dtype=np.float64).reshape(-1, 3)
    om = np.ascontiguousarray(om, dtype=np.float64)
    if isinstance(arrays, PhaseArrays):
        return _by_phase(kernel, q, pcs, om, arrays, shape)
    return kernel(
        q,
        pcs,
        int(shape[0]),
        int(shape[1]),
        om,
        arrays.upper,
        arrays.lower,
        float(arrays.scale),
        float(arrays.stretch),
    )


def _by_phase(kernel, q, pcs, om, arrays: PhaseArrays, shape):
    """:func:`_on_stack` of a stack of several phases: each phase's
    patterns from its own arrays, put back in the stack's order."""
    pcs = np.repeat(pcs, len(q), axis=0) if len(pcs) == 1 and len(q) > 1 else pcs
    out = None
    for rows, a in arrays.groups(len(q)):
        part = _on_stack(kernel, q[rows], pcs[rows], om, a, shape)
        parts = part if isinstance(part, tuple) else (part,)
        if out is None:
            out = tuple(np.empty((len(q),) + p.shape[1:], dtype=p.dtype) for p in parts)
        for o, p in zip(out, parts):
            o[rows] = p
    return out if isinstance(part, tuple) else out[0]
