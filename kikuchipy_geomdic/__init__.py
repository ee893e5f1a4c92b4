"""Global DIC-based sample-detector geometry calibration for EBSD maps.

Importing the package registers :meth:`refine_geometry_dic` and
:meth:`reindex` on kikuchipy's :class:`~kikuchipy.signals.EBSD` (and so on
``LazyEBSD``): each method is the package's function itself, with the
signal as its first argument.

The subpackages are layers; a module imports only from its own layer and
those below it (``tests/test_package.py`` checks this):

0. ``_version``
1. :mod:`~kikuchipy_geomdic.geometry`: parameters, PC field, forward map, map shapes
2. :mod:`~kikuchipy_geomdic.io`: PC conventions, detector and summary files
3. :mod:`~kikuchipy_geomdic.patterns`: simulation, phases, DIC
4. :mod:`~kikuchipy_geomdic.indexing`: orientations, ``reindex``, variants
5. :mod:`~kikuchipy_geomdic.plotting`: figures
6. :mod:`~kikuchipy_geomdic.calibration`: ``refine_geometry_dic`` and its stages
7. :mod:`~kikuchipy_geomdic.validation`: synthetic maps, the study, comparisons
8. :mod:`~kikuchipy_geomdic.cli`: the command line
"""

import warnings

from kikuchipy.signals import EBSD

from kikuchipy_geomdic import (
    calibration,
    geometry,
    indexing,
    io,
    patterns,
    plotting,
    validation,
)
from kikuchipy_geomdic._version import __version__
from kikuchipy_geomdic.calibration import GeometryRefinementResult, refine_geometry_dic
from kikuchipy_geomdic.indexing import reindex

__all__ = [
    "GeometryRefinementResult",
    "refine_geometry_dic",
    "reindex",
    "calibration",
    "geometry",
    "indexing",
    "io",
    "patterns",
    "plotting",
    "validation",
    "__version__",
]

#: The methods registered on kikuchipy's EBSD: name -> function.
METHODS = {"refine_geometry_dic": refine_geometry_dic, "reindex": reindex}


def _is_ours(method, function) -> bool:
    """Whether *method* is *function*, also from an earlier import of a
    reloaded module (importlib.reload, IPython's autoreload)."""
    return method is function or (
        getattr(method, "__module__", None) == function.__module__
        and getattr(method, "__qualname__", None) == function.__qualname__
    )


def _register() -> None:
    """Make each function of :data:`METHODS` a method of kikuchipy's EBSD.

    The function itself is assigned (its first parameter is the signal), so
    ``inspect.signature`` and ``help()`` show its parameters and
    ``s.refine_geometry_dic`` binds the signal. Registering is idempotent.

    If EBSD already has an attribute of that name that is not ours (a
    future kikuchipy, another plugin), we warn and leave it alone rather
    than raise: replacing it would silently change what other code calls,
    and raising would make this package unimportable although its
    functional API, ``kikuchipy_geomdic.refine_geometry_dic(signal, ...)``,
    does not need the method.
    """
    for name, function in METHODS.items():
        existing = getattr(EBSD, name, None)
        if existing is function:
            continue
        if existing is not None and not _is_ours(existing, function):
            warnings.warn(
                f"kikuchipy's EBSD already has a {name} attribute ({existing!r}) that is "
                "not kikuchipy-geomdic's: it is left in place. Call "
                f"kikuchipy_geomdic.{name}(signal, ...) instead of the method.",
                UserWarning,
                stacklevel=3,
            )
            continue
        setattr(EBSD, name, function)


_register()
