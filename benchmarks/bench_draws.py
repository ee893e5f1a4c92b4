"""Noise draws of one map: is a calibration's error a bias of the map or
its noise's draw?

Usage::

    python benchmarks/bench_draws.py --seed 0 --dose 30 --draws 12
    python benchmarks/bench_draws.py --seed 0 --dose 30 --draws 12 --static

The stripe-domain BaTiO3 map of ``bench_variants.py users`` (13 x 13, 120
px, ``Camera(dose)``, only the dynamic background removed unless
``--static``) is recorded again with other noise: the same orientations,
PCs and camera, the Poisson counts and the domains' brightness drawn from
the map's noise seed plus 0, 1, 2, ... (plus 0 is the benchmark's map).
Each draw is calibrated from the truth (true geometry and orientations,
the full field alone: ``max_iterations=0, full_field=True``, the PC
refined, the orientations free, no operators) and its PC error at the
map's reference position printed against its standard error. At the
end: the mean error (with its standard error over the draws), the
scatter over the draws against the mean reported standard error, and
the RMS and largest error over standard error.

A bias of the map shows as a mean error well away from zero; standard
errors too small, as a scatter above them (an RMS above 1).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
import warnings

import numpy as np

import kikuchipy_geomdic.validation.synthetic as synthetic
from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation.camera import Camera, camera_counts

_PC = ("pcx", "pcy", "pcz")


def _map_and_noise_seed(seed, dose, static):
    """The map of ``bench_variants.py users`` and the noise seed it was
    recorded with (read from the call that records it)."""
    seen = {}
    record = synthetic._signal

    def spy(*args, **kwargs):
        seen["seed"] = args[5]["seed"]
        return record(*args, **kwargs)

    synthetic._signal = spy
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sm = synthetic.synthetic_map(
                "BaTiO3", (13, 13), orientations="stripes", shape=(120, 120), seed=seed,
                camera=Camera(dose=dose, static=static), start="indexed", orientation_error=1.0,
            )  # fmt: skip
    finally:
        synthetic._signal = record
    return sm, seen["seed"]


def run(seed: int, dose: float, draws: int, static: bool) -> None:
    sm, noise_seed = _map_and_noise_seed(seed, dose, static)
    camera = Camera(dose=dose, static=static)
    clean = simulate_patterns(sm.simulator, sm.xmap.rotations, sm.detector, sm.energy)
    pcs = sm.detector.pc.reshape(-1, 3)
    labels = np.asarray(sm.xmap.prop["variant"]).astype(int)
    ref = np.array([sm.geometry.reference])
    errors, sigmas = [], []
    for k in range(draws):
        t0 = time.perf_counter()
        draw = np.random.default_rng([noise_seed + k, 1]).uniform(-1, 1, labels.max() + 1)
        counts = camera_counts(
            clean, pcs, camera, 1 + camera.brightness * draw[labels], noise_seed + k,
            np.arange(labels.size),
        )  # fmt: skip
        signal = sm.signal.deepcopy()
        signal.data = counts.reshape(signal.data.shape)
        camera.process(signal)
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = refine_geometry_dic(
                signal, sm.xmap, sm.detector, sm.master_pattern, sm.energy,
                parameters=list(_PC), full_field=True, max_iterations=0, show_progressbar=False,
            )  # fmt: skip
        err = res.geometry.pc_at(ref)[0] - sm.geometry.pc_at(ref)[0]
        se = np.array([res.standard_errors[k] for k in _PC])
        errors.append(err)
        sigmas.append(se)
        print(
            f"draw {k:2d}: PC error {np.array2string(err, precision=6)}, in standard errors "
            f"{np.array2string(err / se, precision=2)} ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    e, s = np.array(errors), np.array(sigmas)
    z = e / s
    fmt = dict(precision=6)
    print(
        f"\nseed {seed}, {dose:g} counts/px, {'static and ' if static else ''}dynamic "
        f"background removed, {draws} draws (pcx, pcy, pcz):\n"
        f"  mean error         {np.array2string(e.mean(0), **fmt)}\n"
        f"  its standard error {np.array2string(e.std(0, ddof=1) / np.sqrt(draws), **fmt)}\n"
        f"  scatter            {np.array2string(e.std(0, ddof=1), **fmt)}\n"
        f"  standard errors    {np.array2string(s.mean(0), **fmt)} (mean reported)\n"
        f"  RMS error / se     {np.array2string(np.sqrt((z**2).mean(0)), precision=2)}\n"
        f"  largest |error|/se {np.array2string(np.abs(z).max(0), precision=2)}"
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dose", type=float, default=30.0)
    p.add_argument("--draws", type=int, default=12)
    p.add_argument("--static", action="store_true", help="the map's mean divided out too")
    args = p.parse_args(argv)
    print("command: benchmarks/bench_draws.py " + " ".join(sys.argv[1:]), flush=True)
    run(args.seed, args.dose, args.draws, args.static)


if __name__ == "__main__":
    main()
