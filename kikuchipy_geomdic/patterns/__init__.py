"""Patterns: simulation from a master pattern in bounded memory, the phase
rule between a crystal map and a master pattern, and DIC between simulated
and experimental patterns (the paper's Eqs. 1-3): the ROI grid
(:mod:`~kikuchipy_geomdic.patterns.roi`), preprocessing
(:mod:`~kikuchipy_geomdic.patterns.preprocessing`), the vectors of one
pattern pair (:mod:`~kikuchipy_geomdic.patterns.vectors`) and the field of
many (:mod:`~kikuchipy_geomdic.patterns.displacement`).

Layer 3 (patterns): may import geometry, io, patterns.
"""

from kikuchipy_geomdic.patterns.displacement import DisplacementField, measure_displacements
from kikuchipy_geomdic.patterns.phases import check_phase
from kikuchipy_geomdic.patterns.simulation import simulate_patterns

__all__ = ["DisplacementField", "measure_displacements", "check_phase", "simulate_patterns"]
