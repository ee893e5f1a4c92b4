"""The geometry parameters: names, units, finite-difference steps and the
exact tilt/sample_tilt equivalence, with the checks of parameter names.

Layer 1 (geometry): imports nothing of the package outside its own layer.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = [
    "PARAMETERS",
    "DEFAULT_PARAMETERS",
    "DEFAULT_STEPS",
    "UNITS",
    "EQUIVALENT_PARAMETERS",
    "check_parameters",
    "solved_parameters",
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
