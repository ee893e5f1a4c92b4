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
strong coupling:
:data:`~kikuchipy_geomdic.geometry.parameters.EQUIVALENT_PARAMETERS` states
it so that the solver treats the pair deliberately rather than letting
damping split it.

Pixel coordinates
-----------------
Functions here take and return pixel coordinates ``(x, y)`` with the centre
of pixel ``(row j, column i)`` at ``(i, j)``, as OpenCV and scikit-image
report feature positions. kikuchipy's simulation places that centre at
``(i + 0.5, j + 0.5)``; the conversion happens only inside
:func:`~kikuchipy_geomdic.geometry.projection.forward_map`.

Modules
-------
:mod:`~kikuchipy_geomdic.geometry.parameters` (names, units, steps),
:mod:`~kikuchipy_geomdic.geometry.projection` (rotation, PC field, forward
map), :mod:`~kikuchipy_geomdic.geometry.rotations` (rotation vectors),
:mod:`~kikuchipy_geomdic.geometry.map_geometry`
(:class:`~kikuchipy_geomdic.geometry.map_geometry.MapGeometry`) and
:mod:`~kikuchipy_geomdic.geometry.maps` (navigation shapes, flat indices,
usable points); their public names are exported here.

Layer 1 (geometry): imports nothing of the package outside its own layer.
"""

from kikuchipy_geomdic.geometry.map_geometry import MapGeometry, copy_detector
from kikuchipy_geomdic.geometry.parameters import (
    DEFAULT_PARAMETERS,
    DEFAULT_STEPS,
    EQUIVALENT_PARAMETERS,
    PARAMETERS,
    UNITS,
    check_parameters,
    solved_parameters,
)
from kikuchipy_geomdic.geometry.projection import forward_map, pc_field, sample_to_detector_matrix
from kikuchipy_geomdic.geometry.rotations import rotation_vectors, rotations_from_vectors

__all__ = [
    "DEFAULT_PARAMETERS",
    "DEFAULT_STEPS",
    "EQUIVALENT_PARAMETERS",
    "PARAMETERS",
    "UNITS",
    "MapGeometry",
    "check_parameters",
    "copy_detector",
    "forward_map",
    "pc_field",
    "rotation_vectors",
    "rotations_from_vectors",
    "sample_to_detector_matrix",
    "solved_parameters",
]
