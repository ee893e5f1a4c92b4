"""Orientations at a known geometry: the per-pattern Gauss-Newton kernel,
whole-map reindexing, pseudo-symmetric variants and domain labels.

The public names live in :mod:`~kikuchipy_geomdic.indexing.orientation`
(the solver, and the projection, misindexed points and variant comparison
it presents from private modules), :mod:`~kikuchipy_geomdic.indexing.reindex`
(the whole map) and :mod:`~kikuchipy_geomdic.indexing.variants` (operators
and domain labels).

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from kikuchipy_geomdic.indexing.orientation import compare_variants, refine_patterns
from kikuchipy_geomdic.indexing.reindex import refine_orientations, reindex
from kikuchipy_geomdic.indexing.variants import (
    VARIANT_NAMES,
    domain_labels,
    pseudo_symmetry_operators,
    variant_operators,
)

__all__ = [
    "compare_variants",
    "refine_patterns",
    "refine_orientations",
    "reindex",
    "VARIANT_NAMES",
    "domain_labels",
    "pseudo_symmetry_operators",
    "variant_operators",
]
