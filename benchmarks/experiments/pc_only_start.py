"""Experiment (a check, not the package's behaviour): one envelope domain map
calibrated from users' starts with the detector angles' start error removed,
so that only the PC is off; the 240 px map with the map's mean divided out
(``results/envelope/px240_processing_pc_only_start.log``).

Usage::

    python benchmarks/experiments/pc_only_start.py --cell px-240 --seed 1

The map is ``bench_envelope.envelope_map("domains", cell, seed,
other_removal=True)`` with the perturbation's tilt and azimuthal set to 0,
calibrated with the crystal model and BaTiO3's variant operators. Printed:
the PC errors with their standard errors, each full-field step's PC and
angle errors (the angles held or not), the orientations' error and the
result's table against the truth.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
from orix.quaternion import Orientation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import bench_envelope as envelope  # noqa: E402

from kikuchipy_geomdic import refine_geometry_dic  # noqa: E402
from kikuchipy_geomdic.geometry.maps import flat_index  # noqa: E402
from kikuchipy_geomdic.indexing.variants import variant_operators  # noqa: E402
from kikuchipy_geomdic.validation import synthetic  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cell", default="px-240", choices=sorted(envelope.CELLS))
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    perturbation = {**synthetic.DEFAULT_PERTURBATION, "tilt": 0.0, "azimuthal": 0.0}
    envelope.CELLS[args.cell] = {**envelope.CELLS[args.cell], "perturbation": perturbation}
    sm = envelope.envelope_map("domains", args.cell, args.seed, other_removal=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = refine_geometry_dic(
            sm.signal, sm.start_xmap, sm.start_detector, sm.master_pattern, sm.energy,
            parameters=envelope.PARAMETERS, pseudo_symmetry_ops=variant_operators()[1:],
            orientation_model="crystal", show_progressbar=True,
        )  # fmt: skip
    truth = sm.geometry.as_dict()
    print(
        {
            k: f"{res.parameters[k] - truth[k]:+.1e} se {res.standard_errors[k]:.1e}"
            for k in ("pcx", "pcy", "pcz")
        }
    )
    for h in res.history:
        if h.get("stage") == "full-field":
            p = h["parameters"]
            print(h["iteration"], {k: f"{p[k] - truth[k]:+.2e}" for k in envelope.PARAMETERS})
    point_group = sm.xmap.phases[sm.xmap.phases.ids[-1]].point_group
    idx = flat_index(res.points, sm.geometry.navigation_shape)
    true = Orientation(sm.xmap.rotations[idx], symmetry=point_group)
    got = Orientation(res.xmap.rotations, symmetry=point_group)
    angle = np.degrees(got.angle_with(true))
    print(
        f"orientations: {int((angle > 5).sum())} in a wrong variant, the rest "
        f"{np.median(angle[angle < 5]):.3f} deg off (median)"
    )
    print(res.table(sm.geometry))


if __name__ == "__main__":
    main()
