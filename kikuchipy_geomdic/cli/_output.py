"""Writing a command's outputs: a staging folder whose files are moved
into place only once all are written, the summary last, and the record of
the inputs every summary holds.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from kikuchipy_geomdic.cli._run import PROG, CLIError


class _Staging:
    """Output files written to a hidden folder inside *out*, moved into
    *out* by :meth:`commit` (the last name, the summary, last). Leaving
    the ``with`` block removes the staging folder, so an interrupted or
    failed run leaves nothing that looks complete."""

    def __init__(self, out: str | os.PathLike, names: Sequence[str], overwrite: bool):
        self.out = Path(out)
        self.names = tuple(names)
        self.tmp: Path | None = None
        if self.out.exists() and not self.out.is_dir():
            raise CLIError(f"--out {str(self.out)!r} is a file, not a folder")
        present = [n for n in self.names if (self.out / n).exists()]
        if present and not overwrite:
            raise CLIError(
                f"{str(self.out)!r} already holds results ({present[0]}, ...): pass "
                "--overwrite or choose another --out"
            )

    def __enter__(self) -> _Staging:
        self.out.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=".kikuchipy-geomdic-", dir=self.out))
        return self

    def path(self, name: str) -> Path:
        assert name in self.names and self.tmp is not None
        return self.tmp / name

    def commit(self) -> list[Path]:
        marker = self.out / self.names[-1]
        marker.unlink(missing_ok=True)  # an old summary must not vouch for new files
        moved = []
        for name in self.names:
            if (self.tmp / name).exists():
                os.replace(self.tmp / name, self.out / name)
                moved.append(self.out / name)
        return moved

    def __exit__(self, *exc) -> bool:
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
        return False


def _inputs(args: argparse.Namespace, signal, master_pattern, **extra) -> dict[str, Any]:
    from kikuchipy_geomdic.geometry.maps import navigation_shape

    return {
        "command": shlex.join([PROG, *getattr(args, "argv", [])]),
        "patterns": str(Path(args.patterns).resolve()),
        "orientations": (
            str(Path(args.orientations).resolve()) if args.orientations else "pattern file"
        ),
        "master_pattern": _one_or_list([_spec(s) for s in args.master_pattern]),
        "master_pattern_title": _one_or_list(
            [str(m.metadata.General.title) for m in _as_list(master_pattern)]
        ),
        "energy_kv": float(args.energy),
        "navigation_shape": list(navigation_shape(signal)),
        "pattern_shape": list(signal.axes_manager.signal_shape[::-1]),
        **extra,
    }


def _spec(spec: str) -> str:
    """A ``--master-pattern`` as given: a file's absolute path, or a name."""
    return str(Path(spec).resolve()) if Path(spec).exists() else spec


def _as_list(master_pattern) -> list:
    return list(master_pattern) if isinstance(master_pattern, (list, tuple)) else [master_pattern]


def _one_or_list(values: list):
    """One value as itself (as with one phase), several as a list."""
    return values[0] if len(values) == 1 else values
