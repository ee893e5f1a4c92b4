"""Pattern simulation from a master pattern, in bounded memory.

kikuchipy's :meth:`~kikuchipy.signals.EBSDMasterPattern.get_patterns`
builds the direction cosines of every pattern eagerly in float64 when the
detector has one PC per pattern (13.8 GB for 100 x 100 patterns of
240 x 240). Here the patterns are projected chunk by chunk so that memory
stays bounded by *max_bytes*.

Layer 3 (patterns): may import geometry, io, patterns.
"""

from __future__ import annotations

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSDMasterPattern
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import copy_detector

__all__ = ["check_master_pattern", "simulate_patterns"]

#: Memory budget for direction cosines of one chunk.
MAX_BYTES = 256 * 2**20


def check_master_pattern(master_pattern: EBSDMasterPattern) -> None:
    """Raise a clear error if *master_pattern* cannot be projected.

    Parameters
    ----------
    master_pattern
        Must be an :class:`~kikuchipy.signals.EBSDMasterPattern` in the
        Lambert projection, both hemispheres or the upper one.

    Raises
    ------
    TypeError, ValueError
    """
    if not isinstance(master_pattern, EBSDMasterPattern):
        raise TypeError(
            f"master_pattern must be a kikuchipy EBSDMasterPattern, not "
            f"{type(master_pattern).__name__}"
        )
    if master_pattern.projection != "lambert":
        raise ValueError(
            f"master_pattern is in the {master_pattern.projection!r} projection; "
            "a 'lambert' master pattern is required (convert with as_lambert())"
        )


def simulate_patterns(
    master_pattern: EBSDMasterPattern,
    rotations: Rotation,
    detector: EBSDDetector,
    energy: float,
    max_bytes: int = MAX_BYTES,
) -> np.ndarray:
    """Return simulated patterns as a float32 array.

    Parameters
    ----------
    master_pattern
        Lambert master pattern.
    rotations
        *n* crystal rotations (any shape; flattened).
    detector
        Detector with one PC or *n* PCs (any navigation shape of size n).
    energy
        Beam energy in kV, selecting the master pattern's energy slice.
    max_bytes
        Upper bound on the direction-cosine memory of one chunk.

    Returns
    -------
    patterns
        Array of shape (n, rows, columns), float32, with kikuchipy's
        intensities (not rescaled).

    Examples
    --------
    Three points of a map, one PC each, from kikuchipy's EMsoft nickel
    master pattern; chunks of one pattern give the same patterns:

    >>> import kikuchipy as kp
    >>> import numpy as np
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.geometry import MapGeometry
    >>> from kikuchipy_geomdic.patterns.simulation import simulate_patterns
    >>> mp = kp.data.nickel_ebsd_master_pattern_small(projection="lambert", hemisphere="both")
    >>> geo = MapGeometry((0.5, 0.3, 0.6), (30, 40), 70, 8, (50, 50), (3, 3))
    >>> det = geo.detector([[0, 0], [1, 1], [2, 2]])
    >>> whole = simulate_patterns(mp, Rotation.identity(3), det, 20)
    >>> whole.shape, whole.dtype.name
    ((3, 30, 40), 'float32')
    >>> np.array_equal(whole, simulate_patterns(mp, Rotation.identity(3), det, 20, max_bytes=1))
    True
    """
    check_master_pattern(master_pattern)
    rotations = rotations.flatten()
    n = rotations.size
    pcs = detector.pc.reshape(-1, 3)
    if pcs.shape[0] not in (1, n):
        raise ValueError(
            f"The detector has {pcs.shape[0]} PCs for {n} rotations; give one PC "
            "or one per rotation"
        )
    out = np.empty((n,) + tuple(detector.shape), dtype=np.float32)
    if n == 0:
        return out
    # kikuchipy builds float64 direction cosines of (chunk, pixels, 3)
    chunk = max(1, int(max_bytes // (detector.size * 3 * 8)))
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        pc = pcs if pcs.shape[0] == 1 else pcs[start:stop]
        det = copy_detector(detector, pc=pc)
        sim = master_pattern.get_patterns(
            rotations[start:stop],
            det,
            energy,
            dtype_out=np.float32,
            compute=False,
            show_progressbar=False,
        )
        # compute=True stores into a local NumPy array that a
        # dask.distributed cluster never fills (kikuchipy 0.13.1)
        data = np.asarray(sim.data.compute(scheduler="threads"))
        out[start:stop] = data.reshape((stop - start,) + tuple(detector.shape))
    return out
