"""One crystal's raise applied only to the PC components beyond the
adequacy limit, recombined without calibrating again.

Tried and left out (see README.md, "A smaller raise on one crystal"). The
parts of each map's standard errors (``one_crystal_parts.py``'s JSON
lines: the full field's own, the raise, the free-rotation prior) joined by
map with ``bench_uncertainty.py``'s records of the same maps (the DIC
stage's step in combined standard errors per component, ``dic_z``), and
combined under three rules: today's (every component raised where any
disagrees), only the components beyond ``ADEQUACY_LIMIT``, none.

Run from ``benchmarks/``::

    python experiments/raise_beyond_limit.py
"""

import json
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parents[1] / "results" / "uncertainty"
PARTS = [
    "one_crystal_parts_seeds01_bf2f3ff.jsonl",
    "one_crystal_parts_seed3_bf2f3ff.jsonl",
    "one_crystal_parts_domains_seeds24_0aa29cd.jsonl",
    "one_crystal_parts_single_seeds24_0aa29cd.jsonl",
]
RECORDS = {
    "domains": "one_crystal_domains_e0d6910.jsonl",
    "single": "one_crystal_single_32af98e.jsonl",
}
PC = ("pcx", "pcy", "pcz")


def _with_prior(se, prior, parts, weight=0.25):
    """``_systematic._with_prior`` at ``CRYSTAL_PRIOR_PARTS``."""
    w = weight / (max(parts - 1, 0) + weight)
    return np.sqrt(se**2 + w * max(prior**2 - se**2, 0.0))


def main() -> None:
    parts = {}
    for name in PARTS:
        for line in open(RESULTS / name):
            r = json.loads(line)
            if r.get("regions", 2) == 2 and "inflated" in r:
                parts[(r["kind"], r["cell"], r["seed"])] = r
    records = {}
    for kind, name in RECORDS.items():
        for line in open(RESULTS / name):
            r = json.loads(line)
            records[(kind, r["map"].split("-", 1)[1], r["seed"])] = r
    for kind in RECORDS:
        z = {"today": [], "beyond the limit only": [], "none": []}
        for key, p in parts.items():
            b = records.get(key)
            if key[0] != kind or b is None or not p["converged"]:
                continue
            for k in PC:
                beyond = not b["consistent"] and abs(b["dic_z"].get(k, 0.0)) > 3
                bases = (p["inflated"][k], p["inflated" if beyond else "raw"][k], p["raw"][k])
                for rule, base in zip(z, bases):
                    z[rule].append(p["err"][k] / _with_prior(base, p["prior"][k], p["parts"]))
        for rule, v in z.items():
            v = np.abs(v)
            print(
                f"{kind:8s} {rule:22s} {len(v) // 3} maps  RMS z {np.sqrt(np.mean(v**2)):.2f}  "
                f"within 1 {np.mean(v <= 1):.0%}  largest {v.max():.2f}"
            )


if __name__ == "__main__":
    main()
