"""Experiment (not the package's behaviour): ``bench_draws.py`` from the
truth with one piece of the full field's model replaced, to see whether
that piece sets the scatter of the PC over noise draws.

Usage::

    python benchmarks/experiments/draws_model_variants.py --variant true-processing
    python benchmarks/experiments/draws_model_variants.py --variant moving-lobe
    python benchmarks/experiments/draws_model_variants.py --variant exact-weights

Variants, each patched into the full field for this process only:

- ``true-processing``: the camera's processing given (point spread 0.6
  px, high-pass an eighth of the width, contrast 0.1, the lobe left in)
  instead of chosen from the patterns;
- ``moving-lobe``: the same, with the lobe fitted to the static background
  moved with each pattern's PC (the backscatter lobe is fixed about the
  beam, so it moves across the screen as the PC does);
- ``exact-weights``: each pattern's gain and offset projected out in the
  weighted metric, with pixel variances proportional to the processed
  model over its low-pass (shot noise carried through kikuchipy's
  dynamic background division).

The map and the draws are those of ``bench_draws.py --map stripes``
(default seed 0, 30 counts/px, 12 draws, only the dynamic background
removed).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import bench_draws  # noqa: E402

from kikuchipy_geomdic.calibration import _full_field, _intensity, _processing  # noqa: E402


def _true_processing(problem, arrays, geometry, rotations):
    shape = problem.experimental.shape[1:]
    return _processing._Processing(
        shape, psf=0.6, highpass=shape[1] / 8, contrast=0.1, static=False, lobe=problem.lobe
    )


def _moving_lobe(problem, arrays, geometry, rotations):
    bg = problem.lobe  # the fitted lobe: its logarithm is the quadratic to move
    shape = bg.shape
    y, x = (np.indices(shape).reshape(2, -1) + 0.5) / shape[1]

    def basis(x, y):
        return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)

    coef, *_ = np.linalg.lstsq(basis(x, y), np.log(bg.ravel()), rcond=None)
    pcs = geometry.pc_at(problem.points)
    d = pcs - pcs.mean(axis=0)
    lobes = np.empty((len(pcs), 1) + shape)
    for i in range(len(pcs)):
        # Bruker PC: pcx a fraction of the width, pcy of the height
        lobe = np.exp(basis(x - d[i, 0], y - d[i, 1] * shape[0] / shape[1]) @ coef)
        lobes[i, 0] = (lobe / lobe.mean()).reshape(shape)
    # One block: the per-pattern lobe broadcasts against whole stacks
    _processing.DERIVATIVE_BLOCK = len(pcs)
    return _processing._Processing(
        shape, psf=0.6, highpass=shape[1] / 8, contrast=0.1, static=False, lobe=lobes
    )


def _exact_weights():
    weights = {}

    def project(x, basis, w):
        bw = basis * w[..., None]
        g_inv = np.linalg.inv(np.einsum("npa,npb->nab", bw, basis))
        if x.ndim == 2:
            coef = np.einsum("nab,nb->na", g_inv, np.einsum("npa,np->na", bw, x))
            return x - np.einsum("npa,na->np", basis, coef), coef
        coef = np.einsum("nab,nbk->nak", g_inv, np.einsum("npa,npk->nak", bw, x))
        return x - np.einsum("npa,nak->npk", basis, coef), coef

    def system(problem, arrays, geometry, rotations, solved, processing, jacobians=True, *_):
        # The lattice and variances flags after the Jacobians' are not used here
        n = len(problem.points)
        e = problem.experimental.reshape(n, -1).astype(np.float64)
        s0, geo, six = _intensity._model(
            problem, arrays, geometry, rotations, solved, processing, jacobians
        )
        basis = np.stack([np.ones_like(s0), s0], axis=2)
        if id(problem) not in weights:
            # Variance proportional to the model over its low-pass, scaled
            # per pattern to the residuals of an unweighted fit
            shape = problem.experimental.shape[1:]
            x, kept = processing._patterns(np.asarray(s0, np.float64).reshape((n, 1) + shape))
            low = kept[3]
            q = np.maximum((x / low if low is not None else x).reshape(n, -1), 1e-6)
            r0 = project(e, basis, np.ones_like(e))[0]
            var = q * ((r0**2).mean(axis=1) / q.mean(axis=1))[:, None]
            weights[id(problem)] = var
        var = weights[id(problem)]
        r, coef = project(e, basis, 1 / var)
        jg = jr = None
        if jacobians:
            gain = coef[:, 1][:, None, None]
            jg = project(np.moveaxis(geo, 1, 2).astype(np.float64), basis, 1 / var)[0] * gain
            jr = project(np.moveaxis(six[:, :3], 1, 2).astype(np.float64), basis, 1 / var)[0]
            jr = jr * gain
        return -r, jg, jr, var

    return system


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--variant", required=True, choices=["true-processing", "moving-lobe", "exact-weights"]
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--draws", type=int, default=12)
    args = p.parse_args(argv)
    print("command: benchmarks/experiments/draws_model_variants.py " + " ".join(sys.argv[1:]))
    if args.variant == "true-processing":
        _full_field._estimate_processing = _true_processing
    elif args.variant == "moving-lobe":
        _full_field._estimate_processing = _moving_lobe
    else:
        _full_field._intensity_system = _exact_weights()
    bench_draws.run("stripes", args.seed, 30.0, args.draws, False, "truth")


if __name__ == "__main__":
    main()
