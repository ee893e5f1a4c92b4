"""The parts of one crystal's standard errors, recorded per map so that
other rules of combining them can be compared without calibrating again:
the full field's own (statistical and the quadrants' systematic), the
raise to a third of the DIC stage's step where the two disagree
(``uncertainty._inflated``), and the prior of the free-rotation standard
errors with its weight (``_systematic._with_prior``).

Writes one JSON line per map (errors against the truth and every part);
``--recombine FILE...`` prints the RMS of error / sigma, the fractions
within 1 and 2 and the largest under each rule.

Usage::

    python benchmarks/experiments/one_crystal_parts.py --kinds single domains --seeds 0 1 \
        --out benchmarks/results/uncertainty/one_crystal_parts_s01.jsonl
    python benchmarks/experiments/one_crystal_parts.py \
        --recombine benchmarks/results/uncertainty/one_crystal_parts_*.jsonl
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/

import bench_envelope as be  # noqa: E402

from kikuchipy_geomdic.calibration import _full_field, _systematic  # noqa: E402
from kikuchipy_geomdic.calibration.solve import solve_joint  # noqa: E402
from kikuchipy_geomdic.indexing.variants import variant_operators  # noqa: E402

PC = ("pcx", "pcy", "pcz")
EDGES = ["base", "pc-low", "pc-high", "tilt-0", "tilt-10", "fov-50", "fov-2000", "px-60",
         "dose-30", "dose-500", "start-paper"]  # fmt: skip


def _with_regions(f, regions):
    def wrapped(*args, **kwargs):
        before = _systematic.REGIONS
        _systematic.REGIONS = (regions, regions)
        try:
            return f(*args, **kwargs)
        finally:
            _systematic.REGIONS = before

    return wrapped


def _block_jackknife(
    residual,
    jg,
    jr,
    weights,
    offsets,
    prior,
    common,
    region,
    geometry_prior=None,
    geometry_offsets=None,
    normal=None,
):
    """The geometry's spread over the solutions that leave one detector
    block out each (a jackknife over blocks, as over a polycrystal's
    grains), less the model's variance: the systematic part."""
    kw = dict(prior=prior, offsets=offsets, common=common, geometry_prior=geometry_prior,
              geometry_offsets=geometry_offsets)  # fmt: skip
    all_ = solve_joint(jg, jr, residual, weights, **kw)
    labels = np.unique(region)
    d = []
    for b in labels:
        sel = region != b
        upd = solve_joint(jg[:, sel], jr[:, sel], residual[:, sel], weights[:, sel], **kw)
        d.append(upd.delta)
    d = np.array(d)
    n = len(d)
    jack = (n - 1) / n * ((d - d.mean(axis=0)) ** 2).sum(axis=0)
    nu = n - 1
    return np.sqrt(np.clip(jack * nu / (nu - 2) - np.diag(all_.covariance), 0, None))


def _record(kinds, cells, seeds, out, regions, jackknife=False):
    # The full field's detector regions, n x n (the DIC stage keeps its
    # quadrants: its few ROIs leave smaller regions empty)
    _full_field.REGIONS = (regions, regions)
    for name in ("_region_errors", "_quadrants"):
        setattr(_full_field, name, _with_regions(getattr(_systematic, name), regions))
    if jackknife:
        _full_field._region_errors = _with_regions(_block_jackknife, regions)
    parts = {}
    inflated, with_prior = _full_field._inflated, _full_field._with_prior

    def rec_inflated(se, adequacy):
        parts["raw"] = {k: se.get(k) for k in PC}
        parts["systematic"] = {
            k: float(v) for k, v in (adequacy.get("systematic") or {}).items() if k in PC
        }
        res = inflated(se, adequacy)
        parts["inflated"] = {k: res.get(k) for k in PC}
        return res

    def rec_prior(se, prior, n):
        parts.setdefault("prior", {})
        parts["parts"] = n
        res = with_prior(se, prior, n)
        for k in PC:
            if parts.get("inflated", {}).get(k) == se:
                parts["prior"][k] = prior
        return res

    _full_field._inflated, _full_field._with_prior = rec_inflated, rec_prior
    with open(out, "a") as f:
        for kind in kinds:
            ops = variant_operators()[1:] if kind == "domains" else None
            for cell in cells:
                for seed in seeds:
                    with be._quiet():
                        sm = be.envelope_map(kind, cell, seed)
                    parts.clear()
                    r, seconds = be._calibrate(sm, "crystal", ops)
                    print(be._row(f"{kind:7} {cell:11} seed {seed}", "crystal", r, seconds),
                          flush=True)  # fmt: skip
                    if r.get("refused"):
                        continue
                    row = dict(kind=kind, cell=cell, seed=seed, regions=regions,
                               jackknife=jackknife, converged=bool(r["converged"]),
                               err={k: r["err"][k] for k in PC},
                               se={k: r["se"][k] for k in PC}, **parts)  # fmt: skip
                    f.write(json.dumps(row) + "\n")
                    f.flush()


