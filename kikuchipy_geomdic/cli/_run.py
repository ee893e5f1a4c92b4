"""How a command runs: its one-line errors and warnings, its exit codes
and the dask cluster it may run on.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
import warnings

PROG = "kikuchipy-geomdic"
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


class CLIError(Exception):
    """An error the user can fix: printed as one line, exit code 2."""


def _one_line(e: BaseException | str) -> str:
    text = str(e).strip() or type(e).__name__
    return " ".join(text.split())


def _warn(message: str) -> None:
    print(f"{PROG}: warning: {_one_line(message)}", file=sys.stderr)


@contextlib.contextmanager
def _cli_warnings():
    """Show Python warnings as one ``kikuchipy-geomdic: warning:`` line."""
    with warnings.catch_warnings():

        def show(message, category, filename, lineno, file=None, line=None):
            _warn(str(message))

        warnings.showwarning = show
        yield


def _run_on_map(function, args: argparse.Namespace, inputs, **kwargs):
    """``function(signal, xmap, detector, master_pattern, energy, ...)``
    on the ``--scheduler`` cluster (if any), with kikuchipy's progress
    unless ``--quiet``; the result and the wall time in seconds."""
    t0 = time.perf_counter()
    with _dask_client(args.scheduler):
        out = function(*inputs, args.energy, show_progressbar=not args.quiet, **kwargs)
    return out, time.perf_counter() - t0


@contextlib.contextmanager
def _dask_client(address: str | None):
    """Connect to a running dask scheduler (address or scheduler file)
    for the duration; nothing if *address* is None."""
    if not address:
        yield None
        return
    try:
        from distributed import Client
    except ImportError:
        raise CLIError("--scheduler needs the 'distributed' package") from None
    kw = {"scheduler_file": address} if address.endswith(".json") else {"address": address}
    try:
        client = Client(timeout="20s", **kw)
    except (OSError, TimeoutError, ValueError) as e:
        raise CLIError(
            f"cannot connect to the dask scheduler {address!r}: {_one_line(e)}"
        ) from None
    try:
        yield client
    finally:
        client.close()
