"""Orientations of synthetic maps, their starts, and the common part of a
start's error.

The true orientations of :func:`~kikuchipy_geomdic.validation.synthetic.synthetic_map`
are random, a single crystal, grains or BaTiO3-like domains of variants;
the starting ones are the truth times small random rotations
(:func:`perturb_rotations`), centred or not. :func:`common_rotation`
measures the mean deviation of a start from the truth: what no
calibration can tell from a change of the detector angles.

Layer 7 (validation): may import geometry, io, patterns, indexing, plotting, calibration.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from orix.crystal_map import CrystalMap
from orix.quaternion import Rotation

from kikuchipy_geomdic.geometry import rotation_vectors, rotations_from_vectors
from kikuchipy_geomdic.indexing.variants import variant_operators

__all__ = [
    "STRIPE_VARIANTS",
    "GRAIN_POINTS",
    "perturb_rotations",
    "CommonRotation",
    "common_rotation",
]

#: Variants (indices into
#: :func:`~kikuchipy_geomdic.indexing.variants.variant_operators`) of the diagonal
#: stripes of ``synthetic_map(orientations="stripes")``, in order: the
#: parent (+z) between a 90 deg domain (c along +x) and a 180 deg one
#: (-z), so that the map has both kinds of domain wall and the parent
#: covers about half of it.
STRIPE_VARIANTS = (0, 2, 0, 1)


def _random_rotations(n: int, rng: np.random.Generator) -> Rotation:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Rotation(q)


def perturb_rotations(rotations: Rotation, scatter: float, rng, centred: bool = True) -> Rotation:
    """Return rotations times small random rotations.

    Parameters
    ----------
    rotations
        Rotations to perturb (any shape; flattened).
    scatter
        RMS misorientation angle in degrees. Each rotation is multiplied
        (on the right, in the sample frame) by a rotation whose rotation
        vector has normal components of standard deviation
        ``scatter / sqrt(3)``.
    rng
        :class:`numpy.random.Generator` or a seed.
    centred
        Subtract the mean rotation vector so that the perturbations have
        exactly zero mean (the paper's perturbation study). A common
        rotation of all orientations is indistinguishable from a change
        of the detector angles, so the random common part of uncentred
        perturbations (of size ``scatter / sqrt(n)``, see
        :func:`common_rotation`) is a bias no calibration can remove.
        The same *rng* state draws the same numbers either way: only the
        centring differs.

    Returns
    -------
    perturbed
        Flat :class:`~orix.quaternion.Rotation`.

    Examples
    --------
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation.orientations import common_rotation, perturb_rotations
    >>> truth = Rotation.identity(100)
    >>> angle, _ = common_rotation(perturb_rotations(truth, 0.3, 0), truth)
    >>> bool(angle < 1e-12)
    True
    >>> angle, _ = common_rotation(perturb_rotations(truth, 0.3, 0, centred=False), truth)
    >>> bool(0.005 < angle < 0.1)
    True
    """
    rng = np.random.default_rng(rng)
    rotations = rotations.flatten()
    v = rng.normal(scale=np.deg2rad(scatter) / np.sqrt(3), size=(rotations.size, 3))
    if centred and rotations.size > 1:
        v -= v.mean(axis=0)
    return rotations * rotations_from_vectors(v)


class CommonRotation(NamedTuple):
    """Mean deviation of starting orientations from the truth."""

    #: Angle in degrees of the mean rotation vector.
    angle: float
    #: Unit axis (3,) in the sample frame; ``[0, 0, 1]`` when *angle* is 0.
    axis: np.ndarray

    @property
    def vector(self) -> np.ndarray:
        """The mean rotation vector (3,) in degrees."""
        return self.angle * self.axis


def _rotations_of(r) -> Rotation:
    if isinstance(r, CrystalMap):
        return r.rotations.flatten()
    return Rotation(r).flatten()


def common_rotation(
    start: Rotation | CrystalMap, truth: Rotation | CrystalMap, symmetry=None
) -> CommonRotation:
    """Return the common part of the deviations of *start* from *truth*.

    The deviation of each orientation is the sample-frame rotation ``T`` with
    ``start = truth * T`` (orix's right factor, as in
    :func:`perturb_rotations`), i.e. ``T = ~truth * start``. Its common part
    is the mean of the rotation vectors of ``T`` over the map (for deviations
    of a few degrees, the mean rotation up to terms of second order in the
    angles). It is what no calibration can tell from a change of the detector
    angles: zero for the "centred" start of
    :func:`~kikuchipy_geomdic.validation.synthetic.synthetic_map`, of order
    ``orientation_error / sqrt(n)`` for "uncentred" and larger for "indexed",
    where the geometry error was absorbed into the orientations.

    Parameters
    ----------
    start, truth
        Rotations or crystal maps of the same size (flattened; for crystal
        maps, the points in the data).
    symmetry
        Optional orix :class:`~orix.quaternion.Symmetry` (e.g. the phase's
        point group): each start is first replaced by the equivalent
        ``op * start`` (crystal-frame operator, left factor) closest to its
        truth. Not needed for starts within a few degrees of the truth.

    Returns
    -------
    common
        :class:`CommonRotation` ``(angle, axis)``, angle in degrees,
        unpacks as a tuple; ``common.vector`` is the mean rotation vector
        in degrees.

    Examples
    --------
    >>> import numpy as np
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.validation.orientations import common_rotation
    >>> truth = Rotation.random(5)
    >>> t = Rotation.from_axes_angles([0, 0, 1], np.deg2rad(0.5))
    >>> angle, axis = common_rotation(truth * t, truth)
    >>> round(angle, 6), np.round(axis, 6).tolist()
    (0.5, [0.0, 0.0, 1.0])
    """
    s = _rotations_of(start)
    t = _rotations_of(truth)
    if s.size != t.size:
        raise ValueError(f"start has {s.size} rotations, truth {t.size}")
    dev = ~t * s
    if symmetry is not None:
        best = np.abs(dev.a)
        q = dev.data.copy()
        ops = getattr(symmetry, "proper_subgroup", symmetry)
        for op in Rotation(ops).flatten():
            cand = ~t * (op * s)
            better = np.abs(cand.a) > best
            best = np.where(better, np.abs(cand.a), best)
            q[better] = cand.data[better]
        dev = Rotation(q)
    v = np.rad2deg(rotation_vectors(dev).mean(axis=0))
    angle = float(np.linalg.norm(v))
    axis = v / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    return CommonRotation(angle, axis)


#: Map points per grain of ``orientations="grains"`` (on average).
GRAIN_POINTS = 16


def _grains(nav: tuple[int, int], rng) -> np.ndarray:
    # Voronoi cells of random centres: grains larger than a step, as in a
    # real polycrystal map, so that neighbours share an orientation
    n = max(2, nav[0] * nav[1] // GRAIN_POINTS)
    centres = rng.uniform([0, 0], nav, size=(n, 2))
    points = np.indices(nav).reshape(2, -1).T + 0.5
    d = ((points[:, None, :] - centres[None]) ** 2).sum(axis=-1)
    return d.argmin(axis=1).reshape(nav)


def _domains(nav: tuple[int, int], n: int = 6) -> np.ndarray:
    # Diagonal stripes, as ferroelectric domain walls often run; all n
    # domains appear once the map has n or more diagonals
    rows, cols = np.indices(nav)
    n_diag = nav[0] + nav[1] - 1
    return ((rows + cols) * n // max(n_diag, 1)) % n


def _true_orientations(orientations, nav, scatter, rng) -> tuple[Rotation, dict]:
    """The true orientations (n,) of a synthetic map and its properties."""
    n = nav[0] * nav[1]
    prop = {}
    if orientations == "random":
        rot = _random_rotations(n, rng)
    elif orientations == "single":
        rot = perturb_rotations(_random_rotations(1, rng) * Rotation.identity(n), scatter, rng)
    elif orientations == "grains":
        grain = _grains(nav, rng).ravel()
        rot = perturb_rotations(_random_rotations(grain.max() + 1, rng)[grain], scatter, rng)
        prop["grain"] = grain
    elif orientations in ("variants", "stripes"):
        cycle = np.arange(6) if orientations == "variants" else np.array(STRIPE_VARIANTS)
        variant = cycle[_domains(nav, cycle.size).ravel()]
        parent = _random_rotations(1, rng)
        rot = variant_operators()[variant] * parent
        rot = perturb_rotations(rot, scatter, rng)
        prop["variant"] = variant
    else:
        raise ValueError(
            "orientations must be 'single', 'random', 'grains', 'variants' or 'stripes', "
            f"not {orientations!r}"
        )
    return rot, prop


def _start_orientations(
    rot, prop, orientations, start, orientation_error, rng, seed
) -> tuple[Rotation, dict]:
    """The starting orientations of a start model and their properties."""
    # "indexed" refines the "uncentred" start: same draws for all models
    start_rot = perturb_rotations(rot, orientation_error, rng, centred=start == "centred")
    start_prop = prop
    if orientations in ("variants", "stripes") and start == "indexed":
        # An indexer cannot tell the variants apart: each point comes in a
        # random one (a generator of its own, so the truth, the patterns and
        # the other start models keep their draws)
        drawn = np.random.default_rng([seed, 25]).integers(6, size=rot.size)
        ops = variant_operators()
        start_rot = ops[drawn] * ~ops[prop["variant"]] * start_rot
        start_prop = {"variant": drawn}
    elif orientations == "stripes":
        # The variant operator removed from each start: the parent's variant
        # with the point's own scatter and start error
        start_rot = ~variant_operators()[prop["variant"]] * start_rot
        start_prop = {"variant": np.zeros_like(prop["variant"])}
    return start_rot, start_prop
