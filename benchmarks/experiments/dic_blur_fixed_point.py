"""The DIC stage's fixed point from the truth against the camera's blur.

Model-family Ni maps (11 x 11, 96 px, the data's own master pattern, the
patterns ``a * blur(S) + b`` with Poisson noise, no background), the DIC
stage alone (``full_field=False``) started from the true detector and
orientations: where it ends is its bias. The patterns blurred by
``--blur`` px, the DIC stage's simulations by ``--sim-blur`` px (0: as
the package compares them, unblurred).

With ``--cases``: ``bench_realistic.py``'s maps of those cases instead
(camera counts, lobe, background removal), the simulations ``plain``,
processed by the full field's model of the processing estimated at the
truth (``full``), or by that model less its high-pass (``no-highpass``).

Usage::

    python benchmarks/experiments/dic_blur_fixed_point.py --blur 0 0.6 --sim-blur 0 0.6 \
        --doses 10000 150 --seeds 0 1 2
    python benchmarks/experiments/dic_blur_fixed_point.py --cases moderate emsoft-data \
        --seeds 0 1 2
"""

import argparse
import contextlib
import io
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from kikuchipy_geomdic import refine_geometry_dic
from kikuchipy_geomdic.calibration import _problem
from kikuchipy_geomdic.calibration._processing import _estimate_processing
from kikuchipy_geomdic.validation import master_patterns, synthetic

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _tee import start_log  # noqa: E402
from bench_realistic import realistic_map  # noqa: E402

PC = ("pcx", "pcy", "pcz")
PLAIN = _problem._Problem.compare


def _blurred_compare(sigma):
    """``_Problem.compare`` with the simulations blurred by *sigma* px."""

    def compare(self, geometry, rotations):
        sim = self.simulate(geometry, rotations)
        sim = ndimage.gaussian_filter(sim, (0, sigma, sigma), mode="nearest").astype(np.float32)
        field = _problem._measure(sim, self.dic_experimental, self.dic_kwargs)
        return field, _problem._ncc(sim, self.dic_experimental)

    return compare


def _processed_compare(highpass: bool):
    """``_Problem.compare`` with the simulations processed by the full
    field's model, estimated at the first call's (the true) geometry;
    without *highpass*, less its high-pass."""
    model = {}

    def compare(self, geometry, rotations):
        sim = self.simulate(geometry, rotations)
        if "proc" not in model:
            proc = _estimate_processing(self, self.arrays, geometry, rotations)
            model["proc"] = proc if highpass else replace(proc, highpass=0.0)
        flat = sim.reshape(len(sim), -1).astype(np.float64)
        sim = model["proc"](flat)[0].reshape(sim.shape).astype(np.float32)
        field = _problem._measure(sim, self.dic_experimental, self.dic_kwargs)
        return field, _problem._ncc(sim, self.dic_experimental)

    return compare


def _fixed_point(sm, label: str) -> None:
    truth = sm.geometry.as_dict()
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = refine_geometry_dic(
            sm.signal, sm.xmap, sm.detector, sm.master_pattern, sm.energy,
            points=sm.xmap.size, full_field=False, show_progressbar=False,
        )  # fmt: skip
    err = [res.parameters[k] - truth[k] for k in PC]
    se = [res.standard_errors[k] for k in PC]
    print(
        f"{label} | err " + " ".join(f"{e:+.1e}" for e in err) + " | se "
        + " ".join(f"{s:.1e}" for s in se)
        + " | z " + " ".join(f"{e / s:+5.1f}" for e, s in zip(err, se)),
        flush=True,
    )  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--blur", type=float, nargs="+", default=[0.0, 0.6])
    ap.add_argument("--sim-blur", type=float, nargs="+", default=[0.0, 0.6])
    ap.add_argument("--doses", type=float, nargs="+", default=[10000.0, 150.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--cases", nargs="+", help="bench_realistic.py's cases instead")
    ap.add_argument("--log", type=Path)
    args = ap.parse_args(argv)
    start_log(args.log)
    if args.cases:
        modes = {"plain": PLAIN, "full": None, "no-highpass": None}
        for case in args.cases:
            for seed in args.seeds:
                sm = realistic_map(case, seed)
                for mode in modes:
                    compare = PLAIN if mode == "plain" else _processed_compare(mode == "full")
                    _problem._Problem.compare = compare
                    _fixed_point(sm, f"{case:14s} seed {seed} sims {mode:11s}")
        _problem._Problem.compare = PLAIN
        return
    mp = master_patterns.master_pattern("Ni", kind="emsoft")
    for dose in args.doses:
        for blur in args.blur:
            for seed in args.seeds:
                sm = synthetic.synthetic_map(
                    mp, (11, 11), shape=(96, 96), seed=seed, orientation_error=1.0,
                    start="indexed", simulator=mp, perturbation=synthetic.DEFAULT_PERTURBATION,
                    dose=dose, blur=blur,
                )  # fmt: skip
                for sim_blur in args.sim_blur:
                    _problem._Problem.compare = _blurred_compare(sim_blur) if sim_blur else PLAIN
                    label = f"dose {dose:6g} blur {blur:.1f} sims {sim_blur:.1f} seed {seed}"
                    _fixed_point(sm, label)
    _problem._Problem.compare = PLAIN


if __name__ == "__main__":
    main()
