"""The geometry calibration: Jacobians, the weighted least squares, the
Cramer-Rao bound, the DIC stage, the full field, the paper's loop and
:func:`refine_geometry_dic` with its result.

Layer 6: may import every layer below it (:mod:`~kikuchipy_geomdic.geometry`,
:mod:`~kikuchipy_geomdic.io`, :mod:`~kikuchipy_geomdic.patterns`,
:mod:`~kikuchipy_geomdic.indexing`, :mod:`~kikuchipy_geomdic.plotting`).
"""

from kikuchipy_geomdic.calibration.bound import CramerRaoBound, cramer_rao_bound
from kikuchipy_geomdic.calibration.refinement import (
    GeometryRefinementResult,
    calibration_points,
    refine_geometry_dic,
)

__all__ = [
    "CramerRaoBound",
    "cramer_rao_bound",
    "GeometryRefinementResult",
    "calibration_points",
    "refine_geometry_dic",
]
