"""One global geometry of a whole map (:class:`MapGeometry`) and detector
copies with some attributes changed.

Layer 1 (geometry): imports nothing of the package outside its own layer.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from kikuchipy.detectors import EBSDDetector

from kikuchipy_geomdic.geometry.parameters import _ANGLES, PARAMETERS, check_parameters
from kikuchipy_geomdic.geometry.projection import forward_map, pc_field

__all__ = ["MapGeometry", "copy_detector"]


def copy_detector(detector: EBSDDetector, **changes) -> EBSDDetector:
    """Return a new detector with the same attributes, some changed.

    Parameters
    ----------
    detector
        Detector to copy; not modified.
    **changes
        Keyword arguments of :class:`~kikuchipy.detectors.EBSDDetector`
        to replace (``pc`` in the Bruker convention).

    Returns
    -------
    new_detector
        A new :class:`~kikuchipy.detectors.EBSDDetector` (Bruker PCs);
        the PC array is a copy.

    Examples
    --------
    >>> from kikuchipy.detectors import EBSDDetector
    >>> from kikuchipy_geomdic.geometry import copy_detector
    >>> det = EBSDDetector((60, 60), binning=2, twist=0.3)
    >>> new = copy_detector(det, shape=(30, 30), binning=4)
    >>> new.shape, new.binning, new.twist
    ((30, 30), 4, 0.3)
    """
    kw = dict(
        shape=detector.shape,
        px_size=detector.px_size,
        binning=detector.binning,
        pc=detector.pc.copy(),
        **{a: getattr(detector, a) for a in _ANGLES},
    )
    kw.update(changes)
    return EBSDDetector(convention="bruker", **kw)


@dataclass(frozen=True)
class MapGeometry:
    """One global sample-detector geometry for a whole EBSD map.

    Holds the reference PC at a reference map position and the four
    angles; every other PC of the map follows from :func:`pc_field`.

    Parameters
    ----------
    pc
        Bruker PC ``(pcx, pcy, pcz)`` at *reference*.
    tilt, azimuthal, sample_tilt, twist
        Angles in degrees.
    shape
        Detector shape (rows, columns), binned.
    px_size
        Unbinned detector pixel size in micrometres.
    binning
        Detector binning.
    step_sizes
        Map step sizes (dy, dx) in micrometres.
    navigation_shape
        Map shape (rows, columns).
    reference
        Map position (row, column) of *pc*. Default is the map centre.

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry import MapGeometry
    >>> geo = MapGeometry(
    ...     pc=(0.5, 0.2, 0.6), sample_tilt=70, shape=(60, 60), px_size=70,
    ...     binning=8, step_sizes=(20, 20), navigation_shape=(11, 11),
    ... )
    >>> geo.reference
    (5.0, 5.0)
    >>> geo.detector().navigation_shape
    (11, 11)
    >>> geo.updated({"pcx": 0.01}).values(["pcx"])
    array([0.51])
    """

    pc: tuple[float, float, float]
    shape: tuple[int, int]
    px_size: float
    binning: float
    step_sizes: tuple[float, float]
    navigation_shape: tuple[int, int]
    tilt: float = 0.0
    azimuthal: float = 0.0
    sample_tilt: float = 70.0
    twist: float = 0.0
    reference: tuple[float, float] | None = field(default=None)

    def __post_init__(self):
        pc = tuple(float(v) for v in np.asarray(self.pc, dtype=float).reshape(3))
        object.__setattr__(self, "pc", pc)
        nav = tuple(int(n) for n in self.navigation_shape)
        if len(nav) == 1:
            nav = (1,) + nav
        if len(nav) != 2:
            raise ValueError(f"navigation_shape must be 2D, not {self.navigation_shape}")
        object.__setattr__(self, "navigation_shape", nav)
        object.__setattr__(self, "shape", tuple(int(n) for n in self.shape))
        object.__setattr__(self, "step_sizes", tuple(float(v) for v in self.step_sizes))
        if self.reference is None:
            ref = ((nav[0] - 1) / 2, (nav[1] - 1) / 2)
        else:
            ref = tuple(float(v) for v in self.reference)
        object.__setattr__(self, "reference", ref)
        for a in _ANGLES:
            object.__setattr__(self, a, float(getattr(self, a)))

    # ------------------------------------------------------------------ #

    @classmethod
    def from_detector(
        cls,
        detector: EBSDDetector,
        step_sizes: tuple[float, float],
        navigation_shape: tuple[int, int],
        reference: tuple[float, float] | None = None,
    ) -> MapGeometry:
        """Return the geometry of a detector with one PC or a PC map.

        With one PC, that PC is taken at *reference* (default the map
        centre). With one PC per map point, the reference PC is the mean
        PC, at the mean map position (exact for the planar fields of
        this model); the detector's PCs are otherwise not used, so
        pattern-wise PC scatter does not enter.

        Parameters
        ----------
        detector
            Detector with one PC or *navigation_shape* PCs.
        step_sizes
            Map step sizes (dy, dx) in micrometres.
        navigation_shape
            Map shape (rows, columns) or (columns,) for a line.
        reference
            Map position of a single PC. Ignored for a PC map.

        Returns
        -------
        geometry
        """
        nav = tuple(navigation_shape)
        nav2 = (1,) + nav if len(nav) == 1 else nav
        pcs = detector.pc.reshape(-1, 3)
        angles = {a: getattr(detector, a) for a in _ANGLES}
        kw = dict(
            shape=detector.shape,
            px_size=detector.px_size,
            binning=float(detector.binning),
            step_sizes=tuple(step_sizes),
            navigation_shape=nav2,
            **angles,
        )
        if pcs.shape[0] == 1:
            return cls(pc=pcs[0], reference=reference, **kw)
        if pcs.shape[0] != int(np.prod(nav2)):
            raise ValueError(
                f"The detector has {pcs.shape[0]} PCs, which fits neither one PC "
                f"nor the map's navigation shape {nav}"
            )
        # NaN PCs (e.g. unrefined points) leave the mean and its position
        finite = np.isfinite(pcs).all(axis=1)
        if not finite.any():
            raise ValueError("The detector's PCs are all NaN")
        rows, cols = np.indices(nav2, dtype=float)
        return cls(
            pc=pcs[finite].mean(axis=0),
            reference=(rows.ravel()[finite].mean(), cols.ravel()[finite].mean()),
            **kw,
        )

    def values(self, names: Sequence[str] = PARAMETERS) -> np.ndarray:
        """Return parameter values in the order of *names*."""
        check_parameters(names)
        d = dict(zip(("pcx", "pcy", "pcz"), self.pc))
        d.update({a: getattr(self, a) for a in _ANGLES})
        return np.array([d[n] for n in names], dtype=np.float64)

    def as_dict(self) -> dict[str, float]:
        """Return ``{name: value}`` for all :data:`PARAMETERS`."""
        return dict(zip(PARAMETERS, map(float, self.values())))

    def updated(self, delta: Mapping[str, float]) -> MapGeometry:
        """Return a new geometry with parameter changes added.

        PC changes are added to the reference PC, angle changes to the
        angles; the PC of every map point follows from both
        (:meth:`pc_at`). Detector and map are kept.

        Parameters
        ----------
        delta
            ``{name: change}`` for names in :data:`PARAMETERS`.

        Returns
        -------
        geometry

        Raises
        ------
        ValueError
            For an unknown parameter name.
        """
        if delta:
            check_parameters(list(delta))
        pc = np.array(self.pc)
        for i, name in enumerate(("pcx", "pcy", "pcz")):
            pc[i] += delta.get(name, 0.0)
        angles = {a: getattr(self, a) + delta.get(a, 0.0) for a in _ANGLES}
        return replace(self, pc=tuple(pc), **angles)

    @property
    def angles(self) -> tuple[float, float, float, float]:
        """``(tilt, azimuthal, sample_tilt, twist)`` in degrees."""
        return (self.tilt, self.azimuthal, self.sample_tilt, self.twist)

    def pc_at(self, points: np.ndarray) -> np.ndarray:
        """Return PCs of shape (n, 3) at map positions (n, 2) (row, col)."""
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        return pc_field(
            self.pc,
            points[:, 0],
            points[:, 1],
            self.reference,
            self.step_sizes,
            self.shape,
            self.px_size,
            self.binning,
            *self.angles,
        )

    def detector(self, points: np.ndarray | None = None) -> EBSDDetector:
        """Return a kikuchipy detector with this geometry's PC field.

        Parameters
        ----------
        points
            Map positions (n, 2). If not given, the whole map: the
            detector's navigation shape is then :attr:`navigation_shape`
            (or ``(columns,)`` for a one-row map).

        Returns
        -------
        detector
        """
        if points is None:
            rows, cols = np.indices(self.navigation_shape)
            points = np.stack([rows.ravel(), cols.ravel()], axis=1)
            nav = self.navigation_shape
            if nav[0] == 1:
                nav = (nav[1],)
        else:
            points = np.asarray(points, dtype=float).reshape(-1, 2)
            nav = (len(points),)
        pc = self.pc_at(points).reshape(nav + (3,))
        return EBSDDetector(
            shape=self.shape,
            px_size=self.px_size,
            binning=self.binning,
            tilt=self.tilt,
            azimuthal=self.azimuthal,
            sample_tilt=self.sample_tilt,
            twist=self.twist,
            pc=pc,
        )

    def displacement(
        self,
        other: MapGeometry,
        points: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        rotations: np.ndarray | None = None,
    ) -> np.ndarray:
        """Return the forward displacement from this geometry to *other*.

        Parameters
        ----------
        other
            Geometry B.
        points
            Map positions (n, 2).
        x, y
            Pixel coordinates (m,), the same for every point, or (n, m),
            per point.
        rotations
            Per-point crystal rotation matrices (n, 3, 3), see *rotation*
            of :func:`forward_map`; default none.

        Returns
        -------
        uv
            Array (n, m, 2) of displacements (dx, dy) in pixels.
        """
        pa = self.pc_at(points)[:, None, :]
        pb = other.pc_at(points)[:, None, :]
        x = np.atleast_2d(np.asarray(x, dtype=float))
        y = np.atleast_2d(np.asarray(y, dtype=float))
        rot = None if rotations is None else np.asarray(rotations)[:, None]
        xb, yb = forward_map(x, y, pa, self.angles, pb, other.angles, self.shape, rot)
        return np.stack([xb - x, yb - y], axis=-1)
