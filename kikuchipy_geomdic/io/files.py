"""Atomic file writes and CSV text: every file the package writes is
replaced in one step, so a reader (or an interrupted run) sees the old
file or the complete new one.

Layer 2 (io): may import geometry.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write_text", "csv_text"]


def _atomic_path(path: Path):
    """A temporary file beside *path* (same file system, so os.replace is
    atomic), keeping the extension (numpy.savetxt looks at it), with the
    permissions a new file gets (mkstemp's are owner-only)."""
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=path.suffix or ".tmp", dir=path.parent
    )
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    return Path(tmp)


@contextlib.contextmanager
def _atomic(path: str | Path):
    """Yield a temporary path to write to; on success it replaces *path*
    in one step, so a reader (or an interrupted run) sees the old file or
    the complete new one, never a partial file."""
    path = Path(path)
    tmp = _atomic_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write *text* to *path* atomically: a reader (or an interrupted run)
    sees the old file or the complete new one, never a partial file.

    Parameters
    ----------
    path
        File to write; its folder must exist.
    text
        Content (UTF-8).

    Returns
    -------
    path
    """
    with _atomic(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def csv_text(columns: Sequence[str], rows: Iterable[Sequence[Any]], digits: int = 12) -> str:
    """Return rows as CSV text with a header line.

    Parameters
    ----------
    columns
        Column names.
    rows
        Rows of values in the order of *columns*.
    digits
        Significant digits of floats; other values are written with
        ``str``.

    Returns
    -------
    text
        One line per row, each ending in a newline.

    Examples
    --------
    >>> from kikuchipy_geomdic.io.files import csv_text
    >>> print(csv_text(["step", "ncc", "accepted"], [(1, 0.123456789, True)], 4), end="")
    step,ncc,accepted
    1,0.1235,True
    """
    lines = [",".join(columns)]
    for row in rows:
        lines.append(
            ",".join(
                f"{v:.{digits}g}" if isinstance(v, (float, np.floating)) else str(v) for v in row
            )
        )
    return "\n".join(lines) + "\n"
