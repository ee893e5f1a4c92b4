"""Patterns: simulation from a master pattern in bounded memory, the phase
rule between a crystal map and a master pattern, and DIC between simulated
and experimental patterns (the paper's Eqs. 1-3).

Layer 3: may import :mod:`~kikuchipy_geomdic.geometry` and
:mod:`~kikuchipy_geomdic.io`.
"""

from kikuchipy_geomdic.patterns.displacement import DisplacementField, measure_displacements
from kikuchipy_geomdic.patterns.phases import check_phase
from kikuchipy_geomdic.patterns.simulation import simulate_patterns

__all__ = ["DisplacementField", "measure_displacements", "check_phase", "simulate_patterns"]
