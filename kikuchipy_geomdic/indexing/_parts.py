"""Per-point work split into parts for dask's local pool: its thread
count, and the points' parts (two per thread) that a call on every point
is run as, each on its own task.

Layer 4 (indexing): imports only dask and numpy.
"""

from __future__ import annotations

import os

import dask
import numpy as np


def _threads() -> int:
    """Threads of dask's local pool (its ``num_workers`` setting, else the
    CPU count)."""
    n = dask.config.get("num_workers", None)
    return int(n) if n else (os.cpu_count() or 1)


def _parts(n: int) -> list[np.ndarray]:
    """The indices of *n* points in two non-empty parts per thread (fewer
    if there are fewer points)."""
    return [p for p in np.array_split(np.arange(n), 2 * _threads()) if p.size]
