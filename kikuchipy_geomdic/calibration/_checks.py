"""The checks of :func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`'s
inputs, before any pattern is read.

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap

from kikuchipy_geomdic.geometry import DEFAULT_STEPS, check_parameters
from kikuchipy_geomdic.geometry.maps import check_signal_and_detector, navigation_shape
from kikuchipy_geomdic.indexing.phases_to_refine import phases_to_refine
from kikuchipy_geomdic.patterns.simulation import check_master_pattern


def _check_inputs(signal, xmap, detector, master_pattern, phase, nav, ops=None, energy=None):
    """Check the inputs; return the phases to refine (:class:`PhaseToRefine`)."""
    check_signal_and_detector(signal, detector)
    if not isinstance(xmap, CrystalMap):
        raise TypeError(f"xmap must be an orix CrystalMap, not {type(xmap).__name__}")
    one = isinstance(master_pattern, EBSDMasterPattern)
    for mp in [master_pattern] if one else master_pattern:
        check_master_pattern(mp)
    if len(xmap.shape) > 2 or navigation_shape(xmap) != nav or xmap.size != nav[0] * nav[1]:
        raise ValueError(
            f"xmap shape {xmap.shape} (with {xmap.size} points) does not match the "
            f"signal's navigation shape {nav}"
        )
    if tuple(detector.shape) != tuple(signal.axes_manager.signal_shape[::-1]):
        raise ValueError(
            f"detector shape {detector.shape} differs from the pattern shape "
            f"{signal.axes_manager.signal_shape[::-1]}"
        )
    n_pc = detector.pc.reshape(-1, 3).shape[0]
    if n_pc not in (1, nav[0] * nav[1]):
        raise ValueError(
            f"The detector has {n_pc} PCs, which fits neither one PC nor the "
            f"signal's {nav[0] * nav[1]} map points"
        )
    return phases_to_refine(xmap, master_pattern, phase, ops, energy)


def _check_steps(names: Sequence[str], steps: Mapping[str, float] | None) -> dict[str, float]:
    """Central-difference steps of the refined parameters: the defaults
    updated by *steps*, all positive."""
    step_all = dict(DEFAULT_STEPS)
    if steps:
        check_parameters(list(steps))
        step_all.update({k: float(v) for k, v in steps.items()})
    if any(step_all[n] <= 0 for n in names):
        raise ValueError("Finite-difference steps must be positive")
    return {n: step_all[n] for n in names}


def _step_sizes(signal: EBSD) -> tuple[float, float]:
    axes = signal.axes_manager.navigation_axes
    if len(axes) == 2:
        dx, dy = axes[0].scale, axes[1].scale
    else:
        dx = axes[0].scale
        dy = dx
    return float(dy), float(dx)
