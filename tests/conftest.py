"""Shared fixtures: small data built once per test session.

Real patterns are third-party data and are not in the repository: they are
read from a kikuchipy data cache, the folder the environment variable
``KIKUCHIPY_DATA_DIR`` names. Unless it is set, it is pointed here at
``../shared/data/kikuchipy_cache`` beside the repository when that exists,
so that nothing is downloaded.

Tests of such data skip, saying how to get it, where it cannot be read;
they fail instead where the run asks for the data: ``KIKUCHIPY_DATA_DIR``
set before pytest starts (as ``.ci/run`` sets it) or ``--require-data``.
"""

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import kikuchipy as kp
import pytest

from kikuchipy_geomdic.validation import master_patterns

# Asked for by the environment, before this file points the variable at a
# cache of its own finding
_DATA_ASKED = "KIKUCHIPY_DATA_DIR" in os.environ

# kikuchipy reads KIKUCHIPY_DATA_DIR when it first looks for a data set
# (kikuchipy.data._data.get_fetching_pooch, cached), not on import: set
# here, before any test runs, it is in time.
_CACHE = Path(__file__).resolve().parents[2] / "shared" / "data" / "kikuchipy_cache"
if not _DATA_ASKED and _CACHE.is_dir():
    os.environ["KIKUCHIPY_DATA_DIR"] = str(_CACHE)


def pytest_addoption(parser):
    parser.addoption(
        "--require-data",
        action="store_true",
        help="fail, not skip, tests whose third-party data cannot be read",
    )


def data_required(config) -> bool:
    """Whether tests of third-party data fail (True) or skip where it
    cannot be read."""
    return _DATA_ASKED or bool(config.getoption("--require-data"))


@pytest.fixture(scope="session")
def si_mp():
    """Dynamical silicon master pattern (package data)."""
    return master_patterns.master_pattern("Si", kind="dynamical")


@pytest.fixture(scope="session")
def bto_mp():
    """Dynamical BaTiO3 master pattern (package data, de-ebsd, 801 x 801)."""
    return master_patterns.master_pattern("BaTiO3", kind="dynamical")


def _si_moving_screen(distance: int, required: bool = True):
    """kikuchipy's real silicon pattern with the camera moved out by
    *distance* mm (0, 5 or 10), read offline from kikuchipy's data cache.

    Where the file cannot be read, the test fails if the data are
    *required*, and skips otherwise, saying how to get them.
    """
    try:
        return kp.data.si_ebsd_moving_screen(distance, allow_download=False)
    except Exception as error:  # kikuchipy raises ValueError, pooch's absence ImportError
        problem = error
    # Outside the except clause: the message alone, not kikuchipy's traceback too
    where = os.environ.get("KIKUCHIPY_DATA_DIR", "unset")
    message = (
        "kikuchipy's silicon moving-screen patterns (third-party data, not in this "
        "repository) were not found offline. Set KIKUCHIPY_DATA_DIR to the absolute "
        "path of a kikuchipy data cache that holds "
        "<version>/data/silicon_ebsd_moving_screen/ (such as ../shared/data/"
        "kikuchipy_cache beside the repository), or fill kikuchipy's cache once "
        f"online with kp.data.si_ebsd_moving_screen({distance}, allow_download=True). "
        f"KIKUCHIPY_DATA_DIR: {where}. kikuchipy said: {problem}"
    )
    if required:
        pytest.fail(message, pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session")
def si_moving_screen(pytestconfig):
    """Loader of kikuchipy's real silicon patterns: ``si_moving_screen(5)`` is
    the pattern with the camera moved out by 5 mm, read offline from
    kikuchipy's data cache; the test skips, saying how to get them, when
    they are not there, and fails if the run requires them
    (:func:`data_required`)."""
    required = data_required(pytestconfig)
    return lambda distance: _si_moving_screen(distance, required)


class TwoPhaseMap:
    """A synthetic map of Ni (left half) and Si (right half) points, each
    phase's patterns simulated from its shipped master pattern at one true
    geometry (a random orientation per point, 200 counts/px), and the
    truth, the start (orientations 0.3 deg off, PC about 2 % off) and both
    phases' :class:`~kikuchipy_geomdic.validation.synthetic.SyntheticMap`."""

    def __init__(self, nav=(6, 6), shape=(60, 60), seed=0, dose=200, names=("Ni", "Si")):
        import numpy as np
        from orix.crystal_map import CrystalMap, PhaseList
        from orix.quaternion import Rotation

        from kikuchipy_geomdic.validation import synthetic

        # ni and si: the first and second phase (Ni and Si unless *names* say)
        self.ni = synthetic.synthetic_map(names[0], nav, shape=shape, seed=seed, dose=dose)
        self.si = synthetic.synthetic_map(names[1], nav, shape=shape, seed=seed + 1, dose=dose)
        self.is_si = (np.indices(nav)[1] >= nav[1] // 2).ravel()
        mask = self.is_si.reshape(nav + (1, 1))
        self.signal = self.ni.signal.deepcopy()
        self.signal.data = np.where(mask, self.si.signal.data, self.ni.signal.data)
        phases = PhaseList({0: self.ni.master_pattern.phase, 1: self.si.master_pattern.phase})
        phases[1].color = "tab:orange"

        def both(a, b, phase_id=None):
            q = np.where(
                self.is_si[:, None],
                b.rotations.data.reshape(-1, 4),
                a.rotations.data.reshape(-1, 4),
            )
            return CrystalMap(
                rotations=Rotation(q),
                phase_id=self.is_si.astype(int) if phase_id is None else phase_id,
                x=a.x,
                y=a.y,
                phase_list=phases.deepcopy(),
                scan_unit="um",
            )

        self.xmap = both(self.ni.xmap, self.si.xmap)
        self.start_xmap = both(self.ni.start_xmap, self.si.start_xmap)
        self.both = both
        self.master_patterns = [self.ni.master_pattern, self.si.master_pattern]
        self.start_detector = self.ni.start_detector
        self.detector = self.ni.detector
        self.geometry = self.ni.geometry


@pytest.fixture(scope="session")
def two_phase():
    """:class:`TwoPhaseMap` of 6 x 6 points of 60 px (Ni left, Si right)."""
    return TwoPhaseMap()
