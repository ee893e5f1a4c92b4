"""Domain maps in absolute terms: each point's pseudo-symmetric variant in
the parent crystal's frame.

:func:`~kikuchipy_geomdic.indexing.reindex.reindex` with ``pseudo_symmetry_ops``
keeps, at every point, the variant its pattern shows, and numbers it
*relative to the point's start* (``variant`` 0: as given, k: operator
k - 1 applied). A map whose starts come in random variants (what an
indexer blind to BaTiO3's small tetragonality gives) then has a
``variant`` map that looks like noise even when every point is right.
:func:`domain_labels` gives each point its variant in one frame for the
whole map, the *parent* crystal's: for BaTiO3, the direction and polarity
of the point's c axis (its polarisation) along +-x, +-y or +-z of the
parent's pseudo-cubic frame, named as
:data:`~VARIANT_NAMES` and numbered as
:func:`~variant_operators`.

An orientation *g* is in variant *k* of a parent *p* when
``g = s * ops[k] * p`` (times a small scatter) for a rotation *s* of the
crystal's point group: operators and crystal symmetry act in the crystal
frame, on the left. The label is the *k* whose ideal orientations
``s * ops[k] * p`` are nearest *g*. Only the proper rotations of the
point group count, so that polarity stays visible: for BaTiO3 (4mm, no
inversion) they are the four rotations about c, which keep c, and
``+z`` and ``-z`` are different labels. A centrosymmetric group (4/mmm)
holds the 180 deg operator itself and is refused.

The quaternion arithmetic lives in ``_quaternions``.

Layer 4 (indexing): may import geometry, io, patterns and indexing.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from orix.crystal_map import CrystalMap
from orix.quaternion import Orientation, Rotation

from kikuchipy_geomdic.geometry.maps import _usable_rotations, check_whole_map, usable_points
from kikuchipy_geomdic.indexing._quaternions import _closure, _conj, _qmul
from kikuchipy_geomdic.patterns.phases import _phase_id

__all__ = [
    "VARIANT_NAMES",
    "variant_operators",
    "PSEUDO_SYMMETRY_NAMES",
    "DomainLabels",
    "domain_labels",
    "pseudo_symmetry_operators",
    "variant_names",
    "check_pseudo_symmetry",
]

#: BaTiO3's six ferroelectric variants as pseudo-symmetry operators (left
#: factors, ``op * rotation``): the c axis along +z, -z, +x, -x, +y, -y of
#: the pseudo-cubic frame (identity, 180 deg about [100], -90 and 90 deg
#: about [010], 90 and -90 deg about [100]).
VARIANT_NAMES = ("+z", "-z", "+x", "-x", "+y", "-y")


def variant_operators() -> Rotation:
    """Return the six BaTiO3 variant operators, identity first.

    Returns
    -------
    operators
        :class:`~orix.quaternion.Rotation` of shape (6,), in the order of
        :data:`VARIANT_NAMES`. ``operators[1:]`` is what kikuchipy's
        ``pseudo_symmetry_ops`` takes.

    Examples
    --------
    >>> import numpy as np
    >>> from orix.vector import Vector3d
    >>> from kikuchipy_geomdic.indexing.variants import variant_operators
    >>> c = ~variant_operators() * Vector3d.zvector()
    >>> np.round(c.data, 6).tolist()[:3]
    [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    """
    axes = [[1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0], [1, 0, 0]]
    angles = np.deg2rad([0, 180, -90, 90, 90, -90])
    return Rotation.from_axes_angles(axes, angles)


#: Materials whose pseudo-symmetry operators the package knows, for
#: :func:`pseudo_symmetry_operators` and the command line's
#: ``--pseudo-symmetry``.
PSEUDO_SYMMETRY_NAMES = ("BaTiO3",)

#: Default angular tolerance (deg) of the parent's robust mean: points
#: further than this from it (modulo the pseudo-symmetry) do not enter it.
TOLERANCE = 5.0

# Points per block of the label computation (bounded memory on big maps)
_BLOCK = 65536
# Points (evenly spread) the parent is chosen from on a larger map
_MAX_PARENT_POINTS = 200_000


def pseudo_symmetry_operators(spec: str | os.PathLike | Rotation | np.ndarray) -> Rotation:
    """Return pseudo-symmetry operators from a name, a file or quaternions.

    Parameters
    ----------
    spec
        A material the package knows (:data:`PSEUDO_SYMMETRY_NAMES`, any
        case: "BaTiO3" gives
        ``variant_operators()[1:]``), a ``.npy`` or text file
        (``.txt``, ``.csv``: whitespace- or comma-separated, ``#``
        comments) of an (n, 4) array of unit quaternions (a, b, c, d), or
        such an array or a :class:`~orix.quaternion.Rotation`. Operators
        act in the crystal frame, as ``op * rotation``, and leave out the
        identity (kikuchipy's ``pseudo_symmetry_ops``).

    Returns
    -------
    operators
        Flat :class:`~orix.quaternion.Rotation` of the n operators.

    Raises
    ------
    ValueError
        An unknown name, a missing or unreadable file, not an (n, 4)
        array, quaternions that are not finite or not of unit norm, or an
        identity operator.

    Examples
    --------
    >>> from kikuchipy_geomdic.indexing.variants import pseudo_symmetry_operators
    >>> pseudo_symmetry_operators("BaTiO3").size
    5
    >>> pseudo_symmetry_operators([[0, 1, 0, 0]]).data.tolist()
    [[0.0, 1.0, 0.0, 0.0]]
    """
    if isinstance(spec, Rotation):
        q, what = spec.flatten().data, "the operators"
    elif isinstance(spec, (str, os.PathLike)):
        known = {n.lower(): n for n in PSEUDO_SYMMETRY_NAMES}
        if str(spec).lower() in known:
            return variant_operators()[1:]
        q, what = _read_quaternions(Path(spec)), f"{str(spec)!r}"
    else:
        q, what = spec, "the operators"
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 1 and q.size == 4:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != 4 or q.shape[0] == 0:
        raise ValueError(
            f"{what} must hold an (n, 4) array of quaternions (a, b, c, d), one operator "
            f"a row, not an array of shape {q.shape}"
        )
    if not np.isfinite(q).all():
        raise ValueError(f"{what} hold(s) quaternions that are not finite")
    norm = np.linalg.norm(q, axis=1)
    if np.any(np.abs(norm - 1) > 1e-3):
        i = int(np.argmax(np.abs(norm - 1)))
        raise ValueError(
            f"{what}: quaternion {i} has norm {norm[i]:.4g}, not 1 (a rotation is a unit "
            "quaternion a, b, c, d)"
        )
    q = q / norm[:, None]
    ident = np.flatnonzero(np.abs(q[:, 0]) > 1 - 1e-9)
    if ident.size:
        raise ValueError(
            f"{what}: operator {int(ident[0])} is the identity; give the operators without "
            "it (every point's own variant is always tried), as kikuchipy's "
            "pseudo_symmetry_ops"
        )
    return Rotation(q)


def _read_quaternions(path: Path) -> np.ndarray:
    known = ", ".join(PSEUDO_SYMMETRY_NAMES)
    if not path.exists():
        raise ValueError(
            f"pseudo-symmetry {str(path)!r} is neither a known material ({known}) nor an "
            "existing .npy or .txt file of (n, 4) quaternions"
        )
    try:
        if path.suffix.lower() == ".npy":
            return np.load(path, allow_pickle=False)
        text = path.read_text().replace(",", " ")
        rows = [ln.split("#")[0].split() for ln in text.splitlines()]
        return np.array([[float(v) for v in r] for r in rows if r], dtype=np.float64)
    except (OSError, ValueError, UnicodeDecodeError) as e:
        msg = " ".join(str(e).split()) or type(e).__name__
        raise ValueError(
            f"cannot read pseudo-symmetry operators from {str(path)!r} (an .npy or text file "
            f"of an (n, 4) array of quaternions): {msg}"
        ) from None


@dataclass(frozen=True)
class DomainLabels:
    """Each point's variant in the parent crystal's frame.

    Attributes
    ----------
    label
        Integer array of the input's shape (a crystal map: flat, one per
        map point, as its properties): the variant index *k* (0: the
        parent's own, k: ``pseudo_symmetry_ops[k - 1]`` applied), -1 where
        not labelled (not indexed, another phase, unusable rotation).
    deviation
        Misorientation (deg) of each point from its variant's ideal
        orientation ``s * ops[k] * parent``; NaN where not labelled. A
        point tens of degrees off is misindexed, not in a variant.
    parent
        The parent orientation (a :class:`~orix.quaternion.Rotation` of
        one rotation) the labels refer to.
    names
        A name per variant index.
    chosen
        True when the parent was chosen from the map, False when given.
    """

    label: np.ndarray
    deviation: np.ndarray
    parent: Rotation
    names: tuple[str, ...]
    chosen: bool

    @property
    def counts(self) -> dict[str, int]:
        """Labelled points per variant name."""
        n = np.bincount(self.label[self.label >= 0].ravel(), minlength=len(self.names))
        return {name: int(c) for name, c in zip(self.names, n)}


def domain_labels(
    orientations: CrystalMap | Orientation | Rotation,
    pseudo_symmetry_ops: Rotation | np.ndarray | str | None = None,
    *,
    symmetry=None,
    parent: Rotation | np.ndarray | None = None,
    phase: str | int | None = None,
    points: np.ndarray | None = None,
    names: tuple[str, ...] | None = None,
    tolerance: float = TOLERANCE,
) -> DomainLabels:
    """Label every point with its variant in the parent crystal's frame.

    Parameters
    ----------
    orientations
        A :class:`~orix.crystal_map.CrystalMap` (its points of *phase*
        with usable rotations are labelled, with the phase's point group),
        an :class:`~orix.quaternion.Orientation` (with its symmetry) or a
        :class:`~orix.quaternion.Rotation` (with *symmetry*). Not
        modified.
    pseudo_symmetry_ops
        The variants' operators without the identity (crystal frame,
        ``op * rotation``), anything :func:`pseudo_symmetry_operators`
        takes; default BaTiO3's, ``variant_operators()[1:]``.
        With the crystal's proper rotations they must form a group (for
        BaTiO3: the six variants times the four rotations about c are
        the 24 rotations of the cubic parent).
    symmetry
        orix :class:`~orix.quaternion.Symmetry` (point group) of the
        crystal, overriding the map's or orientations'; required for a
        plain Rotation. Only its proper rotations are used (for 4mm: the
        four about c).
    parent
        The parent orientation (one rotation). Its own crystal-symmetry
        equivalents are different frames: for BaTiO3, turning it by 90 deg
        about c turns the labels +x into +y. Default: chosen from the
        map, as follows. A seed is the point with the most points within
        *tolerance* of it modulo the group the operators and the crystal
        symmetry generate (the mode of the map's orientation classes, on
        a subsample of at most 256 candidates against 4096 points; on a
        map of more than 200 000 points, from that many spread evenly); the
        parent is the mean quaternion of the points within *tolerance*
        of the seed, each reduced to its equivalent nearest it, iterated
        three times (a robust mean modulo the pseudo-symmetry). Of its
        equivalents, the parent is then the one that makes the most
        common variant variant 0 (for BaTiO3: the c axis of the largest
        domain is +z), and, of the remaining choices (the crystal's
        rotations of the parent), the one whose variant counts, in the
        operators' order, are largest first (for BaTiO3: the most common
        in-plane c axis is +x; -z is the 180 deg domain of the largest
        one). So the labels depend on the map only through which domains
        are largest, and a map of one dominant domain with 90 and 180
        deg domains is labelled as its true variants.
    phase
        Crystal maps: the name or id of the phase to label; default the
        map's only indexed phase.
    points
        Boolean mask (the input's shape, or flat for a crystal map): the
        points that choose the parent (e.g. ``converged == 1``); every
        usable point is labelled. Default: all.
    names
        A name per variant (``len(ops) + 1``); default
        :data:`~VARIANT_NAMES` for BaTiO3's
        operators, else "0", "1", ...
    tolerance
        Angle (deg) of the robust mean and of the seed's count.

    Returns
    -------
    labels
        :class:`DomainLabels`.

    Raises
    ------
    ValueError
        No point to label, no crystal symmetry, bad operators, operators
        equivalent to each other (or to the identity) under the crystal
        symmetry (for BaTiO3's 180 deg operator: a centrosymmetric point
        group such as 4/mmm, which cannot tell polarity), or operators
        that do not form a group with it.

    Examples
    --------
    A BaTiO3 stripe map: the true variants, recovered from orientations
    rotated by random 4mm equivalents (crystal symmetry) and a 2 deg
    common rotation:

    >>> import numpy as np
    >>> from orix.quaternion import Orientation, Rotation
    >>> from kikuchipy_geomdic.validation import synthetic
    >>> from kikuchipy_geomdic.indexing.variants import domain_labels
    >>> sm = synthetic.synthetic_map("BaTiO3", (6, 6), "stripes", shape=(20, 20), seed=1)
    >>> pg = sm.xmap.phases[0].point_group
    >>> s = Rotation(pg.proper_subgroup)[np.random.default_rng(0).integers(0, 4, 36)]
    >>> rot = s * sm.xmap.rotations * Rotation.from_axes_angles([1, 1, 0], np.deg2rad(2))
    >>> lab = domain_labels(Orientation(rot, symmetry=pg))
    >>> bool((lab.label == sm.xmap.prop["variant"]).all()), lab.counts["+z"]
    (True, 18)
    """
    rot, sym, usable = _inputs(orientations, symmetry, phase)
    shape = usable.shape
    ops = pseudo_symmetry_operators(
        "BaTiO3" if pseudo_symmetry_ops is None else pseudo_symmetry_ops
    )
    n_var = ops.size + 1
    names = variant_names(ops) if names is None else tuple(str(n) for n in names)
    if len(names) != n_var:
        raise ValueError(f"{len(names)} names for {n_var} variants (the operators and identity)")
    h, group = _variant_table(ops, sym)

    q = rot.data.reshape(-1, 4)
    ok = usable.ravel()
    if not ok.any():
        raise ValueError("No point to label: none indexed with a usable rotation")
    if parent is None:
        use = ok.copy()
        if points is not None:
            mask = np.asarray(points, dtype=bool).ravel()
            if mask.size != ok.size:
                raise ValueError(f"points has {mask.size} entries, the orientations {ok.size}")
            use &= mask
        if not use.any():
            raise ValueError("No point to choose the parent from (points selects none usable)")
        p = _choose_parent(q[use], h, group, np.deg2rad(tolerance))
        chosen = True
    else:
        p = np.asarray(Rotation(parent).flatten().data, dtype=np.float64)
        if p.shape != (1, 4):
            raise ValueError(f"parent must be one rotation, not {p.shape[0]}")
        p = p[0] / np.linalg.norm(p[0])
        chosen = False
    label = np.full(ok.size, -1, dtype=np.int64)
    deviation = np.full(ok.size, np.nan)
    idx = np.flatnonzero(ok)
    label[idx], deviation[idx] = _label(q[idx], p, h)
    return DomainLabels(
        label=label.reshape(shape),
        deviation=np.rad2deg(deviation).reshape(shape),
        parent=Rotation(p),
        names=names,
        chosen=chosen,
    )


def variant_names(pseudo_symmetry_ops) -> tuple[str, ...]:
    """Return a name per variant: the identity's, then each operator's.

    Parameters
    ----------
    pseudo_symmetry_ops
        Operators without the identity (anything
        :func:`pseudo_symmetry_operators` takes).

    Returns
    -------
    names
        :data:`~VARIANT_NAMES` (the c axis
        in the parent frame) for BaTiO3's operators, else "0", "1", ...

    Examples
    --------
    >>> from kikuchipy_geomdic.indexing.variants import variant_names
    >>> variant_names("BaTiO3")
    ('+z', '-z', '+x', '-x', '+y', '-y')
    >>> variant_names([[0, 1, 0, 0]])
    ('0', '1')
    """

    q = pseudo_symmetry_operators(pseudo_symmetry_ops).data
    known = variant_operators().data[1:]
    if q.shape == known.shape and np.allclose(np.abs((q * known).sum(axis=1)), 1):
        return tuple(VARIANT_NAMES)
    return tuple(str(k) for k in range(len(q) + 1))


def check_pseudo_symmetry(pseudo_symmetry_ops, symmetry) -> None:
    """Check that operators describe distinct variants of a crystal.

    Parameters
    ----------
    pseudo_symmetry_ops, symmetry
        The operators, as :func:`variant_names` takes them, and the orix
        point group of the crystal (e.g. ``phase.point_group``).

    Raises
    ------
    ValueError
        Operators equivalent to each other or to the identity under the
        crystal's rotations (a centrosymmetric point group cannot tell
        BaTiO3's polarity; operators for another crystal system), or
        operators that do not form a group with them.

    Examples
    --------
    >>> from orix.quaternion import symmetry
    >>> from kikuchipy_geomdic.indexing.variants import check_pseudo_symmetry
    >>> check_pseudo_symmetry("BaTiO3", symmetry.C4v)
    >>> check_pseudo_symmetry("BaTiO3", symmetry.Oh)
    Traceback (most recent call last):
    ...
    ValueError: pseudo-symmetry operator 0 is the identity times a rotation of point group m-3m...
    """
    _variant_table(pseudo_symmetry_operators(pseudo_symmetry_ops), symmetry)


def _variant_table(ops: Rotation, symmetry):
    """``s * ops[k]`` (m, K + 1, 4) for the crystal's rotations s and the
    operators with the identity first, and the group they form, checked."""
    variants = np.concatenate([[[1.0, 0.0, 0.0, 0.0]], ops.data])
    s = _proper_rotations(_need(symmetry))
    h = _qmul(s[:, None, :], variants[None, :, :])
    _check_cosets(h, ops, symmetry)
    group = _closure(h.reshape(-1, 4))
    if group.shape[0] != h.shape[0] * h.shape[1]:
        raise ValueError(
            f"the {ops.size} pseudo-symmetry operators with the crystal's {s.shape[0]} "
            f"rotations do not form a group (they generate {group.shape[0]} rotations, not "
            f"{h.shape[0] * h.shape[1]}): give every variant's operator"
        )
    return h, group


def _inputs(orientations, symmetry, phase):
    """Rotations, symmetry and usable mask (the input's shape)."""
    if isinstance(orientations, CrystalMap):
        check_whole_map(orientations)
        if phase is None:
            ids = [int(i) for i in np.unique(orientations.phase_id) if i >= 0]
            if len(ids) != 1:
                raise ValueError(
                    "No point to label: the crystal map has no indexed points"
                    if not ids
                    else f"The crystal map has several phases "
                    f"{[orientations.phases[i].name for i in ids]}: choose one (phase=...)"
                )
            pid = ids[0]
        else:
            pid = _phase_id(orientations, phase)
        usable = usable_points(orientations, pid).ravel()
        if symmetry is None:
            symmetry = orientations.phases[pid].point_group
        rot = Rotation(orientations.rotations.data.reshape(-1, 4))
        return rot, _need(symmetry), usable
    if isinstance(orientations, Orientation) and symmetry is None:
        symmetry = orientations.symmetry
    if not isinstance(orientations, Rotation):
        raise TypeError(
            "orientations must be an orix CrystalMap, Orientation or Rotation, not "
            f"{type(orientations).__name__}"
        )
    q = orientations.data
    return Rotation(q), _need(symmetry), _usable_rotations(q)


def _need(symmetry):
    if symmetry is None:
        raise ValueError(
            "The crystal symmetry is needed (symmetry=, e.g. the phase's point_group): "
            "equivalent orientations must get the same label"
        )
    return symmetry


def _proper_rotations(symmetry) -> np.ndarray:
    """The point group's proper rotations as quaternions (m, 4)."""
    sub = getattr(symmetry, "proper_subgroup", symmetry)
    q = np.asarray(Rotation(sub).flatten().data, dtype=np.float64)
    improper = getattr(sub, "improper", np.zeros(len(q), dtype=bool))
    return q[~np.asarray(improper, dtype=bool).ravel()]


def _check_cosets(h: np.ndarray, ops: Rotation, symmetry) -> None:
    """Each operator must be a distinct variant under the crystal symmetry."""
    first = h[0]  # (K + 1, 4): identity * ops[k]
    for k in range(1, h.shape[1]):
        # Variant k equals variant j if ops[k] = s * ops[j]
        d = np.abs(np.einsum("mjq,q->mj", h[:, :k], first[k]))
        same = np.flatnonzero((d > 1 - 1e-9).any(axis=0))
        if same.size:
            j = int(same[0])
            pg = getattr(symmetry, "name", "the crystal's")
            what = "the identity" if j == 0 else f"operator {j - 1}"
            raise ValueError(
                f"pseudo-symmetry operator {k - 1} is {what} times a rotation of point group "
                f"{pg}: both give the same variant, so they are not pseudo-symmetries of this "
                "crystal (BaTiO3's need its polar point group 4mm: 4/mmm cannot tell polarity)"
            )


def _nearest(q: np.ndarray, ref: np.ndarray, group: np.ndarray):
    """For each rotation g of *q*: the element h of *group* with g ~ h * ref
    (largest |<g * ~ref, h>|), and that |dot|."""
    out_h = np.empty(len(q), dtype=np.int64)
    out_d = np.empty(len(q))
    for i in range(0, len(q), _BLOCK):
        r = _qmul(q[i : i + _BLOCK], _conj(ref))
        d = np.abs(r @ group.T)
        out_h[i : i + _BLOCK] = d.argmax(axis=1)
        out_d[i : i + _BLOCK] = d.max(axis=1)
    return out_h, out_d


def _label(q: np.ndarray, parent: np.ndarray, h: np.ndarray):
    """Variant index and deviation (rad) of each rotation from *parent*."""
    m, k = h.shape[:2]
    idx, dot = _nearest(q, parent, h.reshape(-1, 4))
    return idx % k, 2 * np.arccos(np.clip(dot, 0.0, 1.0))


def _reduced_mean(q: np.ndarray, ref: np.ndarray, group: np.ndarray, tol: float):
    """Mean quaternion of the points within *tol* of *ref* modulo *group*,
    each reduced to its equivalent nearest *ref*; *ref* if none."""
    idx, dot = _nearest(q, ref, group)
    near = 2 * np.arccos(np.clip(dot, 0.0, 1.0)) <= tol
    if not near.any():
        return ref
    # g = h * ref  ->  ~h * g is ref's equivalent of g
    red = _qmul(_conj(group[idx[near]]), q[near])
    red *= np.sign(red @ ref)[:, None] + (red @ ref == 0)[:, None]
    mean = red.sum(axis=0)
    return mean / np.linalg.norm(mean)


def _choose_parent(q: np.ndarray, h: np.ndarray, group: np.ndarray, tol: float) -> np.ndarray:
    """The parent orientation of a map (see :func:`domain_labels`)."""
    if len(q) > _MAX_PARENT_POINTS:  # evenly spread over the map
        q = q[np.linspace(0, len(q) - 1, _MAX_PARENT_POINTS).astype(int)]
    n = len(q)
    cand = q[np.unique(np.linspace(0, n - 1, min(n, 256)).astype(int))]
    sample = q[np.unique(np.linspace(0, n - 1, min(n, 4096)).astype(int))]
    counts = [(_nearest(sample, c, group)[1] >= np.cos(tol / 2)).sum() for c in cand]
    p = cand[int(np.argmax(counts))]
    for _ in range(3):
        p = _reduced_mean(q, p, group, tol)
    m, k = h.shape[:2]
    # The most common variant becomes variant 0: g ~ s * ops[k] * p means
    # g ~ s * p' with p' = ops[k] * p
    label, _ = _label(q, p, h)
    top = int(np.argmax(np.bincount(label, minlength=k)))
    p = _qmul(h[0, top], p)
    # Of the crystal's rotations of it, the one whose variant counts are
    # largest first in the operators' order
    best, best_counts = p, None
    for s in h[:, 0]:
        ps = _qmul(s, p)
        c = tuple(np.bincount(_label(q, ps, h)[0], minlength=k)[1:].tolist())
        if best_counts is None or c > best_counts:
            best, best_counts = ps, c
    # Its robust mean over its own variant (reduced by the crystal symmetry)
    return _reduced_mean(q, best, h[:, 0], tol)
