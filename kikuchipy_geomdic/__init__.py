"""Global DIC-based sample-detector geometry calibration for EBSD maps.

Importing the package registers :meth:`refine_geometry_dic` on kikuchipy's
:class:`~kikuchipy.signals.EBSD` (and so on ``LazyEBSD``): a thin method
over :func:`kikuchipy_geomdic.refinement.refine_geometry_dic`.
"""

from kikuchipy.signals import EBSD

from kikuchipy_geomdic import (
    displacement,
    geometry,
    jacobian,
    simulation,
    solve,
    synthetic,
    validation,
)
from kikuchipy_geomdic.refinement import GeometryRefinementResult, refine_geometry_dic

__version__ = "0.1.0.dev0"

__all__ = [
    "GeometryRefinementResult",
    "refine_geometry_dic",
    "displacement",
    "geometry",
    "jacobian",
    "simulation",
    "solve",
    "synthetic",
    "validation",
    "__version__",
]


def _refine_geometry_dic(self, xmap, detector, master_pattern, energy, **kwargs):
    return refine_geometry_dic(self, xmap, detector, master_pattern, energy, **kwargs)


_refine_geometry_dic.__doc__ = refine_geometry_dic.__doc__
_refine_geometry_dic.__name__ = "refine_geometry_dic"
EBSD.refine_geometry_dic = _refine_geometry_dic
