"""The geometry calibration: Jacobians
(:mod:`~kikuchipy_geomdic.calibration.jacobian`), the weighted least squares
(:mod:`~kikuchipy_geomdic.calibration.solve`), the Cramer-Rao bound
(:mod:`~kikuchipy_geomdic.calibration.bound`),
:func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic` (its
stages in the private modules of this package) and its result
(:mod:`~kikuchipy_geomdic.calibration.result`).

Layer 6: may import every layer below it (:mod:`~kikuchipy_geomdic.geometry`,
:mod:`~kikuchipy_geomdic.io`, :mod:`~kikuchipy_geomdic.patterns`,
:mod:`~kikuchipy_geomdic.indexing`, :mod:`~kikuchipy_geomdic.plotting`).
"""

from kikuchipy_geomdic.calibration._crystal import NotOneCrystalError
from kikuchipy_geomdic.calibration.bound import CramerRaoBound, cramer_rao_bound
from kikuchipy_geomdic.calibration.refinement import calibration_points, refine_geometry_dic
from kikuchipy_geomdic.calibration.result import GeometryRefinementResult

__all__ = [
    "CramerRaoBound",
    "cramer_rao_bound",
    "GeometryRefinementResult",
    "NotOneCrystalError",
    "calibration_points",
    "refine_geometry_dic",
]
