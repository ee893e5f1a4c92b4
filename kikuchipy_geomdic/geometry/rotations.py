"""Small crystal rotations as rotation vectors (angle times axis), the
form in which orientation changes add to first order.

Layer 1 (geometry): imports nothing of the package outside its own layer.
"""

from __future__ import annotations

import numpy as np
from orix.quaternion import Rotation

__all__ = ["rotation_vectors", "rotations_from_vectors"]


def rotation_vectors(rotations: Rotation) -> np.ndarray:
    """Return rotation vectors (angle times axis) in radians.

    Orientation changes ``g -> g * T`` (orix's right factor, a sample-frame
    rotation) are small; their vectors add to first order.

    Parameters
    ----------
    rotations
        Rotations (any shape; flattened). ``q`` and ``-q`` give the same
        vector, of length at most pi.

    Returns
    -------
    vectors
        Array (n, 3), accurate also for tiny angles.

    Examples
    --------
    >>> import numpy as np
    >>> from orix.quaternion import Rotation
    >>> from kikuchipy_geomdic.geometry import rotation_vectors, rotations_from_vectors
    >>> v = np.array([[0.0, 0.0, 0.1], [1e-9, 0.0, 0.0]])
    >>> bool(np.allclose(rotation_vectors(rotations_from_vectors(v)), v, rtol=1e-9, atol=0))
    True
    """
    q = np.asarray(Rotation(rotations).flatten().data, dtype=float)
    q = np.where(q[:, :1] < 0, -q, q)
    n = np.linalg.norm(q[:, 1:], axis=1)
    angle = 2 * np.arctan2(n, q[:, 0])
    factor = np.where(n > 0, angle / np.where(n > 0, n, 1.0), 2.0)
    return q[:, 1:] * factor[:, None]


def rotations_from_vectors(vectors: np.ndarray) -> Rotation:
    """Return rotations from rotation vectors; the inverse of
    :func:`rotation_vectors`.

    Parameters
    ----------
    vectors
        Rotation vectors (n, 3) (or (3,)): axis times angle, radians.

    Returns
    -------
    rotations
        orix rotations (n,).

    Examples
    --------
    >>> import numpy as np
    >>> from kikuchipy_geomdic.geometry import rotation_vectors, rotations_from_vectors
    >>> v = np.array([[0.0, 0.0, np.pi / 2]])
    >>> np.allclose(rotation_vectors(rotations_from_vectors(v)), v)
    True
    """
    v = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    half = np.linalg.norm(v, axis=1) / 2
    # sin(x) / x without dividing by zero; exact to float64 for tiny x
    sinc = np.sinc(half / np.pi) / 2
    return Rotation(np.concatenate([np.cos(half)[:, None], v * sinc[:, None]], axis=1))
