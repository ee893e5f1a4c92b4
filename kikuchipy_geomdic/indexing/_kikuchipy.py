"""kikuchipy's route: a map or a stack of patterns refined by kikuchipy's
:meth:`~kikuchipy.signals.EBSD.refine_orientation`, quietly
(``method="kikuchipy"`` of
:func:`~kikuchipy_geomdic.indexing.reindex.reindex`, and the stacks of
the calibration). The public names are presented by
:mod:`~kikuchipy_geomdic.indexing.reindex`.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import contextlib
import io
from typing import Any

import numpy as np
from kikuchipy.detectors import EBSDDetector
from kikuchipy.signals import EBSD, EBSDMasterPattern
from orix.crystal_map import CrystalMap, PhaseList
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import copy_detector
from kikuchipy_geomdic.indexing._map_output import _merge
from kikuchipy_geomdic.patterns.preprocessing import bin_pattern


def _reindex_kikuchipy(
    signal, xmap, detector, master_pattern, energy, todo, phase_id, mp_phase, show, kwargs
):
    """:func:`reindex` by kikuchipy's ``refine_orientation``."""
    nav = tuple(signal.axes_manager.navigation_shape[::-1])
    kwargs = dict(kwargs)
    if "kikuchipy_method" in kwargs:
        kwargs["method"] = kwargs.pop("kikuchipy_method")
    # What kikuchipy sees: one phase (the master pattern's), the points to
    # refine indexed, every other point not indexed
    q_in = xmap.rotations.data.reshape(-1, 4)
    flat = todo.ravel()
    q = np.tile([1.0, 0.0, 0.0, 0.0], (flat.size, 1))
    q[flat] = q_in[flat]
    kx = CrystalMap(
        rotations=Rotation(q),
        phase_id=np.where(flat, 0, -1),
        x=xmap.x,
        y=xmap.y,
        phase_list=PhaseList({0: mp_phase}),
        scan_unit=xmap.scan_unit,
    )
    det = detector.deepcopy()
    if det.navigation_size > 1 and det.navigation_shape != nav:
        det.pc = det.pc.reshape(nav + (3,))
    with contextlib.nullcontext() if show else quiet():
        ref = signal.refine_orientation(kx, det, master_pattern, energy, **kwargs)

    n = flat.size
    done = np.zeros(n, dtype=bool)
    done[ref.id] = True
    done &= flat
    scores = np.zeros(n)
    scores[ref.id] = ref.prop["scores"]
    bad = done & ~np.isfinite(scores)
    done &= ~bad
    scores[~done] = 0.0
    num_evals = np.zeros(n, dtype=np.int64)
    num_evals[ref.id] = ref.prop["num_evals"]
    q_out = xmap.rotations.data.reshape(-1, 4).copy()
    q_out[done] = ref.rotations.data.reshape(-1, 4)[np.searchsorted(ref.id, np.flatnonzero(done))]
    prop = {"scores": scores, "num_evals": num_evals}
    if "pseudo_symmetry_index" in ref.prop:
        psi = np.zeros(n, dtype=np.int64)
        psi[ref.id] = ref.prop["pseudo_symmetry_index"]
        prop["pseudo_symmetry_index"] = psi
    return _merge(xmap, q_out, done, bad, prop, phase_id, mp_phase)


def refine_orientations(
    patterns: np.ndarray,
    rotations: Rotation,
    detector: EBSDDetector,
    master_pattern: EBSDMasterPattern,
    energy: float,
    phase,
    binning: int = 1,
    **refine_kwargs: Any,
) -> CrystalMap:
    """Refine the orientations of a stack of patterns, quietly.

    A stack (the calibration points of a map, say) is refined with
    kikuchipy's :meth:`~kikuchipy.signals.EBSD.refine_orientation` as a
    1D map, without kikuchipy's summary and progress bar.

    Parameters
    ----------
    patterns
        Patterns (N, rows, columns).
    rotations
        Starting orientations (N,).
    detector
        Detector of the full-resolution patterns with one PC or N PCs.
    master_pattern, energy
        Lambert master pattern of *phase* and beam energy in kV.
    phase
        orix :class:`~orix.crystal_map.Phase` of the patterns.
    binning
        Refine on patterns binned by this factor, which must divide the
        pattern shape (the PC fractions stay the same).
    **refine_kwargs
        Passed to :meth:`~kikuchipy.signals.EBSD.refine_orientation`.

    Returns
    -------
    xmap
        1D :class:`~orix.crystal_map.CrystalMap` of the N refined
        orientations with their ``scores``.

    Examples
    --------
    The four patterns of a 2 x 2 synthetic map, refined at their true
    PCs:

    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.indexing.reindex import refine_orientations
    >>> sm = synthetic.synthetic_map("Si", (2, 2), shape=(40, 40), seed=0)
    >>> patterns, mp = sm.signal.data.reshape(4, 40, 40), sm.master_pattern
    >>> det = sm.geometry.detector([[0, 0], [0, 1], [1, 0], [1, 1]])
    >>> xmap = refine_orientations(patterns, sm.start_xmap.rotations, det, mp, 20, mp.phase)
    >>> len(xmap.scores), bool(xmap.scores.min() > 0.99)
    (4, True)
    """
    patterns = np.asarray(patterns)
    if binning > 1:
        # Averaged in the patterns' own floating type, as kikuchipy would
        patterns = bin_pattern(patterns, binning, np.result_type(patterns.dtype, np.float32))
        detector = copy_detector(
            detector, shape=patterns.shape[1:], binning=detector.binning * binning
        )
    signal, xmap = stack_signal(patterns, rotations, phase)
    with quiet():
        return signal.refine_orientation(xmap, detector, master_pattern, energy, **refine_kwargs)


def stack_signal(patterns: np.ndarray, rotations: Rotation, phase) -> tuple[EBSD, CrystalMap]:
    """Return a stack of patterns as a 1D map and a crystal map of it.

    Parameters
    ----------
    patterns
        Patterns (N, rows, columns).
    rotations
        Orientations (N,).
    phase
        orix :class:`~orix.crystal_map.Phase` of every point.

    Returns
    -------
    signal
        :class:`~kikuchipy.signals.EBSD` with one navigation axis "x".
    xmap
        :class:`~orix.crystal_map.CrystalMap` with points at x = 0, 1, ...
    """
    n = len(patterns)
    signal = EBSD(patterns)
    # kikuchipy matches the crystal map's x coordinates to this axis
    signal.axes_manager.navigation_axes[0].name = "x"
    xmap = CrystalMap(
        rotations=rotations, x=np.arange(n, dtype=float), phase_list=PhaseList(phase)
    )
    return signal, xmap


def quiet():
    """Return a context in which kikuchipy's summaries and progress bars,
    which go to stdout, are not shown.

    Examples
    --------
    >>> from kikuchipy_geomdic.indexing.reindex import quiet
    >>> with quiet():
    ...     print("not shown")
    """
    return contextlib.redirect_stdout(io.StringIO())
