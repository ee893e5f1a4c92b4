"""Noise draws of one map: is a calibration's error a bias of the map or
its noise's draw, and do its standard errors cover the scatter?

Usage::

    python benchmarks/bench_draws.py --map stripes --seed 0 --dose 30 --draws 12
    python benchmarks/bench_draws.py --map stripes --seed 0 --dose 30 --start users
    python benchmarks/bench_draws.py --map real-noise --seed 1 --start users --draws 8

Maps: ``stripes``, the BaTiO3 domain map of ``bench_variants.py users``
(13 x 13, 120 px, ``Camera(dose)``, only the dynamic background removed
unless ``--static``), or a case of ``bench_realistic.py`` (``moderate``,
``real-noise``, ``emsoft-data``, ``ebsdsim-data``: 11 x 11 Ni maps of 96
px, the map's mean divided out as there). The map is recorded again with
other noise: the same orientations, PCs and camera, the Poisson counts
and the brightness of grains or domains drawn from the map's noise seed
plus 0, 1, 2, ... (plus 0 is the benchmark's map).

``--start truth`` calibrates each draw from the true geometry and
orientations with the full field alone (``max_iterations=0,
full_field=True``, the PC refined, the orientations free, no operators);
``--start users`` with the defaults from the map's start (orientations
indexed and refined at the perturbed detector; the stripes map with its
pseudo-symmetry operators; the Ni maps from all their points), as the
benchmarks do. Each draw's PC error at
the map's reference position is printed against its standard error; at
the end the mean error (with its standard error over the draws), the
scatter over the draws against the mean reported standard error, the RMS
error and the RMS and largest error over standard error.

A bias of the map shows as a mean error well away from zero; standard
errors too small, as a scatter above them (an RMS error over standard
error above 1).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kikuchipy_geomdic.validation.synthetic as synthetic
from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic
from kikuchipy_geomdic.indexing.variants import variant_operators
from kikuchipy_geomdic.patterns.simulation import simulate_patterns
from kikuchipy_geomdic.validation.camera import Camera, camera_counts

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_realistic import realistic_map  # noqa: E402
from bench_variants import _quiet  # noqa: E402

_PC = ("pcx", "pcy", "pcz")


def _map(name, seed, dose, static):
    """The map, and the noise seed and brightness labels it was recorded
    with (read from the call that records it)."""
    seen = {}
    record = synthetic._signal

    def spy(*args, **kwargs):
        seen["seed"], seen["labels"] = args[5]["seed"], np.asarray(args[6]).astype(int)
        return record(*args, **kwargs)

    synthetic._signal = spy
    try:
        with _quiet():
            if name == "stripes":
                sm = synthetic.synthetic_map(
                    "BaTiO3", (13, 13), orientations="stripes", shape=(120, 120), seed=seed,
                    camera=Camera(dose=dose, static=static), start="indexed",
                    orientation_error=1.0,
                )  # fmt: skip
            else:
                sm = realistic_map(name, seed)
    finally:
        synthetic._signal = record
    return sm, seen["seed"], seen["labels"]


def run(name: str, seed: int, dose: float, draws: int, static: bool, start: str) -> None:
    sm, noise_seed, labels = _map(name, seed, dose, static)
    camera = sm.camera
    clean = simulate_patterns(sm.simulator, sm.xmap.rotations, sm.detector, sm.energy)
    pcs = sm.detector.pc.reshape(-1, 3)
    ref = np.array([sm.geometry.reference])
    ops = variant_operators()[1:] if name == "stripes" else None
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
        with _quiet():
            if start == "truth":
                res = refine_geometry_dic(
                    signal, sm.xmap, sm.detector, sm.master_pattern, sm.energy,
                    parameters=list(_PC), full_field=True, max_iterations=0,
                    show_progressbar=False,
                )  # fmt: skip
            else:
                # As the benchmarks call it: every point of the Ni maps
                kw = {} if name == "stripes" else {"points": labels.size}
                res = refine_geometry_dic(
                    signal, sm.start_xmap, sm.start_detector, sm.master_pattern, sm.energy,
                    pseudo_symmetry_ops=ops, show_progressbar=False, **kw,
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
    removed = "static and dynamic" if camera.static else "dynamic"
    print(
        f"\n{name} seed {seed}, {camera.dose:g} counts/px, {removed} background removed, from "
        f"the {start}, {draws} draws (pcx, pcy, pcz):\n"
        f"  mean error         {np.array2string(e.mean(0), **fmt)}\n"
        f"  its standard error {np.array2string(e.std(0, ddof=1) / np.sqrt(draws), **fmt)}\n"
        f"  scatter            {np.array2string(e.std(0, ddof=1), **fmt)}\n"
        f"  standard errors    {np.array2string(s.mean(0), **fmt)} (mean reported)\n"
        f"  RMS error          {np.array2string(np.sqrt((e**2).mean(0)), **fmt)}\n"
        f"  RMS error / se     {np.array2string(np.sqrt((z**2).mean(0)), precision=2)}\n"
        f"  largest |error|/se {np.array2string(np.abs(z).max(0), precision=2)}"
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--map",
        default="stripes",
        choices=["stripes", "moderate", "real-noise", "emsoft-data", "ebsdsim-data"],
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dose", type=float, default=30.0, help="stripes: counts per pixel")
    p.add_argument("--draws", type=int, default=12)
    p.add_argument("--static", action="store_true", help="stripes: the map's mean divided out")
    p.add_argument("--start", default="truth", choices=["truth", "users"])
    args = p.parse_args(argv)
    print("command: benchmarks/bench_draws.py " + " ".join(sys.argv[1:]), flush=True)
    run(args.map, args.seed, args.dose, args.draws, args.static, args.start)


if __name__ == "__main__":
    main()
