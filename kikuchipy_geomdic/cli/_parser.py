"""The options ``refine`` and ``reindex`` share (inputs, starting
geometry, running) and the building blocks of each command's options.

Layer 8 (cli): may import anything of the package.
"""

from __future__ import annotations

import argparse

from kikuchipy_geomdic.cli._load import MASTER_PATTERN_NAMES


def _common_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "patterns",
        metavar="PATTERNS",
        help="EBSD map: any file kikuchipy.load reads (EDAX, Oxford or Bruker h5ebsd, "
        "NORDIF, kikuchipy h5ebsd, ...); read lazily",
    )
    common.add_argument(
        "--orientations",
        metavar="MAP",
        help="starting orientations: a crystal map orix reads (.ang, .ctf, orix h5); "
        "default: the orientations stored with the patterns",
    )
    common.add_argument(
        "--master-pattern",
        metavar="MP",
        required=True,
        action="append",
        help="master pattern file kikuchipy reads (e.g. EMsoft h5), or a shipped one: "
        + ", ".join(MASTER_PATTERN_NAMES)
        + "; repeat it, one per phase, for a map of several phases (NAME=FILE checks that "
        "FILE is matched to the map's phase NAME): every phase with one is calibrated from "
        "or reindexed",
    )
    common.add_argument(
        "--energy", metavar="KV", type=float, required=True, help="beam energy in kV"
    )
    common.add_argument(
        "--phase",
        metavar="NAME",
        help="name or id of the map's phase to use, which must match the master "
        "pattern's (default: the map's only indexed phase)",
    )
    common.add_argument(
        "--pseudo-symmetry",
        metavar="OPS",
        help="operators of the material's pseudo-symmetric variants: a name the package "
        "knows (BaTiO3: its six c-axis variants) or an .npy or text file of an (n, 4) "
        "array of unit quaternions (crystal frame, acting as op * rotation, identity left "
        "out). refine: each calibration point takes the variant its pattern shows; reindex: "
        "each point is refined in every variant and writes its variant, domain (the variant "
        "in the parent crystal's frame), confidence, margin and significance (calls within "
        "the pattern's noise get converged 0), and domains.png (with "
        "--method kikuchipy: its pseudo_symmetry_index and the domain, no figure)",
    )
    geo = common.add_argument_group("starting geometry (default: the pattern file's metadata)")
    geo.add_argument(
        "--pc",
        metavar=("X", "Y", "Z"),
        nargs=3,
        type=float,
        help="projection centre in --convention",
    )
    geo.add_argument(
        "--convention",
        choices=("bruker", "edax", "tsl", "oxford", "emsoft", "emsoft4", "emsoft5"),
        type=str.lower,
        help="convention of --pc (default bruker; emsoft = emsoft5)",
    )
    geo.add_argument("--tilt", type=float, metavar="DEG", help="detector tilt")
    geo.add_argument("--sample-tilt", type=float, metavar="DEG", help="sample tilt")
    geo.add_argument(
        "--azimuthal",
        type=float,
        metavar="DEG",
        help="detector azimuthal angle (kikuchipy >= 0.12 sign)",
    )
    geo.add_argument("--twist", type=float, metavar="DEG", help="detector twist")
    geo.add_argument(
        "--px-size", type=float, metavar="UM", help="unbinned detector pixel size in micrometres"
    )
    geo.add_argument("--binning", type=float, metavar="B", help="detector binning")
    run = common.add_argument_group("running")
    run.add_argument("--overwrite", action="store_true", help="replace results already in --out")
    run.add_argument("--quiet", action="store_true", help="no progress output")
    run.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the dask work on a running dask.distributed scheduler (address "
        "such as tcp://host:8786, or a scheduler file .json); see docs/cluster.md",
    )
    run.add_argument("--traceback", action="store_true", help="show the full traceback of errors")
    return common


def _command_output(parser: argparse.ArgumentParser, command: str, func) -> None:
    """The ``--out`` folder of a command (default ``geomdic-<command>``)
    and the function that runs it."""
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=f"geomdic-{command}",
        help=f"output folder (default geomdic-{command})",
    )
    parser.set_defaults(func=func)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not positive")
    return value


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"{value} is not a fraction >= 0")
    return value
