"""The sample-detector geometry model: parameters, PC field and
forward displacement map.

This module is the one place where the geometry of an EBSD map is
described. It follows kikuchipy's :class:`~kikuchipy.detectors.EBSDDetector`
exactly (Bruker PC convention, edge-based pixel coordinates, kikuchipy's
sample-to-detector rotation), so a geometry built here and a detector built
by kikuchipy always project the same patterns.

Parameters
----------
The paper's parameter vector is
``p = [pcx, pcy, pcz, tilt, azimuthal, sample_tilt]`` with kikuchipy's
names; ``twist`` is an optional seventh. PC values are Bruker fractions
(``pcx`` of the detector width, ``pcy`` and ``pcz`` of the height) and
angles are in degrees, with the sign conventions of the supported
kikuchipy versions (the sign of ``azimuthal`` flipped after 0.11).

The tilt degeneracy
-------------------
In kikuchipy's projection only the difference ``tilt - sample_tilt``
enters the sample-to-detector rotation: the sample tilt rotates about the
detector's X axis before the detector tilt does, about the same axis. The
PC field (how the PC moves with the beam over the map) also only depends
on this difference. Patterns and PC fields for (``sample_tilt`` 70,
``tilt`` 5) and (65, 0) are therefore identical, and a Jacobian with both
columns has rank one less than its number of columns. This is exact, not a
strong coupling: :data:`EQUIVALENT_PARAMETERS` states it so that the
solver treats the pair deliberately rather than letting damping split it.

Pixel coordinates
-----------------
Functions here take and return pixel coordinates ``(x, y)`` with the centre
of pixel ``(row j, column i)`` at ``(i, j)``, as OpenCV and scikit-image
report feature positions. kikuchipy's simulation places that centre at
``(i + 0.5, j + 0.5)``; the conversion happens only inside this module.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from kikuchipy.detectors import EBSDDetector
from orix.quaternion import Rotation

__all__ = [
    "PARAMETERS",
    "DEFAULT_PARAMETERS",
    "DEFAULT_STEPS",
    "UNITS",
    "EQUIVALENT_PARAMETERS",
    "MapGeometry",
    "check_parameters",
    "solved_parameters",
    "sample_to_detector_matrix",
    "pc_field",
    "forward_map",
    "copy_detector",
    "rotation_vectors",
    "rotations_from_vectors",
]

#: All geometry parameters, in the order of the paper's vector ``p`` plus
#: ``twist``.
PARAMETERS = ("pcx", "pcy", "pcz", "tilt", "azimuthal", "sample_tilt", "twist")

#: The paper's six parameters, refined by default.
DEFAULT_PARAMETERS = PARAMETERS[:6]

#: Units of each parameter.
UNITS = {
    "pcx": "fraction of detector width",
    "pcy": "fraction of detector height",
    "pcz": "fraction of detector height",
    "tilt": "deg",
    "azimuthal": "deg",
    "sample_tilt": "deg",
    "twist": "deg",
}

#: Default central-difference step per parameter. Each moves features of
#: a 120 x 120 pattern by roughly 0.5-1 px: large against the DIC noise
#: (a few hundredths of a pixel), small against the nonlinearity.
DEFAULT_STEPS = {
    "pcx": 0.005,
    "pcy": 0.005,
    "pcz": 0.005,
    "tilt": 0.5,
    "azimuthal": 0.5,
    "sample_tilt": 0.5,
    "twist": 0.5,
}

#: Parameters whose effect equals another parameter's times a factor,
#: exactly, in kikuchipy's projection: ``{name: (other, factor)}``.
#: Changing ``sample_tilt`` by ``d`` does what changing ``tilt`` by ``-d``
#: does, to patterns and to the PC field alike.
EQUIVALENT_PARAMETERS = {"sample_tilt": ("tilt", -1.0)}

_ANGLES = ("tilt", "azimuthal", "sample_tilt", "twist")


def check_parameters(names: Sequence[str]) -> tuple[str, ...]:
    """Return parameter names as a tuple in canonical order, or raise.

    Parameters
    ----------
    names
        Names from :data:`PARAMETERS`.

    Returns
    -------
    names
        The same names in the order of :data:`PARAMETERS`.

    Raises
    ------
    ValueError
        If a name is unknown, repeated, or none are given.

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry import check_parameters
    >>> check_parameters(["tilt", "pcx"])
    ('pcx', 'tilt')
    """
    if isinstance(names, str):
        names = [names]
    names = list(names)
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        raise ValueError(
            f"Unknown geometry parameter(s) {unknown}; choose from {list(PARAMETERS)}"
        )
    if len(set(names)) != len(names):
        raise ValueError(f"Geometry parameters are repeated: {names}")
    if not names:
        raise ValueError("At least one geometry parameter must be given")
    return tuple(n for n in PARAMETERS if n in names)


def solved_parameters(names: Sequence[str]) -> tuple[tuple[str, ...], dict[str, str]]:
    """Return the parameters a solve has columns for, and ``{name: base}``
    for each one left out because its column is a multiple of a solved
    one's (:data:`EQUIVALENT_PARAMETERS`: only tilt - sample_tilt is seen).

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry import solved_parameters
    >>> solved_parameters(["pcx", "tilt", "sample_tilt"])
    (('pcx', 'tilt'), {'sample_tilt': 'tilt'})
    """
    solved, split = [], {}
    for n in names:
        base = EQUIVALENT_PARAMETERS.get(n, (None,))[0]
        if base in names:
            split[n] = base
        else:
            solved.append(n)
    return tuple(solved), split


def sample_to_detector_matrix(
    tilt: float, azimuthal: float, sample_tilt: float, twist: float = 0.0
) -> np.ndarray:
    """Return kikuchipy's sample-to-detector rotation matrix.

    Parameters
    ----------
    tilt, azimuthal, sample_tilt, twist
        Angles in degrees, as in :class:`~kikuchipy.detectors.EBSDDetector`.

    Returns
    -------
    matrix
        Array of shape (3, 3) with ``matrix @ v_sample = v_detector``.

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.geometry import sample_to_detector_matrix
    >>> a = sample_to_detector_matrix(5, 0, 70)
    >>> b = sample_to_detector_matrix(0, 0, 65)
    >>> bool(np.allclose(a, b))  # only tilt - sample_tilt matters
    True
    """
    # Taken from kikuchipy itself so the two can never disagree
    det = EBSDDetector(
        tilt=float(tilt),
        azimuthal=float(azimuthal),
        sample_tilt=float(sample_tilt),
        twist=float(twist),
    )
    return det.sample_to_detector.to_matrix().reshape(3, 3)


def pc_field(
    pc: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    reference: tuple[float, float],
    step_sizes: tuple[float, float],
    shape: tuple[int, int],
    px_size: float,
    binning: float,
    tilt: float,
    azimuthal: float,
    sample_tilt: float,
    twist: float = 0.0,
) -> np.ndarray:
    r"""Return the PC at map positions from one global geometry.

    The beam moves over the sample surface; the PC is the foot of the
    perpendicular from the beam's impact point to the detector screen.
    A beam displacement :math:`\mathbf{s}` in the sample frame is
    :math:`\mathbf{M}\mathbf{s}` in the detector frame, with
    :math:`\mathbf{M}` the full sample-to-detector rotation (all four
    angles), so the PC moves within the screen by its X and Y components
    and ``pcz`` changes by its Z component.

    Parameters
    ----------
    pc
        Bruker PC ``(pcx, pcy, pcz)`` at the *reference* map position.
    rows, cols
        Map positions (row, column), in steps, of any shape (fractional
        values allowed).
    reference
        Map position (row, column) where the PC equals *pc*.
    step_sizes
        Map step sizes (dy, dx) in the same length unit as *px_size*
        (kikuchipy uses micrometres).
    shape
        Detector shape (rows, columns), binned.
    px_size
        Unbinned detector pixel size.
    binning
        Detector binning.
    tilt, azimuthal, sample_tilt, twist
        Angles in degrees.

    Returns
    -------
    pcs
        Array of shape ``rows.shape + (3,)``.

    Notes
    -----
    With ``azimuthal = twist = 0`` this equals
    :meth:`~kikuchipy.detectors.EBSDDetector.extrapolate_pc` (Singh et al.
    2017, appendix A), which ignores the two other angles. kikuchipy's
    sample frame has :math:`X_s` along decreasing map rows and
    :math:`Y_s` along decreasing map columns.

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry import pc_field
    >>> pcs = pc_field(
    ...     (0.5, 0.2, 0.6), rows=[0, 10], cols=[0, 0], reference=(0, 0),
    ...     step_sizes=(10, 10), shape=(120, 120), px_size=70, binning=4,
    ...     tilt=0, azimuthal=0, sample_tilt=70,
    ... )
    >>> pcs.shape
    (2, 3)
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    pc = np.asarray(pc, dtype=np.float64).reshape(3)
    dy, dx = step_sizes
    nrows, ncols = shape
    s = np.stack(
        [
            -(rows - reference[0]) * dy,
            -(cols - reference[1]) * dx,
            np.zeros_like(rows),
        ],
        axis=-1,
    )
    m = sample_to_detector_matrix(tilt, azimuthal, sample_tilt, twist)
    d = s @ m.T / (px_size * binning)  # Detector frame, in binned pixels
    # The source sits at (pcx Nx, -pcy Ny, -pcz Ny) from the screen's
    # upper-left corner in the detector frame
    return pc + np.stack([d[..., 0] / ncols, -d[..., 1] / nrows, -d[..., 2] / nrows], axis=-1)


