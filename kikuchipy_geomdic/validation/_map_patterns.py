"""The patterns of a synthetic map, simulated chunk by chunk, and the
"indexed" start refined on them.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

import dask.array as da
import numpy as np
from kikuchipy.signals import EBSD, LazyEBSD
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import copy_detector
from kikuchipy_geomdic.indexing.reindex import quiet
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation.camera import camera_counts, degrade_patterns


def _signal(simulator, rot, detector, geometry, energy, noise, labels, lazy) -> EBSD:
    """The map's patterns as a signal; *noise* holds the arguments of
    :func:`degrade_patterns`, or a camera and a seed."""
    nav = geometry.navigation_shape
    camera = noise.get("camera")
    brightness = _brightness(camera, noise.get("seed"), labels)
    data = _simulate_map(
        simulator, rot.data.reshape(nav + (4,)), detector.pc, geometry, energy, noise, brightness
    )
    axes = _axes(geometry)
    if lazy:
        signal = LazyEBSD(data, axes=axes)
    else:
        signal = EBSD(data.compute(scheduler="threads"), axes=axes)
    if camera is not None:
        camera.process(signal)
    return signal


def _brightness(camera, seed, labels: np.ndarray) -> np.ndarray:
    """Each point's brightness (N,): one uniform draw per grain of *labels*
    scaled by the *camera*'s brightness variation, or ones without one."""
    if camera is None:
        return np.ones(labels.size)
    draws = np.random.default_rng([seed, 1]).uniform(-1, 1, int(labels.max()) + 1)
    return 1 + camera.brightness * draws[labels]


def _axes(geometry) -> list[dict]:
    """The axes of a map's signal: navigation in um, the detector in px."""
    nav, (dy, dx) = geometry.navigation_shape, geometry.step_sizes
    return [
        {"name": "y", "size": nav[0], "scale": dy, "units": "um"},
        {"name": "x", "size": nav[1], "scale": dx, "units": "um"},
        {"name": "dy", "size": geometry.shape[0], "scale": 1, "units": "px"},
        {"name": "dx", "size": geometry.shape[1], "scale": 1, "units": "px"},
    ]


def _refine_orientations(signal, xmap, detector, master_pattern, energy) -> Rotation:
    # kikuchipy's orientation refinement at fixed (per-point) PCs, as a
    # user would run it after indexing at the nominal geometry: default
    # method (SciPy Nelder-Mead) and no trust region, because with a trust
    # region SciPy builds the first simplex from 5 % of each start value,
    # clipped to the bounds, and stalls on orientations with a small Euler
    # angle (Phi near 2 deg). It builds a dask graph over the signal's
    # chunks, so a lazy signal is simulated chunk by chunk
    with quiet():
        refined = signal.refine_orientation(xmap, detector, master_pattern, energy)
    return refined.rotations.flatten()


def _simulate_map(master_pattern, quats, pcs, geometry, energy, degrade, brightness) -> da.Array:
    nav = quats.shape[:2]
    sig = tuple(geometry.shape)
    # Rows of patterns per chunk: about 32 MiB of float32 output each
    rows_per_chunk = max(1, int(32 * 2**20 // (4 * nav[1] * sig[0] * sig[1])))
    chunks = (min(rows_per_chunk, nav[0]), nav[1])
    q = da.from_array(quats, chunks=chunks + (4,))
    p = da.from_array(pcs, chunks=chunks + (3,))
    b = da.from_array(brightness.reshape(nav + (1,)), chunks=chunks + (1,))
    camera = degrade.get("camera")
    return da.map_blocks(
        _simulate_block,
        q,
        p,
        b,
        master_pattern=master_pattern,
        template=geometry.detector(points=[[0, 0]]),
        energy=energy,
        degrade=degrade,
        nav_cols=nav[1],
        dtype=np.float32 if camera is None else np.uint16,
        chunks=q.chunks[:2] + ((sig[0],), (sig[1],)),
        drop_axis=2,
        new_axis=[2, 3],
    )


def _simulate_block(q, p, b, master_pattern, template, energy, degrade, nav_cols, block_info=None):
    shape = q.shape[:2]
    det = copy_detector(template, pc=p.reshape(-1, 3))
    patterns = simulate_patterns(master_pattern, Rotation(q.reshape(-1, 4)), det, energy)
    # Flat map indices so that noise does not depend on the chunking
    (r0, _), (c0, _) = block_info[0]["array-location"][:2]
    rows, cols = np.indices(shape)
    flat = ((rows + r0) * nav_cols + cols + c0).ravel()
    degrade = dict(degrade)
    camera = degrade.pop("camera", None)
    if camera is None:
        out = degrade_patterns(patterns, index=flat, **degrade)
    else:
        out = camera_counts(patterns, p.reshape(-1, 3), camera, b.ravel(), degrade["seed"], flat)
    return out.reshape(shape + patterns.shape[1:])