RULES = {
    "today": lambda p, k: p["se"][k],
    "no raise": lambda p, k: _prior(p["raw"][k], p, k, 2.0),
    "no prior": lambda p, k: p["inflated"][k],
    "neither": lambda p, k: p["raw"][k],
}


def _prior(se, p, k, parts_weight):
    prior = p.get("prior", {}).get(k)
    if prior is None:
        return se
    nu = max(p["parts"] - 1, 0.0)
    weight = parts_weight / (nu + parts_weight)
    return float(np.sqrt(se**2 + weight * max(prior**2 - se**2, 0.0)))


def _recombine(files):
    rows = [json.loads(line) for f in files for line in open(f)]
    rows = [r for r in rows if r["converged"] and np.isfinite(r["se"]["pcx"])]
    # A map whose full field was skipped (the DIC stage's errors only) has
    # no parts to recombine
    skipped = [r for r in rows if "raw" not in r]
    rows = [r for r in rows if "raw" in r]
    print(f"{len(rows)} converged maps with a full field; {len(skipped)} without")
    rules = dict(RULES)
    for w in (0.25, 0.5, 1.0):
        rules[f"raise, prior parts {w}"] = lambda p, k, w=w: _prior(p["inflated"][k], p, k, w)
        rules[f"no raise, prior parts {w}"] = lambda p, k, w=w: _prior(p["raw"][k], p, k, w)
    for kind, regions, jk in sorted(
        {(r["kind"], r.get("regions", 2), r.get("jackknife", False)) for r in rows}
    ):
        sub = [r for r in rows if r["kind"] == kind and r.get("regions", 2) == regions
               and r.get("jackknife", False) == jk]  # fmt: skip
        how = "leave-one-out" if jk else "regions alone"
        print(f"\n{kind}, {regions} x {regions} regions, {how}: {len(sub)} maps")
        for name, rule in rules.items():
            z = np.array([abs(r["err"][k]) / rule(r, k) for r in sub for k in PC])
            worst = max(sub, key=lambda r: max(abs(r["err"][k]) / rule(r, k) for k in PC))
            print(
                f"  {name:26} RMS z {np.sqrt(np.mean(z**2)):.2f} | within 1 {np.mean(z <= 1):4.0%}"
                f" | within 2 {np.mean(z <= 2):4.0%} | beyond 3 {int(np.sum(z > 3))}"
                f" | largest {z.max():.2f} ({worst['cell']} seed {worst['seed']})"
            )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kinds", nargs="+", default=["single", "domains"])
    ap.add_argument("--cells", nargs="+", default=EDGES)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--out", default="one_crystal_parts.jsonl")
    ap.add_argument("--regions", type=int, default=2, help="the detector's regions, n x n")
    ap.add_argument("--jackknife", action="store_true", help="leave one block out each")
    ap.add_argument("--recombine", nargs="+")
    args = ap.parse_args()
    if args.recombine:
        _recombine(args.recombine)
    else:
        _record(args.kinds, args.cells, args.seeds, args.out, args.regions, args.jackknife)


if __name__ == "__main__":
    main()
