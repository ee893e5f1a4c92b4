"""Global DIC-based sample-detector geometry calibration for EBSD maps.

Importing the package registers :meth:`refine_geometry_dic` on kikuchipy's
:class:`~kikuchipy.signals.EBSD` (and so on ``LazyEBSD``): the method is
:func:`kikuchipy_geomdic.refinement.refine_geometry_dic` itself, with the
signal as its first argument.
"""

import warnings

from kikuchipy.signals import EBSD

from kikuchipy_geomdic import (
    comparison,
    displacement,
    geometry,
    jacobian,
    maps,
    phases,
    simulation,
    solve,
    study,
    synthetic,
)
from kikuchipy_geomdic.refinement import GeometryRefinementResult, refine_geometry_dic

__version__ = "0.1.0.dev0"

__all__ = [
    "GeometryRefinementResult",
    "refine_geometry_dic",
    "comparison",
    "displacement",
    "geometry",
    "jacobian",
    "maps",
    "phases",
    "simulation",
    "solve",
    "study",
    "synthetic",
    "__version__",
]


def _is_ours(method) -> bool:
    """Whether *method* is this package's refine_geometry_dic, also from an
    earlier import of a reloaded module (importlib.reload, IPython's
    autoreload)."""
    return method is refine_geometry_dic or (
        getattr(method, "__module__", None) == refine_geometry_dic.__module__
        and getattr(method, "__qualname__", None) == refine_geometry_dic.__qualname__
    )


def _register() -> None:
    """Make :func:`refine_geometry_dic` a method of kikuchipy's EBSD.

    The function itself is assigned (its first parameter is the signal), so
    ``inspect.signature`` and ``help()`` show its parameters and
    ``s.refine_geometry_dic`` binds the signal. Registering is idempotent.

    If EBSD already has a ``refine_geometry_dic`` that is not ours (a future
    kikuchipy, another plugin), we warn and leave it alone rather than
    raise: replacing it would silently change what other code calls, and
    raising would make this package unimportable although its functional
    API, ``kikuchipy_geomdic.refine_geometry_dic(signal, ...)``, does not
    need the method.
    """
    existing = getattr(EBSD, "refine_geometry_dic", None)
    if existing is refine_geometry_dic:
        return
    if existing is not None and not _is_ours(existing):
        warnings.warn(
            "kikuchipy's EBSD already has a refine_geometry_dic attribute "
            f"({existing!r}) that is not kikuchipy-geomdic's: it is left in place. Call "
            "kikuchipy_geomdic.refine_geometry_dic(signal, ...) instead of the method.",
            UserWarning,
            stacklevel=3,
        )
        return
    EBSD.refine_geometry_dic = refine_geometry_dic


_register()
