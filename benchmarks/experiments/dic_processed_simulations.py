"""The DIC stage against simulations processed as the camera's patterns.

Tried and left out (see README.md). The DIC stage compares the recorded
patterns (blurred by the phosphor, the dynamic background divided out)
with plain simulations; here each simulation is blurred by 0.6 px (the
camera's point spread) and has kikuchipy's dynamic background removed too,
on the Si single crystals of ``bench_crystal.py --case si100 --start
users`` (tutorial 02b's A1 map; the data's own master pattern), DIC stage
alone and with the full field after it.

Run from the repository root::

    python benchmarks/experiments/dic_processed_simulations.py --fov 100 --seeds 0 1 2 3 4
"""

import argparse
import contextlib
import io
import time
import warnings

import numpy as np
from kikuchipy.signals import EBSD
from scipy import ndimage

from kikuchipy_geomdic.calibration import _problem
from kikuchipy_geomdic.geometry import MapGeometry
from kikuchipy_geomdic.indexing import orientation as ori
from kikuchipy_geomdic.patterns import displacement as dsp
from kikuchipy_geomdic.validation import master_patterns, synthetic
from kikuchipy_geomdic.validation.camera import Camera

PLAIN_COMPARE, PLAIN_NCC = _problem._Problem.compare, _problem._Problem.ncc


def _processed_compare(self, geometry, rotations):
    sim = self.simulate(geometry, rotations)
    blurred = ndimage.gaussian_filter(sim, (0, 0.6, 0.6))
    z = ori.standardise(blurred.reshape(len(sim), -1)).reshape(sim.shape)
    s = EBSD((100.0 * (1 + 0.1 * z)).astype(np.float32))
    s.remove_dynamic_background("divide", show_progressbar=False)
    sim = s.data.astype(np.float32)
    field = dsp.measure_displacements(sim, self.dic_experimental, **self.dic_kwargs)
    return field, _problem._ncc(sim, self.dic_experimental)


def _processed_ncc(self, geometry, rotations):
    return _processed_compare(self, geometry, rotations)[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fov", type=float, default=100.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    mp = master_patterns.master_pattern("Si", kind="dynamical")
    nav, step = (10, 10), args.fov / 9
    pcs = ("pcx", "pcy", "pcz")
    for seed in args.seeds:
        g = MapGeometry(
            pc=(0.52, 0.176, 0.858), shape=(120, 120), px_size=70.0, binning=4.0,
            step_sizes=(step, step), navigation_shape=nav, tilt=10.0, azimuthal=-2.0,
            sample_tilt=70.0,
        )  # fmt: skip
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            sm = synthetic.synthetic_map(
                mp, nav, orientations="single", geometry=g,
                perturbation=synthetic.DEFAULT_PERTURBATION, camera=Camera(dose=150, static=False),
                start="indexed", orientation_error=1.0, seed=seed,
            )  # fmt: skip
        truth = sm.geometry.as_dict()
        for label, compare, ncc in (
            ("plain", PLAIN_COMPARE, PLAIN_NCC),
            ("processed", _processed_compare, _processed_ncc),
        ):
            for full_field in (False, True):
                _problem._Problem.compare, _problem._Problem.ncc = compare, ncc
                t = time.perf_counter()
                try:
                    with contextlib.redirect_stdout(io.StringIO()):
                        res = sm.signal.refine_geometry_dic(
                            sm.start_xmap, sm.start_detector, mp, sm.energy,
                            parameters=["pcx", "pcy", "pcz", "tilt", "azimuthal"],
                            orientation_model="crystal", full_field=full_field,
                            show_progressbar=False,
                        )  # fmt: skip
                finally:
                    _problem._Problem.compare, _problem._Problem.ncc = PLAIN_COMPARE, PLAIN_NCC
                err = [res.parameters[n] - truth[n] for n in pcs]
                se = [res.standard_errors[n] for n in pcs]
                z = max(abs(e) / s for e, s in zip(err, se))
                print(
                    f"fov {args.fov:5.0f} seed {seed} {label:9s} full_field={full_field!s:5s} err "
                    + " ".join(f"{e:+.1e}" for e in err)
                    + " se "
                    + " ".join(f"{s:.1e}" for s in se)
                    + f" z {z:4.1f} conv {res.converged} {time.perf_counter() - t:.0f} s",
                    flush=True,
                )


if __name__ == "__main__":
    main()
