"""Shared fixtures: small data built once per test session.

Real patterns are third-party data and are not in the repository: they are
read from a kikuchipy data cache, the folder the environment variable
``KIKUCHIPY_DATA_DIR`` names. Unless it is set, it is pointed here at
``../shared/data/kikuchipy_cache`` beside the repository when that exists,
so that nothing is downloaded.
"""

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import kikuchipy as kp
import pytest

from kikuchipy_geomdic.validation import master_patterns

# kikuchipy reads KIKUCHIPY_DATA_DIR when it first looks for a data set
# (kikuchipy.data._data.get_fetching_pooch, cached), not on import: set
# here, before any test runs, it is in time.
_CACHE = Path(__file__).resolve().parents[2] / "shared" / "data" / "kikuchipy_cache"
if "KIKUCHIPY_DATA_DIR" not in os.environ and _CACHE.is_dir():
    os.environ["KIKUCHIPY_DATA_DIR"] = str(_CACHE)


@pytest.fixture(scope="session")
def si_mp():
    """Dynamical silicon master pattern (package data)."""
    return master_patterns.master_pattern("Si", kind="dynamical")


@pytest.fixture(scope="session")
def bto_mp():
    """Dynamical BaTiO3 master pattern (package data, de-ebsd, 801 x 801)."""
    return master_patterns.master_pattern("BaTiO3", kind="dynamical")


def _si_moving_screen(distance: int):
    """kikuchipy's real silicon pattern with the camera moved out by
    *distance* mm (0, 5 or 10), read offline from kikuchipy's data cache.

    Fails (does not skip) the test when the file is not there, naming
    ``KIKUCHIPY_DATA_DIR``.
    """
    try:
        return kp.data.si_ebsd_moving_screen(distance, allow_download=False)
    except Exception as error:  # kikuchipy raises ValueError, pooch's absence ImportError
        problem = error
    # Outside the except clause: the message alone, not kikuchipy's traceback too
    where = os.environ.get("KIKUCHIPY_DATA_DIR", "unset")
    pytest.fail(
        "kikuchipy's silicon moving-screen patterns (third-party data, not in this "
        "repository) were not found offline. Set KIKUCHIPY_DATA_DIR to the absolute "
        "path of a kikuchipy data cache that holds "
        "<version>/data/silicon_ebsd_moving_screen/ (such as ../shared/data/"
        "kikuchipy_cache beside the repository), or fill kikuchipy's cache once "
        f"online with kp.data.si_ebsd_moving_screen({distance}, allow_download=True). "
        f"KIKUCHIPY_DATA_DIR: {where}. kikuchipy said: {problem}",
        pytrace=False,
    )


@pytest.fixture(scope="session")
def si_moving_screen():
    """Loader of kikuchipy's real silicon patterns: ``si_moving_screen(5)`` is
    the pattern with the camera moved out by 5 mm, read offline from
    kikuchipy's data cache; the test fails, naming ``KIKUCHIPY_DATA_DIR``,
    when it is not there."""
    return _si_moving_screen
