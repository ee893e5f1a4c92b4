"""Time the default calibration of one realistic map in-process (the map
built once, the calibration run --repeats times after a warm-up): to set
one code version against another on the same machine, run it with each
checked out (``PYTHONPATH=<checkout>``) in turn.

Maps: ``poly`` (``bench_realistic.py``'s moderate case, seed 0, 121
points) and ``domains`` (``bench_envelope.py``'s base domain map, seed 0).

Usage::

    python benchmarks/experiments/time_default_path.py --map poly --repeats 3
"""

import argparse
import contextlib
import io
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/

import kikuchipy_geomdic  # noqa: E402
from kikuchipy_geomdic import refine_geometry_dic  # noqa: E402
from kikuchipy_geomdic.indexing.variants import variant_operators  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--map", choices=["poly", "domains"], default="poly")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    with contextlib.redirect_stdout(io.StringIO()):
        if args.map == "poly":
            from bench_realistic import realistic_map

            sm = realistic_map("moderate", 0)
            kw = dict(points=sm.xmap.size)
        else:
            from bench_envelope import PARAMETERS, envelope_map

            sm = envelope_map("domains", "base", 0)
            kw = dict(parameters=PARAMETERS, pseudo_symmetry_ops=variant_operators()[1:])
    times = []
    for i in range(args.repeats + 1):
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            res = refine_geometry_dic(*sm.start_inputs, show_progressbar=False, **kw)
        if i:
            times.append(time.perf_counter() - t0)
    err = max(abs(res.parameters[k] - sm.geometry.as_dict()[k]) for k in ("pcx", "pcy", "pcz"))
    median = sorted(times)[len(times) // 2]
    each = " ".join(f"{t:.2f}" for t in times)
    where = kikuchipy_geomdic.__file__
    print(f"{where}: {args.map} PC error {err:.2e}, s {each} (median {median:.2f})")


if __name__ == "__main__":
    main()