def forward_map(
    x: np.ndarray,
    y: np.ndarray,
    pc_a: np.ndarray,
    angles_a: Sequence[float],
    pc_b: np.ndarray,
    angles_b: Sequence[float],
    shape: tuple[int, int],
    rotation: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Return where a pixel seen with geometry A lands with geometry B.

    A feature of a pattern at ``(x, y)`` under geometry A shows a
    sample-frame direction; the same direction (same crystal orientation)
    lands at ``(x_b, y_b)`` under geometry B. ``(x_b - x, y_b - y)`` is the
    displacement a geometry change causes, predicted without simulating.
    With *rotation*, the crystal is also rotated: its orientation ``g``
    becomes ``g * T`` (orix's right factor, a sample-frame rotation), and
    the feature follows its crystal direction, which now points along
    ``T^-1`` times the old sample direction.

    Parameters
    ----------
    x, y
        Pixel coordinates (centre of pixel (j, i) at (i, j)) under A.
    pc_a, pc_b
        Bruker PCs of shape (3,) or ``(n, 1, 3)``-like, broadcasting
        against *x* and *y* with a trailing axis of 3.
    angles_a, angles_b
        ``(tilt, azimuthal, sample_tilt, twist)`` in degrees.
    shape
        Detector shape (rows, columns).
    rotation
        Rotation matrix ``T`` (3, 3) of the crystal change, or matrices
        broadcasting against *x* with two trailing axes of 3 (e.g.
        ``(n, 1, 3, 3)``, one per pattern). Default: no change.

    Returns
    -------
    x_b, y_b
        Pixel coordinates under B, broadcast shape of the inputs.
        Directions that miss the screen plane of B (behind the source)
        are NaN.

    Examples
    --------
    >>> from kikuchipy_geomdic.geometry import forward_map
    >>> xb, yb = forward_map(
    ...     10.0, 20.0, (0.5, 0.5, 0.6), (0, 0, 70, 0),
    ...     (0.5 + 1 / 60, 0.5, 0.6), (0, 0, 70, 0), shape=(60, 60),
    ... )
    >>> round(float(xb), 9), round(float(yb), 9)  # PCx by +1 px: +1 px
    (11.0, 20.0)
    """
    nrows, ncols = shape
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    pc_a = np.asarray(pc_a, dtype=np.float64)
    pc_b = np.asarray(pc_b, dtype=np.float64)
    # Vector from the source to the pixel centre in detector frame A,
    # in units of binned pixels (as in kikuchipy's direction cosines)
    v_a = np.stack(
        np.broadcast_arrays(
            x + 0.5 - pc_a[..., 0] * ncols,
            pc_a[..., 1] * nrows - (y + 0.5),
            pc_a[..., 2] * nrows,
        ),
        axis=-1,
    )
    m_a = sample_to_detector_matrix(*angles_a)
    m_b = sample_to_detector_matrix(*angles_b)
    if rotation is None:
        v_b = v_a @ (m_b @ m_a.T).T
    else:
        # Row vectors: sample direction s = M_a^T v_a, then T^-1 s, then M_b
        s_a = v_a @ m_a
        v_b = np.einsum("...i,...ij->...j", s_a, np.asarray(rotation, dtype=np.float64))
        v_b = v_b @ m_b.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = pc_b[..., 2] * nrows / v_b[..., 2]
        t = np.where(t > 0, t, np.nan)
        x_b = pc_b[..., 0] * ncols + t * v_b[..., 0] - 0.5
        y_b = pc_b[..., 1] * nrows - t * v_b[..., 1] - 0.5
    return x_b, y_b


def rotation_vectors(rotations: Rotation) -> np.ndarray:
    """Return rotation vectors (angle times axis) in radians.

    Orientation changes ``g -> g * T`` (orix's right factor, a sample-frame
    rotation) are small; their vectors add to first order.

    Parameters
    ----------
    rotations
        Rotations (any shape; flattened). ``q`` and ``-q`` give the same
        vector, of length at most pi.

    Returns
    -------
    vectors
        Array (n, 3), accurate also for tiny angles.

    Examples
    --------
    >>> import numpy as np
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.geometry import rotation_vectors, rotations_from_vectors
    >>> v = np.array([[0.0, 0.0, 0.1], [1e-9, 0.0, 0.0]])
    >>> bool(np.allclose(rotation_vectors(rotations_from_vectors(v)), v, rtol=1e-9, atol=0))
    True
    """
    q = np.asarray(Rotation(rotations).flatten().data, dtype=float)
    q = np.where(q[:, :1] < 0, -q, q)
    n = np.linalg.norm(q[:, 1:], axis=1)
    angle = 2 * np.arctan2(n, q[:, 0])
    factor = np.where(n > 0, angle / np.where(n > 0, n, 1.0), 2.0)
    return q[:, 1:] * factor[:, None]


def rotations_from_vectors(vectors: np.ndarray) -> Rotation:
    """Return rotations from rotation vectors; the inverse of
    :func:`rotation_vectors`.

    Parameters
    ----------
    vectors
        Rotation vectors (n, 3) (or (3,)): axis times angle, radians.

    Returns
    -------
    rotations
        orix rotations (n,).

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.geometry import rotation_vectors, rotations_from_vectors
    >>> v = np.array([[0.0, 0.0, np.pi / 2]])
    >>> np.allclose(rotation_vectors(rotations_from_vectors(v)), v)
    True
    """
    v = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    half = np.linalg.norm(v, axis=1) / 2
    # sin(x) / x without dividing by zero; exact to float64 for tiny x
    sinc = np.sinc(half / np.pi) / 2
    return Rotation(np.concatenate([np.cos(half)[:, None], v * sinc[:, None]], axis=1))


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
