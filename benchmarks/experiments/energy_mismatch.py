"""How far a band-width mismatch between the data and the master pattern
moves the PC: the hypothesis behind the pcz bias of section 2's EMsoft-data
maps (about -1e-4 on every map; EMsoft's 20 kV energy bin against
ebsdsim's Ni averaged over 14-20 kV). Kinematical Ni master patterns
(kikuchipy's simulator) make the data at 20 kV and calibrate at
``--energies`` kV: only the Bragg angles, hence the band widths, differ.
Section 1's realistic 11 x 11 maps of 96 px (camera, 150 counts/px,
background removed), users' starts.

Usage::

    python benchmarks/experiments/energy_mismatch.py --energies 19 20 21 --seeds 0 1 2
"""

import argparse
import contextlib
import io
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/

from kikuchipy_geomdic import refine_geometry_dic  # noqa: E402
from kikuchipy_geomdic.validation import master_patterns, synthetic  # noqa: E402
from kikuchipy_geomdic.validation.camera import MODERATE  # noqa: E402

PC = ("pcx", "pcy", "pcz")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--energies", type=float, nargs="+", default=[19.0, 20.0, 21.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    with contextlib.redirect_stderr(io.StringIO()):
        data = master_patterns.master_pattern("Ni", kind="kinematical", energy=20)
        calib = {
            e: master_patterns.master_pattern("Ni", kind="kinematical", energy=e)
            for e in args.energies
        }
    print(f"data: kinematical Ni at 20 kV; calibrated at {args.energies} kV")
    for seed in args.seeds:
        for e, mp in calib.items():
            sm = synthetic.synthetic_map(
                mp, (11, 11), shape=(96, 96), seed=seed, orientation_error=1.0,
                start="indexed", simulator=data, camera=MODERATE,
            )  # fmt: skip
            with contextlib.redirect_stdout(io.StringIO()):
                res = refine_geometry_dic(*sm.start_inputs, points=121, show_progressbar=False)
            truth = sm.geometry.as_dict()
            err = [res.parameters[k] - truth[k] for k in PC]
            z = [d / res.standard_errors[k] for d, k in zip(err, PC)]
            print(
                f"seed {seed} calibrated at {e:4.1f} kV | PC err "
                + " ".join(f"{d:+.1e}" for d in err)
                + " | z "
                + " ".join(f"{v:+5.1f}" for v in z),
                flush=True,
            )


if __name__ == "__main__":
    main()
