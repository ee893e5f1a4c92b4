"""What the user sees while a refinement runs: a header, one line per
trial step and a progress bar over the iterations (:class:`_Progress`).

Layer 6 (calibration): may import geometry, io, patterns, indexing, plotting
and calibration.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

import hyperspy.api as hs
from tqdm import tqdm


def _show_progressbar(show_progressbar: bool | None) -> bool:
    """*show_progressbar*, or HyperSpy's preference if None (kikuchipy's
    convention)."""
    if show_progressbar is None:
        return bool(hs.preferences.General.show_progressbar)
    return bool(show_progressbar)


class _Progress:
    """What the user sees while a loop runs, if *show*: *header* and one
    line per trial step printed to stdout, and a tqdm bar over the
    iterations on stderr with the current RMS displacement and NCC.

    The lines are printed as kikuchipy prints its refinement information
    next to its progress bars (:meth:`~kikuchipy.signals.EBSD.refine_orientation`
    prints; kikuchipy logs only debug messages); ``tqdm.write`` keeps them
    above the bar.
    """

    def __init__(self, show: bool, total: int, header: str):
        self.show = show
        self._bar = None
        if show:
            print(header)
            self._bar = tqdm(total=total, desc="Geometry refinement", unit="iteration")

    def write(self, line: str) -> None:
        if self.show:
            tqdm.write(line, file=sys.stdout)

    def advance(self, record: Mapping[str, Any] | None = None) -> None:
        """One iteration done; *record* is the history record of its last
        trial step."""
        if self._bar is None:
            return
        if record is not None:
            self._bar.set_postfix(
                rms=f"{100 * record['displacement_after']:.4f} %",
                ncc=f"{record['ncc_after']:.4f}",
                refresh=False,
            )
        self._bar.update()

    def __enter__(self) -> _Progress:
        return self

    def __exit__(self, exc_type, *exc) -> bool:
        if self._bar is not None:
            if exc_type is None:
                # Converged before max_iterations: a full bar
                self._bar.total = self._bar.n
            self._bar.close()
        return False
