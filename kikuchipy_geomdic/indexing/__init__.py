"""Orientations at a known geometry: the per-pattern Gauss-Newton kernel,
whole-map reindexing, pseudo-symmetric variants and domain labels.

Layer 4: may import :mod:`~kikuchipy_geomdic.geometry`,
:mod:`~kikuchipy_geomdic.io` and :mod:`~kikuchipy_geomdic.patterns`.
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
