"""The refined map as a crystal map: refined points put back into a copy
of the input map, the domain labels of a pseudo-symmetric reindexing,
and the flag on isolated variant calls; both methods of
:func:`~kikuchipy_geomdic.indexing.reindex.reindex` end here.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import warnings

import numpy as np
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry.maps import _usable_rotations
from kikuchipy_geomdic.indexing.variants import domain_labels
from kikuchipy_geomdic.patterns.phases import map_with_phase


def _merge(xmap, q_out, done, bad, prop, phase_id, mp_phase) -> CrystalMap:
    """The refined points (*done*) of *q_out* put back into a copy of
    *xmap* with properties *prop*; *bad* points (NaN patterns) are not
    indexed."""
    q = xmap.rotations.data.reshape(-1, 4).copy()
    q[done] = np.asarray(q_out).reshape(-1, 4)[done]
    pid = xmap.phase_id.copy()
    # Points with an invalid rotation (any phase) or a NaN pattern are not
    # indexed; masked-out points and other phases keep theirs
    lost = bad | ~_usable_rotations(q)
    pid[lost] = -1
    q[lost] = [1.0, 0.0, 0.0, 0.0]
    props = {k: np.asarray(v).copy() for k, v in xmap.prop.items()}
    props.update(prop)
    props["refined"] = done.astype(np.int8)
    return map_with_phase(xmap, Rotation(q), pid, props, phase_id, mp_phase)


def _with_domain(xmap: CrystalMap, ops, phase_id: int) -> CrystalMap:
    """Add property ``domain`` (:func:`~kikuchipy_geomdic.indexing.variants.domain_labels`,
    the parent chosen from the refined, converged points) to a fresh map."""
    if ops is None:
        return xmap
    trusted = xmap.prop["refined"].astype(bool) & (xmap.prop.get("converged", 1) != 0)
    try:
        lab = domain_labels(xmap, ops, phase=phase_id, points=trusted if trusted.any() else None)
    except ValueError as e:  # operators that do not make a group with the crystal's
        warnings.warn(f"No domain labels: {e}", UserWarning, stacklevel=3)
        return xmap
    xmap.prop["domain"] = lab.label.astype(np.int64)
    return xmap


def _flag_isolated(xmap: CrystalMap) -> None:
    """Give ``converged`` = 0 to every trusted point whose domain none of
    its trusted neighbours (8-connected, at least two of them) shares, in
    place, and add property ``isolated_variant`` (1 there).

    A detector angle error biases polarity calls beyond their noise
    (measured: two +z points of a 13 x 13 map at 30 counts per pixel
    called -z with significances 3.4 and 3.6, at an azimuthal angle 1 deg
    off); such errors are scattered points, while domains span several
    steps. A true domain one step wide is flagged too: it is not declared
    wrong, only not trusted."""
    shape = xmap.shape if len(xmap.shape) == 2 else (1, xmap.size)
    dom = np.asarray(xmap.prop["domain"]).reshape(shape)
    conv = np.asarray(xmap.prop["converged"]).reshape(shape).astype(bool)
    trusted = conv & (dom >= 0)
    n_trusted = np.zeros(shape, dtype=int)
    n_same = np.zeros(shape, dtype=int)
    rows, cols = shape
    pad_t = np.pad(trusted, 1)
    pad_d = np.pad(dom, 1, constant_values=-1)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == dc == 0:
                continue
            t = pad_t[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
            d = pad_d[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
            n_trusted += t
            n_same += t & (d == dom)
    isolated = (trusted & (n_trusted >= ISOLATED_NEIGHBOURS) & (n_same == 0)).ravel()
    xmap.prop["converged"] = np.where(isolated, 0, xmap.prop["converged"]).astype(np.int8)
    xmap.prop["isolated_variant"] = isolated.astype(np.int8)


#: Trusted neighbours a trusted point needs, none of them in its domain,
#: for :func:`reindex` to flag it as an isolated variant call
ISOLATED_NEIGHBOURS = 2
