"""Validation against a known truth: synthetic maps made the way a camera
and a user make them (two-phase maps too), the paper's perturbation study,
and the comparison with kikuchipy's refiners.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from kikuchipy_geomdic.validation.camera import Camera
from kikuchipy_geomdic.validation.comparison import compare_methods
from kikuchipy_geomdic.validation.multiphase import two_phase_map
from kikuchipy_geomdic.validation.study import perturbation_study
from kikuchipy_geomdic.validation.synthetic import synthetic_map

__all__ = ["compare_methods", "perturbation_study", "Camera", "synthetic_map", "two_phase_map"]
