"""The ``kikuchipy-geomdic`` command line.

Three commands, each a thin layer over the Python API:

``demo``
    Calibrate a synthetic silicon map with a known, perturbed geometry and
    print the recovered values against the truth.
``refine``
    Calibrate the sample-detector geometry of a measured map
    (:func:`~kikuchipy_geomdic.calibration.refinement.refine_geometry_dic`) and write
    the calibrated detector in every PC convention, a summary, the
    per-iteration history and the diagnostic figures.
``reindex``
    Refine every orientation of a map with a calibrated detector
    (:func:`~kikuchipy_geomdic.indexing.reindex.reindex`) and write an orix crystal
    map (``.ang`` and orix h5). With ``--pseudo-symmetry`` (``refine``
    too) the variants of a pseudo-symmetric material are told apart, and
    ``reindex`` writes each point's variant, its domain in the parent
    crystal's frame (:func:`~kikuchipy_geomdic.indexing.variants.domain_labels`),
    confidence, margin and significance (a call within the pattern's noise
    is not ``converged``), and draws the domain map (``domains.png``).

``kikuchipy-geomdic COMMAND --help`` lists the options. Known errors (a
missing or unreadable file, a master pattern of the wrong phase or
energy, maps and patterns of different sizes) end the program with one
line ``kikuchipy-geomdic: error: ...`` on stderr and exit code 2; Ctrl-C
ends it with exit code 130. Output files are written to a hidden staging
folder inside the output folder and moved into place only once all are
written, the summary (``summary.json``, ``reindex.json``) last: an
interrupted run leaves no file that looks complete, and input files are
only read.

The commands live in ``_demo``, ``_refine`` and ``_reindex`` (each with
its options), reading inputs in ``_load``, writing outputs in ``_output``,
the shared options in ``_parser`` and errors, warnings and the dask
cluster in ``_run``.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse
import sys

from kikuchipy_geomdic.cli._demo import _demo_parser
from kikuchipy_geomdic.cli._load import (
    MASTER_PATTERN_NAMES,
    load_crystal_map,
    load_master_pattern,
    load_patterns,
    start_detector,
)
from kikuchipy_geomdic.cli._parser import _common_parser
from kikuchipy_geomdic.cli._refine import REFINE_OUTPUTS, _refine_parser
from kikuchipy_geomdic.cli._reindex import (
    ANG_VARIANT_COLUMNS,
    DOMAIN_FIGURE,
    REINDEX_OUTPUTS,
    _reindex_parser,
)
from kikuchipy_geomdic.cli._run import (
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    PROG,
    CLIError,
    _cli_warnings,
    _one_line,
)

__all__ = [
    "main",
    "CLIError",
    "load_patterns",
    "load_crystal_map",
    "load_master_pattern",
    "start_detector",
    "MASTER_PATTERN_NAMES",
    "REFINE_OUTPUTS",
    "REINDEX_OUTPUTS",
    "DOMAIN_FIGURE",
    "ANG_VARIANT_COLUMNS",
]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kikuchipy-geomdic",
        description="Global DIC-based EBSD sample-detector geometry calibration.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    _demo_parser(sub)
    common = _common_parser()
    _refine_parser(sub, common)
    _reindex_parser(sub, common)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line.

    Parameters
    ----------
    argv
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    status
        Exit code: 0 on success, 2 on an error (a one-line message on
        stderr), 130 when interrupted.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    if args.command == "demo":
        return args.func(args)
    args.argv = argv
    try:
        with _cli_warnings():
            return args.func(args)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (CLIError, OSError, ValueError) as e:
        if getattr(args, "traceback", False):
            raise
        print(f"{PROG}: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
