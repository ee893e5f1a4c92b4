"""Global DIC-based sample-detector geometry calibration for EBSD maps.

Importing the package registers :meth:`refine_geometry_dic` on kikuchipy's
:class:`~kikuchipy.signals.EBSD` (and so on ``LazyEBSD``).
"""

from kikuchipy_geomdic import geometry, simulation, synthetic

__version__ = "0.1.0.dev0"

__all__ = ["geometry", "simulation", "synthetic", "__version__"]
