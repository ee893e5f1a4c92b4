"""Shared fixtures: small data built once per test session."""

import matplotlib

matplotlib.use("Agg")

import pytest

from kikuchipy_geomdic.validation import master_patterns


@pytest.fixture(scope="session")
def si_mp():
    """Dynamical silicon master pattern (package data)."""
    return master_patterns.master_pattern("Si", kind="dynamical")


@pytest.fixture(scope="session")
def bto_mp():
    """Dynamical BaTiO3 master pattern (package data, de-ebsd, 801 x 801)."""
    return master_patterns.master_pattern("BaTiO3", kind="dynamical")
